"""Drago et al.'s adaptive logarithmic mapping (2003), through OpenCV."""

from __future__ import annotations

from typing import Any

import numpy as np

from .opencv import opencv_tonemap


def tonemap_drago(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    saturation: float = 1.0,
    bias: float = 0.85,
) -> np.ndarray:
    """Drago et al.'s adaptive logarithmic mapping (OpenCV's ``TonemapDrago``).

    Luminance is mapped by a logarithm whose base varies from 2 in the darks to 10 in
    the highlights, interpolated by a bias power function [1]_. The radiance is first
    divided by the white level and clipped there, then OpenCV maps it and stretches
    the result to [0, 1].

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units. Mono input is mapped
        as grey RGB.
    exposure : float, optional
        Display-side exposure in stops (see :func:`tonemap_reinhard`).
    gamma : float, optional
        Display gamma applied to the result.
    white : float, optional
        Luminance level (radiance units) taken as white; estimated by
        :func:`robust_levels` when not given.
    saturation : float, optional
        Colour saturation exponent: 1 keeps the colour ratios, 0 gives grey.
    bias : float, optional
        Bias of the base interpolation, in (0, 1); 0.7 to 0.9 give the best results [1]_.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] F. Drago, K. Myszkowski, T. Annen and N. Chiba, "Adaptive logarithmic mapping
       for displaying high contrast scenes", Computer Graphics Forum 22(3)
       (Eurographics), 2003, pp. 419-426.
    """
    if not 0.0 < float(bias) < 1.0:
        raise ValueError(f"Drago bias must lie strictly between 0 and 1; got {bias}.")
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Drago saturation must lie in [0, 4]; got {saturation}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapDrago(1.0, float(saturation), float(bias))

    return opencv_tonemap(radiance, make, exposure=exposure, gamma=gamma, white=white)
