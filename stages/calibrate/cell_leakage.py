"""The LCoS's leakage, per VET pixel and per cell, from flat fields a lab records.

All cells closed over all open, per VET pixel, is the relay-blurred per-cell leakage
(:func:`leakage_per_pixel`). The per-cell map comes through the relay blur's
deconvolution (:func:`leakage_per_cell`), whose noise amplification the frames averaged
must beat: a recording split in two halves measures that noise
(:func:`leakage_from_halves`), and sets the weight of the prior. The ``emulated_*``
functions record the frames on the emulated rig's physics (its truth in ``RigParams``).
"""

from __future__ import annotations

import logging

import numpy as np

from ..optics import pixel_leakage, relay_blur
from ..physics import CellMap
from ..rig import RigParams

log = logging.getLogger("vet.calibrate")

#: Flat frames a calibration averages, each all closed and all open, for the per-cell
#: leakage: the relay blur's deconvolution amplifies the noise, and at the published
#: rig's cells (1.25 VET pixels) thousands are needed to bring every cell within 10%.
LEAKAGE_FRAMES = 16384


def leakage_per_pixel(closed_dn: np.ndarray, open_dn: np.ndarray) -> np.ndarray:
    """Per-pixel leakage from flat-field frames, all cells closed and all open, of the
    same exposure (DN, dark frame subtracted, (H, W[, C])): their ratio, (H, W) float32
    (the brightest channel's)."""
    c = np.asarray(closed_dn, np.float64)
    o = np.asarray(open_dn, np.float64)
    if c.ndim == 3:
        k = int(np.argmax(o.reshape(-1, o.shape[2]).mean(axis=0)))
        c, o = c[..., k], o[..., k]
    return (c / np.maximum(o, 1e-12)).astype(np.float32)


def _mean_exposure(lam_e: np.ndarray, rig: RigParams, rng: np.random.Generator, frames: int):
    """The mean DN of ``frames`` independent exposures of ``lam_e`` expected electrons,
    drawn from its distribution in one step: the shot noise as a Poisson draw of the
    total electrons, the read noise shrunk by ``sqrt(frames)``. Exact where no frame
    reaches the full well; each frame's rounding to a code (dithered by the noise) is
    left out."""
    e = rng.poisson(np.asarray(lam_e, np.float64) * frames) / frames
    np.minimum(e, rig.full_well_e, out=e)
    e += rig.read_noise_e / np.sqrt(frames) * rng.standard_normal(e.shape)
    return e * rig.gain_dn_per_e


