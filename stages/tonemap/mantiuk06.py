"""Mantiuk et al.'s contrast-domain tone mapping (2006), through OpenCV."""

from __future__ import annotations

from typing import Any

import numpy as np

from .opencv import opencv_tonemap

#: Percentile of the output luminance of Mantiuk's operator taken as white.
MANTIUK_WHITE_PERCENTILE = 99.9


def tonemap_mantiuk(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    scale: float = 0.7,
    saturation: float = 1.0,
    white_percentile: float = MANTIUK_WHITE_PERCENTILE,
) -> np.ndarray:
    """Mantiuk et al.'s contrast-domain tone mapping (OpenCV's ``TonemapMantiuk``).

    Log-luminance gradients on a Gaussian pyramid are converted to contrast, scaled by
    ``scale`` and the image is rebuilt by solving the resulting optimisation with
    conjugate gradients [1]_. This is a local operator: it keeps the order of
    luminances within smooth regions but not necessarily across the image. The radiance
    is first divided by the white level and clipped there. The result keeps far more
    range than a display shows (``scale`` times the input's, in log units), so rather
    than stretching its extremes to [0, 1] as OpenCV does, the ``white_percentile``-th
    percentile of its luminance is taken as white and brighter pixels clip. Images
    smaller than 2x2 are edge-padded for OpenCV and cropped back.

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
    scale : float, optional
        Contrast scale factor, in (0, 1]; 0.6 to 0.9 are typical.
    saturation : float, optional
        Colour saturation exponent: 1 keeps the colour ratios, 0 gives grey.
    white_percentile : float, optional
        Percentile (in (50, 100]) of the output luminance shown as white; 100 keeps
        OpenCV's own stretch.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] R. Mantiuk, K. Myszkowski and H.-P. Seidel, "A perceptual framework for
       contrast processing of high dynamic range images", ACM Transactions on Applied
       Perception 3(3), 2006, pp. 286-308.
    """
    if not 0.0 < float(scale) <= 1.0:
        raise ValueError(f"Mantiuk scale must lie in (0, 1]; got {scale}.")
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Mantiuk saturation must lie in [0, 4]; got {saturation}.")
    if not 50.0 < float(white_percentile) <= 100.0:
        raise ValueError(f"Mantiuk white_percentile must lie in (50, 100]; got {white_percentile}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapMantiuk(1.0, float(scale), float(saturation))

    return opencv_tonemap(
        radiance,
        make,
        exposure=exposure,
        gamma=gamma,
        white=white,
        min_size=2,
        output_percentile=float(white_percentile),
    )
