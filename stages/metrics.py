"""Quality measures of DESIGN.md §6: errors in stops, split by region."""

from __future__ import annotations

from typing import Any

import numpy as np

from .scenes import luminance


def stops_error(
    estimate: np.ndarray,
    truth: np.ndarray,
    exposure_time: np.ndarray | None = None,
    frame_s: float | None = None,
    border: int = 8,
    floor_frac: float = 1e-4,
) -> dict[str, Any]:
    """Error |log2(estimate / truth)| on luminance, over valid pixels, with statistics.

    Parameters
    ----------
    estimate, truth : ndarray of shape (H, W, C)
        Linear radiance in the same units.
    exposure_time : ndarray of shape (H, W), optional
        The capture's T; splits pixels into ``bright`` (closed before the frame ended)
        and ``dark`` (exposed the whole frame).
    frame_s : float, optional
        Frame length for the split.
    border : int
        Pixels excluded at each image edge.
    floor_frac : float
        Pixels whose true luminance is below ``floor_frac`` x the 99.9th percentile are
        excluded (they are dominated by noise by design).

    Returns
    -------
    dict with ``all``, ``bright``, ``dark`` entries, each ``{median, p99, rms, n}`` in
    stops, plus ``scale`` (2 ** median signed log2 ratio: the global scale error) and
    ``nonfinite`` (count of NaN/inf estimates inside the region).
    """
    if estimate.shape != truth.shape:
        raise ValueError(f"estimate {estimate.shape} and truth {truth.shape} differ in shape")
    le, lt = luminance(estimate.astype(np.float32)), luminance(truth.astype(np.float32))
    h, w = lt.shape
    region = np.zeros((h, w), bool)
    region[border : h - border, border : w - border] = True
    floor = floor_frac * float(np.percentile(lt, 99.9))
    region &= lt > floor
    nonfinite = int((~np.isfinite(le) & region).sum())
    valid = region & np.isfinite(le) & (le > 0)
    signed = np.zeros((h, w), np.float64)
    signed[valid] = np.log2(le[valid].astype(np.float64) / lt[valid])
    err = np.abs(signed)
    # Non-positive estimates inside the region count as infinitely wrong.
    bad = region & ~valid
    out: dict[str, Any] = {"nonfinite": nonfinite, "nonpositive": int(bad.sum()) - nonfinite}
    groups = {"all": region}
    if exposure_time is not None and frame_s is not None:
        dark = exposure_time >= np.float32(frame_s) * (1 - 1e-6)
        groups["bright"] = region & ~dark
        groups["dark"] = region & dark
    for name, g in groups.items():
        e = np.where(bad[g], np.inf, err[g])
        if e.size == 0:
            out[name] = {"median": float("nan"), "p99": float("nan"), "rms": float("nan"), "n": 0}
            continue
        out[name] = {
            "median": float(np.median(e)),
            "p99": float(np.percentile(e, 99)),
            "rms": float(np.sqrt(np.mean(np.square(e)))),
            "n": int(e.size),
        }
    out["scale"] = float(2.0 ** np.median(signed[valid])) if valid.any() else float("nan")
    return out