def emulated_leakage_frames(
    rig: RigParams, frames: int = LEAKAGE_FRAMES, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Flat-field frames of the emulated VET camera, every cell closed (0.8 of the full
    well through the brightest leakage) and every cell open at an exposure 1/250 of it
    (gain-corrected so both are in the same exposure's DN): ``(closed, opened)``, each
    (2, H, W) float64, the means of the two halves of ``frames`` frames (a lab splits
    its recording so to measure the noise, :func:`leakage_from_halves`)."""
    h, w = rig.sensor_size[1], rig.sensor_size[0]
    cm = CellMap.for_rig(rig, (h, w))
    eps = relay_blur(pixel_leakage(rig, cm), rig.relay_blur_px)
    rng = np.random.default_rng(seed)
    rate = 0.8 * rig.full_well_e / float(eps.max())
    short = 1.0 / 250.0
    half = max(1, frames // 2)
    closed = np.stack([_mean_exposure(eps * rate, rig, rng, half) for _ in range(2)])
    flat = np.full((h, w), rate * short)
    opened = np.stack([_mean_exposure(flat, rig, rng, half) / short for _ in range(2)])
    return closed, opened


def leakage_from_halves(closed: np.ndarray, opened: np.ndarray) -> tuple[np.ndarray, float]:
    """The per-pixel leakage of two equal halves of a recording (``closed``, ``opened``:
    (2, H, W[, C]) mean DN of each half, dark-subtracted) and its noise: ``(ratio, sigma)``,
    the ratio of all frames' means ((H, W) float32, :func:`leakage_per_pixel`) and its
    standard error per pixel, half the robust spread (MAD) of the halves' difference."""
    ratio = leakage_per_pixel(closed.mean(axis=0), opened.mean(axis=0))
    diff = leakage_per_pixel(closed[0], opened[0]) - leakage_per_pixel(closed[1], opened[1])
    diff = diff[np.isfinite(diff)]
    sigma = float(np.median(np.abs(diff - np.median(diff)))) / 0.6745 / 2 if diff.size else 0.0
    return ratio, sigma


def _candidate_cells(rig: RigParams, shape: tuple[int, int], margin_px: float) -> np.ndarray:
    """The cells each VET pixel's centre could lie in, the geometry known within
    ``margin_px``: (H * W, 9) int64 (:func:`~stages.physics.cells_near`; ``cells_w *
    cells_h`` outside the LCoS), column 4 the centre's own."""
    from ..physics import cells_near

    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    return cells_near(np.asarray(rig.homography, np.float64), rig.lcos_cells, xs, ys, margin_px)


def _map_solve(
    label: np.ndarray, y: np.ndarray, noise: float, sigma: float, n_cells: int, iters: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The MAP values of the unknowns ``label`` assigns the pixels of ``y`` (labels below
    ``n_cells`` are cells, the rest a pixel's own): ``(unknowns, inverse, values)``."""
    from ..measure_grid import pcg

    h, w = y.shape
    unk, inv = np.unique(label, return_inverse=True)
    n = unk.size
    counts = np.bincount(inv, minlength=n).astype(np.float64)
    cells = unk < n_cells
    mean = float(np.median(y))

    def blur(img: np.ndarray) -> np.ndarray:
        return relay_blur(img.astype(np.float32), sigma).astype(np.float64)

    def means(img: np.ndarray) -> np.ndarray:
        return np.bincount(inv, weights=img.ravel(), minlength=n) / counts

    e0 = means(y)
    # the cells' spread s: the variance of their plain averages is s^2 times that of a
    # white unit pattern's through the same blur, plus the noise averaged into them
    white = np.random.default_rng(0).standard_normal(n)
    shrink = float(np.var(means(blur(white[inv].reshape(h, w)))[cells]))
    noise_in = float(np.mean(noise**2 / counts[cells]))
    spread2 = max((float(np.var(e0[cells])) - noise_in) / max(shrink, 1e-12), 1e-24)
    prior = max(noise, 1e-12) ** 2 / spread2

    def normal(e: np.ndarray) -> np.ndarray:
        img = blur(blur(e[inv].reshape(h, w)))  # the Gaussian is its own adjoint
        return np.bincount(inv, weights=img.ravel(), minlength=n) + prior * e

    b = np.bincount(inv, weights=blur(y).ravel(), minlength=n) + prior * mean
    return unk, inv, pcg(normal, b, counts + prior, e0, iters)


#: Margins (VET px) the per-cell solve tries in turn for the calibrated geometry's
#: uncertainty: the first whose fit explains the map to its noise is kept.
MARGINS_PX = (0.02, 0.05, 0.1, 0.2)


def leakage_per_cell(
    ratio: np.ndarray,
    rig: RigParams,
    noise: float,
    iters: int = 1000,
    margins_px: tuple[float, ...] = MARGINS_PX,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Per-cell leakage from a per-pixel map (:func:`leakage_per_pixel`) through the
    relay blur and the cell geometry of ``rig`` (its homography, as calibrated, and
    ``relay_blur_px``).

    The MAP estimate under Gaussian noise and prior: the values ``e`` minimising
    ``|blur(P e) - ratio|^2 / noise^2 + |e - m|^2 / s^2`` by conjugate gradients
    (``P``: the unknown each pixel sees; ``noise``: the ratio's standard error per pixel,
    :func:`leakage_from_halves`; ``m`` and ``s``: the cells' median and spread,
    estimated from the map). A pixel whose centre lies within a margin of a cell edge,
    where the calibrated geometry cannot tell its cell, first gets an unknown of its
    own; it is then given the candidate cell whose value its own is clearly nearest
    (under 0.3 of the distance to the next candidate; every candidate estimated) and the
    map solved again; the rest keep their own. The margins ``margins_px`` are tried in
    turn until the fit's mean squared residual is within the noise (``chi2`` at most
    1): a pixel given the wrong cell leaves a residual far above it.

    Returns
    -------
    cells : ndarray of int64
        Row-major indices of the cells estimated (some pixel is theirs).
    leak : ndarray of float32
        Their leakage.
    layer : ndarray of shape (H, W), float32
        Each pixel's leakage: its cell's, or its own; within [0, 0.999], NaN outside the
        LCoS (``Calibration.cell_leakage``).
    fit : dict
        ``margin_px`` kept and its ``chi2`` (mean squared residual over noise squared).
    """
    best = None
    for margin in margins_px:
        log.info("calibrate: per-cell leakage through the relay blur (margin %g px)", margin)
        got = _solve_at_margin(np.asarray(ratio, np.float64), rig, noise, iters, margin)
        if best is None or got[3]["chi2"] < best[3]["chi2"]:
            best = got
        if got[3]["chi2"] <= 1.0:
            return got
    return best


def _solve_at_margin(
    y: np.ndarray, rig: RigParams, noise: float, iters: int, margin_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """:func:`leakage_per_cell` at one margin."""
    h, w = y.shape
    n_cells = rig.lcos_cells[0] * rig.lcos_cells[1]
    cand = _candidate_cells(rig, (h, w), margin_px)
    label = cand[:, 4].copy()
    amb = np.flatnonzero((cand != cand[:, 4:5]).any(axis=1))
    label[amb] = n_cells + 1 + np.arange(amb.size)
    sigma = rig.relay_blur_px
    unk, inv, e = _map_solve(label, y, noise, sigma, n_cells, iters)
    if amb.size:
        value = np.full(n_cells + 1, np.nan)
        estimated = unk < n_cells
        value[unk[estimated]] = e[estimated]
        own = e[inv[amb]]
        dist = np.abs(value[np.minimum(cand[amb], n_cells)] - own[:, None])
        dist[np.isnan(dist)] = np.inf
        k = np.argmin(dist, axis=1)
        best = cand[amb, k]
        nearest = dist[np.arange(amb.size), k]
        runner_up = np.where(cand[amb] != best[:, None], dist, np.inf).min(axis=1)
        sure = (nearest < 0.3 * runner_up) & np.isfinite(runner_up)  # (every one estimated)
        label[amb[sure]] = best[sure]
        unk, inv, e = _map_solve(label, y, noise, sigma, n_cells, iters)
    per_pixel = e[inv].reshape(h, w)
    resid = relay_blur(per_pixel.astype(np.float32), sigma).astype(np.float64) - y
    chi2 = float(np.mean(resid**2)) / max(noise, 1e-12) ** 2
    layer = np.clip(per_pixel, 0.0, 0.999).astype(np.float32)
    layer[(cand[:, 4] >= n_cells).reshape(h, w)] = np.nan
    cells = unk < n_cells
    return unk[cells], e[cells].astype(np.float32), layer, {"margin_px": margin_px, "chi2": chi2}


def calibrate_cell_leakage(
    truth: RigParams,
    known: RigParams,
    frames: int = LEAKAGE_FRAMES,
    seed: int = 0,
    margins_px: tuple[float, ...] = MARGINS_PX,
) -> tuple[np.ndarray, dict]:
    """The per-cell leakage of the emulated rig ``truth`` from ``frames`` flat frames
    each all closed and all open (:func:`emulated_leakage_frames`), solved through the
    geometry the calibration found (``known``: its homography and relay blur; the
    margins for its uncertainty ``margins_px``, ``(0,)`` when it is the truth's).
    Returns the layer (:func:`leakage_per_cell`) and, against the truth, the relative
    errors over the cells estimated (``cell_leakage_median_rel_err``,
    ``cell_leakage_p99_rel_err``, ``cell_leakage_max_rel_err``) with the fit's
    ``cell_leakage_margin_px`` and ``cell_leakage_chi2`` and the map's standard error
    ``cell_leakage_noise``."""
    from ..optics import leakage_map

    ratio, noise = leakage_from_halves(*emulated_leakage_frames(truth, frames, seed))
    cells, leak, layer, fit = leakage_per_cell(ratio, known, noise, margins_px=margins_px)
    err = np.abs(leak / leakage_map(truth).ravel()[cells] - 1)
    errors = {
        "cell_leakage_median_rel_err": float(np.median(err)),
        "cell_leakage_p99_rel_err": float(np.percentile(err, 99)),
        "cell_leakage_max_rel_err": float(err.max()),
        "cell_leakage_margin_px": fit["margin_px"],
        "cell_leakage_chi2": fit["chi2"],
        "cell_leakage_noise": noise,
    }
    return layer, errors


def _sweep(size: tuple[int, int], counts: tuple[int, ...] = (16, 256, 1024, 4096, 16384)) -> None:
    """Print the per-cell errors of the emulated realistic rig of ``size`` against the
    number of flat frames, the truth's geometry given (exact: no pixel's cell in doubt)."""
    from ..optics import rig_profile

    rig = rig_profile("realistic", size)
    print(f"realistic rig {size[0]}x{size[1]}, {rig.lcos_cells[0]}x{rig.lcos_cells[1]} cells")
    print(f"{'frames':>7s} {'noise':>9s} {'median':>7s} {'p99':>7s} {'max':>7s}")
    for n in counts:
        _, err = calibrate_cell_leakage(rig, rig, n, margins_px=(0.0,))
        print(
            f"{n:7d} {err['cell_leakage_noise']:9.3g} {err['cell_leakage_median_rel_err']:7.2%}"
            f" {err['cell_leakage_p99_rel_err']:7.2%} {err['cell_leakage_max_rel_err']:7.2%}",
            flush=True,
        )


if __name__ == "__main__":
    import sys

    wh = sys.argv[1] if len(sys.argv) > 1 else "320x240"
    _sweep(tuple(int(v) for v in wh.split("x")))
