"""Quality measures of DESIGN.md §6: errors in stops, split by region."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from .scenes import luminance

if TYPE_CHECKING:
    from .rig import RigParams

#: Pixels left out at each image edge (where a moving scene enters and leaves the frame).
BORDER_PX = 8


def measurable_floor(rig: RigParams, radiance_scale: float) -> float:
    """Scene level below which a rig cannot measure a pixel at all (truth units).

    The level at which a whole-frame exposure of the VET sensor (the longest any method
    gets) gathers as many signal electrons ``S`` as its own noise:
    ``S = sqrt(S + read_noise^2 + dark_current * frame)``; 6.4 e- with DESIGN.md's
    defaults. Below it every method reads noise, so the error in stops measures nothing
    but the noise; above it the pixels are scored, however dark.

    ``radiance_scale``: electrons per second at the VET sensor per scene unit.
    """
    var0 = rig.read_noise_e**2 + rig.dark_current_e_s * rig.frame_s
    s_min = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * var0))
    return float(s_min / (radiance_scale * rig.frame_s))


def stops_error(
    estimate: np.ndarray,
    truth: np.ndarray,
    exposure_time: np.ndarray | None = None,
    frame_s: float | None = None,
    border: int = BORDER_PX,
    floor_frac: float = 1e-4,
    floor: float | None = None,
    mask: np.ndarray | None = None,
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
        Without ``floor``: pixels whose true luminance is below ``floor_frac`` x the
        99.9th percentile are excluded (a scale-free guard against black pixels).
    floor : float, optional
        Absolute floor on the true luminance (truth units); pixels at or below it are
        excluded. :func:`measurable_floor` gives the one of a rig: where even a
        whole-frame exposure gathers less signal than noise.
    mask : ndarray of shape (H, W), bool, optional
        Score only these pixels (within the border and above the floor).

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
    if mask is not None:
        if mask.shape != (h, w):
            raise ValueError(f"mask {mask.shape} and image {(h, w)} differ in shape")
        region &= mask
    if floor is None:
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
