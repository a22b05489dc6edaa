"""Reinhard and Devlin's photoreceptor tone mapping (2005), through OpenCV."""

from __future__ import annotations

from typing import Any

import numpy as np

from .opencv import opencv_tonemap


def tonemap_reinhard(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    intensity: float = 0.0,
    light_adapt: float = 0.0,
    color_adapt: float = 0.0,
) -> np.ndarray:
    """Reinhard and Devlin's photoreceptor tone mapping (OpenCV's ``TonemapReinhard``).

    Each channel is compressed as ``c / (c + (e^{-f} a)^m)`` where the adaptation level
    ``a`` blends the pixel's own and the image's mean luminance and colour, and the
    contrast ``m`` follows from the image's log-luminance key [1]_. The radiance is first
    divided by the white level and clipped there (so the result does not depend on its
    units), then OpenCV maps it and stretches the result to [0, 1].

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units. Mono input is mapped
        as grey RGB.
    exposure : float, optional
        Display-side exposure in stops: the operator's display-linear output is
        multiplied by ``2**exposure`` and clipped to 1 before the gamma is applied.
    gamma : float, optional
        Display gamma applied to the result.
    white : float, optional
        Luminance level (radiance units) taken as white; brighter pixels are clipped.
        Estimated by :func:`robust_levels` when not given.
    intensity : float, optional
        Overall intensity ``f``, in [-8, 8] (OpenCV's ``intensity``).
    light_adapt : float, optional
        Light adaptation in [0, 1]: 0 (default, as in OpenCV's HDR tutorial) adapts to
        the image's mean luminance, 1 (OpenCV's default) to each pixel's own, which
        flattens dark-keyed scenes to a uniform grey.
    color_adapt : float, optional
        Chromatic adaptation in [0, 1]: 1 adapts each channel separately, 0 does not.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] E. Reinhard and K. Devlin, "Dynamic range reduction inspired by photoreceptor
       physiology", IEEE Transactions on Visualization and Computer Graphics 11(1),
       2005, pp. 13-24.
    """
    if not -8.0 <= float(intensity) <= 8.0:
        raise ValueError(f"Reinhard intensity must lie in [-8, 8]; got {intensity}.")
    for name, value in (("light_adapt", light_adapt), ("color_adapt", color_adapt)):
        if not 0.0 <= float(value) <= 1.0:
            raise ValueError(f"Reinhard {name} must lie in [0, 1]; got {value}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapReinhard(
            1.0, float(intensity), float(light_adapt), float(color_adapt)
        )

    return opencv_tonemap(radiance, make, exposure=exposure, gamma=gamma, white=white)
