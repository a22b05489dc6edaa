"""Display encoding: display-linear values to the code values an image file stores.

The shared last steps of every tone-mapping operator of :mod:`stages.tonemap`: the
display-side checks of exposure and gamma, fitting colours into the display gamut
without changing their hue, and clipping to [0, 1] with the display gamma applied.
"""

from __future__ import annotations

import math

import numpy as np


def check_exposure_gamma(exposure: float, gamma: float) -> tuple[float, float]:
    exposure = float(exposure)
    gamma = float(gamma)
    if not math.isfinite(exposure) or abs(exposure) > 64:
        raise ValueError(f"Exposure must be a finite number of stops within +/-64; got {exposure}.")
    if not math.isfinite(gamma) or gamma <= 0.0:
        raise ValueError(f"Gamma must be a positive finite number; got {gamma}.")
    return exposure, gamma


def encode(display: np.ndarray, gamma: float, shape: tuple[int, ...]) -> np.ndarray:
    """Clip display-linear (H, W, C) to [0, 1], apply 1/gamma, restore the input's shape."""
    out = np.clip(display, 0.0, 1.0).astype(np.float32, copy=False)
    if gamma != 1.0:
        out = np.power(out, np.float32(1.0 / gamma), dtype=np.float32)
    return out.reshape(shape)


def fit_to_gamut(rgb: np.ndarray) -> np.ndarray:
    """Scale each pixel down so that its largest channel is at most 1 (keeps hue)."""
    peak = rgb.max(axis=2, keepdims=True)
    scale = np.where(peak > 1.0, 1.0 / np.maximum(peak, 1e-30), 1.0).astype(np.float32)
    return rgb * scale
