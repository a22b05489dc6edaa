"""Sensor models fitted from flat and dark frames: bias, dark current, leakage.

- **Dark frames** (no light) at two or more exposure times: per pixel, a straight line
  DN = bias + g * d * t gives the bias (black-level residual, DN) and the dark current
  d (electrons/s; g the conversion gain in DN per electron).
- **Leakage**: a flat field with the LCoS all open and all closed, each dark-subtracted
  and divided by its exposure time; the ratio per pixel is the closed cells'
  transmittance.
"""

from __future__ import annotations

import numpy as np


def dark_model(
    dark: dict[float, np.ndarray], gain_dn_per_e: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel bias and dark current from dark frames at two or more exposure times.

    Parameters
    ----------
    dark : dict of float -> ndarray of shape (H, W)
        Exposure time (s) -> mean dark frame at that exposure (DN).
    gain_dn_per_e : float
        Conversion gain, DN per electron.

    Returns
    -------
    bias_dn : ndarray of shape (H, W), float32
        Intercept at zero exposure, DN (the black level as delivered: about 0 for
        black-subtracted frames, the pedestal for raw ones).
    dark_current_e_s : ndarray of shape (H, W), float32
        Slope divided by the gain, electrons per second.
    """
    times = np.array(sorted(dark), dtype=np.float64)
    if times.size < 2 or times[-1] - times[0] <= 0:
        raise ValueError("dark current needs dark frames at two or more different exposure times.")
    tm = times.mean()
    denom = float(np.sum((times - tm) ** 2))
    mean_img = sum(np.asarray(dark[t], np.float64) for t in times) / times.size
    slope = sum((t - tm) * np.asarray(dark[t], np.float64) for t in times) / denom
    bias = mean_img - slope * tm
    return bias.astype(np.float32), (slope / gain_dn_per_e).astype(np.float32)


def signal_rate(
    frame: np.ndarray, exposure_s: float, bias_dn: np.ndarray | float, dark_dn_s: np.ndarray | float
) -> np.ndarray:
    """Dark-subtracted signal per second, DN/s: ``(frame - bias - dark * t) / t``."""
    return (
        (np.asarray(frame, np.float64) - bias_dn - np.asarray(dark_dn_s) * exposure_s) / exposure_s
    ).astype(np.float32)


def leakage_map(open_rate: np.ndarray, closed_rate: np.ndarray, min_rate: float) -> np.ndarray:
    """Closed-cell transmittance per pixel: closed over open signal rate.

    Parameters
    ----------
    open_rate, closed_rate : ndarray of shape (H, W)
        Dark-subtracted signal rates (DN/s) with the LCoS all open / all closed.
    min_rate : float
        Pixels whose open rate is below this (DN/s) get NaN (too dark to tell).

    Returns
    -------
    ndarray of shape (H, W), float32
    """
    ok = open_rate > min_rate
    out = np.full(open_rate.shape, np.nan, np.float32)
    out[ok] = closed_rate[ok] / open_rate[ok]
    return out
