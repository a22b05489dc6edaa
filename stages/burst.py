"""Burst merge: the HDR+ align-and-merge of a capture's measuring subframes alone.

A comparison method every user can run (``vet deblur --method burst``, ``vet evaluate``
row ``burst-merge``): what an off-the-shelf burst
pipeline makes of the rig's own short, sharp, noisy measuring subframes, ignoring the VET
image. It follows Hasinoff et al. (2016):

Alignment (§4). A tile whose best match is not clearly better than its average match
(:data:`CONFIDENT_COST`: no texture above the noise, a dark or flat tile) keeps the
displacement the coarser level proposed, and at the coarsest level the median of the
confident tiles' (departures from the paper, which aligns bright, well-exposed frames). The reference is the first frame (the scene nearest t = 0, which vet's
outputs show). Each frame is aligned to it tile by tile, coarse to fine, on a Gaussian
pyramid of the frames' channel mean (:data:`PYRAMID_LEVELS` levels, each half the size
of the one below): at each level every :data:`TILE` x :data:`TILE` tile (stride
``TILE / 2``) searches :data:`SEARCH` pixels around the displacement the coarser level
proposes (the best of its own and its neighbours' upsampled proposals), minimising the
sum of squared differences at the coarse levels and of absolute differences at the
finest, in whole pixels.

Merge (§5). Overlapping :data:`TILE` x :data:`TILE` tiles (stride ``TILE / 2``, a raised
cosine window whose shifted copies sum to one) are merged in the 2-D frequency domain,
each alternate frame's tile ``T_z`` pulled toward the reference's ``T_0`` by the
pairwise robust Wiener shrinkage ``A_z = |D_z|^2 / (|D_z|^2 + c sigma^2)`` with ``D_z =
T_0 - T_z``: ``T~ = mean_z (T_z + A_z D_z)``, so a frequency that differs from the
reference by no more than the noise is averaged and one that differs more (an alignment
failure, an occlusion) keeps the reference. A measuring subframe holds a few electrons
in the dark, so one frame is a poor reference there: a second pass merges every frame
(the first too) again, pulled toward the first pass's merge instead (a reference
``sqrt(N)`` times less noisy), with the noise of that merge's level. ``sigma^2`` is the tile's noise variance per
frequency from the sensor's noise model (shot noise at the reference tile's mean plus a
full read noise per subframe; Poisson-Gaussian, no estimate from the data). Then the
paper's spatial denoising: each merged frequency is shrunk by ``|T~|^2 / (|T~|^2 +
c_s sigma^2 / N)`` (``N`` frames merged), all but the tile's mean (its zero frequency:
shrinking that would bias dark tiles towards black). Tiles are overlap-added back.

Units: frames in DN (black level subtracted) at the measurement sensor, which receives
``rig.measure_fraction`` of the VET sensor's light; the result is the rate in electrons
per second at the VET sensor, as hdr-static's.

References
----------
S. W. Hasinoff, D. Sharlet, R. Geiss, A. Adams, J. T. Barron, F. Kainz, J. Chen,
M. Levoy, "Burst photography for high dynamic range and low-light imaging on mobile
cameras", ACM Trans. Graphics 35(6), 192, 2016.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import scipy.fft

from .formats.capture import Capture, provenance_entry
from .formats.hdr import HDRImage
from .rig import RigParams

#: Tile side (merge and alignment), pixels; tiles overlap by half.
TILE = 16
#: Search radius per pyramid level, pixels of that level.
SEARCH = 4
#: Pyramid levels for the alignment (each half the size of the one below).
PYRAMID_LEVELS = 4
#: Temporal robustness (the paper's c) and spatial denoising strengths.
C_TEMPORAL = 8.0
C_SPATIAL = 1.0
#: A tile's alignment counts when its best cost is below this share of its mean cost.
CONFIDENT_COST = 0.7


def _window(n: int) -> np.ndarray:
    """Raised cosine whose copies shifted by ``n / 2`` sum to one, (n, n)."""
    x = np.arange(n)
    w1 = 0.5 - 0.5 * np.cos(2 * np.pi * (x + 0.5) / n)
    return np.outer(w1, w1)


def _pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    import cv2

    out = [img]
    for _ in range(levels - 1):
        if min(out[-1].shape) < 2 * TILE:
            break
        out.append(cv2.pyrDown(out[-1]))
    return out


def _tile_sums(cost: np.ndarray, n_ty: int, n_tx: int, step: int) -> np.ndarray:
    """Sum of ``cost`` (H, W) over each tile of side ``2 step`` at stride ``step``."""
    import cv2

    h, w = cost.shape
    ii = cv2.integral(np.ascontiguousarray(cost, np.float32), sdepth=cv2.CV_64F)
    y0 = np.arange(n_ty) * step
    x0 = np.arange(n_tx) * step
    y1 = np.minimum(y0 + 2 * step, h)
    x1 = np.minimum(x0 + 2 * step, w)
    return ii[np.ix_(y1, x1)] - ii[np.ix_(y0, x1)] - ii[np.ix_(y1, x0)] + ii[np.ix_(y0, x0)]


def _pull(dz: np.ndarray, sigma2: np.ndarray) -> np.ndarray:
    """``A_z D_z``: the pairwise robust Wiener shrinkage of §5 (``A_z = |D_z|^2 /
    (|D_z|^2 + c sigma^2)``) applied to the difference ``D_z`` from the reference."""
    mag = dz.real**2 + dz.imag**2
    return dz * (mag / (mag + C_TEMPORAL * sigma2))


def align(ref_pyr: list[np.ndarray], alt: np.ndarray) -> np.ndarray:
    """Per-tile whole-pixel displacement of ``alt`` onto the reference (§4): (n_ty, n_tx, 2)
    as ``(dy, dx)``: the tile at ``y`` of the reference is at ``y + d`` in ``alt``.

    Each level searches :data:`SEARCH` pixels (1 at the finest, as the paper) around the
    candidates the coarser level proposes; the work is one whole-image difference per
    distinct shift that some tile tries, so a smooth motion (few distinct candidates) is
    cheap.
    """
    alt_pyr = _pyramid(alt, len(ref_pyr))
    disp = None
    step = TILE // 2
    for lev in range(len(ref_pyr) - 1, -1, -1):
        ref, cur = ref_pyr[lev], alt_pyr[lev]
        h, w = ref.shape
        n_ty, n_tx = max(1, (h - TILE) // step + 1), max(1, (w - TILE) // step + 1)
        if disp is None:
            cands = [np.zeros((n_ty, n_tx, 2), np.int64)]
        else:
            # The coarser proposal upsampled; each tile also tries its neighbours' (§4).
            up = np.repeat(np.repeat(disp * 2, 2, axis=0), 2, axis=1)
            pad = ((0, max(0, n_ty - up.shape[0])), (0, max(0, n_tx - up.shape[1])), (0, 0))
            up = np.pad(up, pad, mode="edge")[:n_ty, :n_tx]
            cands = [up, np.roll(up, 1, axis=0), np.roll(up, 1, axis=1)]
        radius = 1 if lev == 0 else SEARCH
        best = np.full((n_ty, n_tx), np.inf)
        best_d = np.zeros((n_ty, n_tx, 2), np.int64)
        cost_sum = np.zeros((n_ty, n_tx))
        cost_n = np.zeros((n_ty, n_tx))
        offsets = np.unique(np.concatenate([c.reshape(-1, 2) for c in cands]), axis=0)
        window = np.array(
            [(sy, sx) for sy in range(-radius, radius + 1) for sx in range(-radius, radius + 1)]
        )
        # Every distinct shift once (neighbouring candidates' windows overlap): its cost
        # counts for the tiles that have a candidate within ``radius`` of it.
        shifts = np.unique((offsets[:, None, :] + window[None]).reshape(-1, 2), axis=0)
        margin = int(np.abs(shifts).max())
        cur_pad = np.pad(cur, margin, mode="edge")
        for dy, dx in shifts:
            allowed = np.zeros((n_ty, n_tx), bool)
            for c in cands:
                allowed |= (np.abs(c[..., 0] - dy) <= radius) & (np.abs(c[..., 1] - dx) <= radius)
            if not allowed.any():
                continue
            y0, x0 = margin + int(dy), margin + int(dx)
            diff = ref - cur_pad[y0 : y0 + h, x0 : x0 + w]
            cost = _tile_sums(np.abs(diff) if lev == 0 else diff * diff, n_ty, n_tx, step)
            better = allowed & (cost < best)
            best[better] = cost[better]
            best_d[better] = (dy, dx)
            cost_sum += np.where(allowed, cost, 0.0)
            cost_n += allowed
        # A tile whose best match is not clearly better than its average one holds no
        # texture above the noise: it keeps the coarser level's proposal, and at the
        # coarsest level the median displacement of the confident tiles.
        confident = best < CONFIDENT_COST * cost_sum / np.maximum(cost_n, 1)
        if disp is None:
            fallback = np.zeros_like(best_d)
            if confident.any():
                fallback[:] = np.median(best_d[confident], axis=0).round().astype(np.int64)
        else:
            fallback = cands[0]
        disp = np.where(confident[..., None], best_d, fallback)
    return disp


def burst_merge(
    frames: np.ndarray,
    times: np.ndarray,
    rig: RigParams,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Align and merge measuring frames (see the module docstring).

    Parameters
    ----------
    frames : ndarray of shape (K, H, W, C)
        DN, black level subtracted; any numeric type. Each may sum several subframes.
    times : ndarray of shape (K, 2)
        ``[start, end)`` of each frame, seconds.
    rig : RigParams
    progress : callable, optional
        ``progress(done, total)`` per frame.

    Returns
    -------
    rate : ndarray of shape (H, W, C), float32
        Electrons per second at the VET sensor.
    info : dict
        ``frames`` merged and ``mean_shrink`` (of the second pass: ``|A_z D_z|`` summed
        over ``|D_z|`` summed, averaged over frames; 0 all averaged, 1 all rejected).
    """
    k_n, h, w, c = frames.shape
    g = float(rig.gain_dn_per_e)
    dur = np.diff(np.asarray(times, np.float64), axis=1)[:, 0]
    n_sub = np.maximum(np.rint(dur / rig.subframe_s), 1)
    # Pad by half a tile all round (so that every pixel is under two tiles per axis and
    # the windows sum to one) and to whole tiles; cut back at the end.
    step = TILE // 2
    hp = int(np.ceil((h + step) / step)) * step + step
    wp = int(np.ceil((w + step) / step)) * step + step

    def frame(k: int) -> np.ndarray:
        f = np.asarray(frames[k], np.float32)
        return np.pad(f, ((step, hp - h - step), (step, wp - w - step), (0, 0)), mode="edge")

    ref = frame(0)
    ref_pyr = _pyramid(ref.mean(axis=2), PYRAMID_LEVELS)
    n_ty, n_tx = (hp - TILE) // step + 1, (wp - TILE) // step + 1
    ty = np.arange(n_ty) * step
    tx = np.arange(n_tx) * step
    yy = ty[:, None, None, None] + np.arange(TILE)[None, None, :, None]  # (ty,1,T,1)
    xx = tx[None, :, None, None] + np.arange(TILE)[None, None, None, :]  # (1,tx,1,T)
    win = _window(TILE).astype(np.float32)

    def tiles(img: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
        ys, xs = yy, xx
        if d is not None:
            ys = np.clip(yy + d[:, :, 0][:, :, None, None], 0, hp - 1)
            xs = np.clip(xx + d[:, :, 1][:, :, None, None], 0, wp - 1)
        t = img[ys, xs]  # (ty, tx, T, T, C)
        # (single precision throughout: scipy's FFT keeps float32 as complex64)
        return scipy.fft.rfft2(t * win[None, None, :, :, None], axes=(2, 3))

    t0 = tiles(ref)
    # Noise variance per frequency of a tile: per-pixel variance (shot at the reference
    # tile's mean + a read noise per subframe + quantisation, DN^2) times sum(w^2).
    mean_dn = np.maximum(ref[yy, xx].mean(axis=(2, 3)), 0)  # (ty, tx, C)
    var_px = g * mean_dn + n_sub[0] * (g * float(rig.read_noise_e)) ** 2 + 1.0 / 12
    sigma2 = (var_px * float(np.sum(win**2)))[:, :, None, None, :]
    acc = t0.copy()
    disps: list[np.ndarray | None] = [None]
    for k in range(1, k_n):
        cur = frame(k)
        d = align(ref_pyr, cur.mean(axis=2))
        disps.append(d)
        tz = tiles(cur, d)
        acc += tz + _pull(t0 - tz, sigma2)
        if progress:
            progress(k, 2 * k_n - 1)
    # Second pass: every frame (the first too) pulled toward the first pass's merge, a
    # reference far less noisy than one frame, with the noise of its own mean level.
    ref_merge = acc / k_n
    mean_dn = np.maximum(ref_merge[:, :, 0, 0, :].real / float(win.sum()), 0)
    var_px = g * mean_dn + n_sub[0] * (g * float(rig.read_noise_e)) ** 2 + 1.0 / 12
    sigma2 = (var_px * float(np.sum(win**2)))[:, :, None, None, :]
    acc = np.zeros_like(t0)
    shrink = 0.0
    for k in range(k_n):
        tz = tiles(frame(k), disps[k])
        a_dz = _pull(ref_merge - tz, sigma2)
        acc += tz + a_dz
        shrink += float(np.abs(a_dz).sum() / max(float(np.abs(ref_merge - tz).sum()), 1e-30))
        if progress:
            progress(k_n + k, 2 * k_n - 1)
    shrink /= k_n
    merged = acc / k_n
    mag = merged.real**2 + merged.imag**2
    shrink_s = mag / (mag + C_SPATIAL * sigma2 / k_n)
    shrink_s[:, :, 0, 0] = 1.0  # a tile's mean is kept: shrinking it would bias the dark
    merged *= shrink_s
    back = scipy.fft.irfft2(merged, s=(TILE, TILE), axes=(2, 3))  # windowed tiles
    # Overlap-add: tile (i, j)'s quadrant (a, b) lands on block (i + a, j + b) of a grid
    # of half-tile blocks (the windows' shifted copies sum to one).
    blocks = np.zeros((n_ty + 1, n_tx + 1, step, step, c))
    for a in (0, 1):
        for b in (0, 1):
            blocks[a : a + n_ty, b : b + n_tx] += back[
                :, :, a * step : (a + 1) * step, b * step : (b + 1) * step
            ]
    out = blocks.transpose(0, 2, 1, 3, 4).reshape((n_ty + 1) * step, (n_tx + 1) * step, c)
    mean_dn = out[step : step + h, step : step + w]
    tau = float(dur.mean())
    e = mean_dn / g - float(rig.dark_current_e_s) * tau
    rate = e / (tau * float(rig.measure_fraction))
    info = {"frames": int(k_n), "mean_shrink": round(shrink, 4)}
    return rate.astype(np.float32), info


def burst_hdr(cap: Capture, progress: Callable[[int, int], None] | None = None) -> HDRImage:
    """The burst merge of a capture's measuring images as an HDR image (hdr-static's
    units, mask 0 everywhere, 3 where the merged rate is below one electron per frame of
    the measurement sensor's subframes, 2 where the reference clipped)."""
    from .errors import InputError
    from .hdr_static import reconstruction

    if cap.measure is None or cap.measure_times is None or cap.measure.shape[0] < 2:
        raise InputError("a burst merge needs a capture with two or more measuring images")
    t0 = time.perf_counter()
    rig = cap.rig
    rate, info = burst_merge(cap.measure, cap.measure_times, rig, progress)
    n = cap.measure.shape[0]
    dur = float(np.diff(cap.measure_times, axis=1).sum())
    floor = 1.0 / (dur * rig.measure_fraction)
    mask = np.zeros(cap.shape, np.uint8)
    low = (rate < floor).any(axis=2)
    mask[low] = 3
    clipped = (np.asarray(cap.measure[0], np.float32) >= np.float32(rig.saturation_dn)).any(axis=2)
    mask[clipped] = 2
    rate = np.maximum(rate, np.float32(floor))
    return reconstruction(
        cap,
        rate,
        mask,
        "burst-merge",
        provenance_entry("burst-merge", method="hasinoff2016"),
        burst=dict(info, reference="measuring image 0", images=int(n)),
        runtime_s=round(time.perf_counter() - t0, 3),
    )
