"""Rig physics shared by ``simulate``, the emulated rig behind ``capture``, and ``deblur``.

Sensor model (both sensors): expected electrons ``lam`` -> shot noise (Poisson) -> clip at
the full well -> read noise (Gaussian) -> ADC (``gain_dn_per_e``, rounding, clip to the
code range). Closure: the host sums measuring subframes per pixel; an LCoS cell closes on
its brightest pixel once that sum reaches the threshold, and the closure takes effect
``latency_subframes`` after the end of the subframe that crossed it.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.special import ndtr

from .crossings import CrossingScan
from .rig import RigParams

#: Above this mean the normal approximation replaces exact Poisson sampling. At lam = 30
#: the approximation's skewness error is 1/sqrt(30) ~ 0.18 sigma^3, far below what the
#: ADC (2.4 e- per DN) resolves, and exact sampling of large means is slower.
POISSON_EXACT_BELOW = 30.0


def _normal_shot(lam: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``lam + sqrt(lam) z`` (float32) for clamped means ``lam``, with those means and the
    mask of the ones that need exact Poisson counts instead."""
    lam = np.maximum(lam, 0, dtype=np.float32)
    out = np.sqrt(lam)
    out *= z
    out += lam
    return out, lam, lam < POISSON_EXACT_BELOW


def shot_noise(lam: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Photon/dark shot noise: a Poisson draw per pixel with mean ``lam`` (electrons).

    Exact for ``lam < POISSON_EXACT_BELOW``, normal approximation above (float32).
    """
    out, lam, small = _normal_shot(lam, rng.standard_normal(np.shape(lam), dtype=np.float32))
    if small.any():
        out[small] = rng.poisson(lam[small]).astype(np.float32)
    return out


def poisson_quantile(u: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Inverse Poisson CDF: the smallest k with P(X <= k) >= u for X ~ Poisson(lam).

    The same answer as ``scipy.stats.poisson.ppf`` on ``0 < u < 1`` for the small means
    this is used for (lam below ``POISSON_EXACT_BELOW``), by one vectorised pass per
    count over the pixels still below their quantile instead of a root search per pixel
    (``make bench``, bench_foundation, times both).
    """
    u = np.asarray(u, np.float64)
    lam = np.asarray(lam, np.float64)
    k = np.zeros(lam.shape, np.float64)
    p = np.exp(-lam)
    cdf = p.copy()
    todo = np.flatnonzero(cdf < u)
    n = 0
    # The CDF's float sum can stop short of a u within rounding of 1: stop where the
    # Poisson tail is below double precision anyway (mean + 40 sd is far past it).
    limit = float(lam.max(initial=0.0)) + 40.0 * np.sqrt(float(lam.max(initial=0.0))) + 40
    while todo.size and n < limit:
        n += 1
        p_t = p[todo] * lam[todo] / n
        p[todo] = p_t
        cdf[todo] += p_t
        k[todo] = n
        todo = todo[cdf[todo] < u[todo]]
    return k


class SensorNoise:
    """One realisation of a sensor's noise, per pixel, that several exposures can share.

    Exposures of the same scene by different methods (VET, long, short, adaptive
    attenuation) are compared on the same noise, not on independent draws (common random
    numbers). Shot noise is drawn by inversion: a standard normal ``z`` per pixel becomes
    the Poisson count at quantile ``Phi(z)`` (exact below ``POISSON_EXACT_BELOW``, the
    normal approximation ``lam + sqrt(lam) z`` above, as in :func:`shot_noise`); read noise
    is a second standard normal per pixel. Each exposure's noise has exactly the
    distribution an independent draw would have; two exposures with the same expected
    electrons in a pixel record the same value there, and nearby means get nearby counts.
    """

    def __init__(self, shape: tuple[int, ...], rng: np.random.Generator):
        self.shot_z = rng.standard_normal(shape, dtype=np.float32)
        self.read_z = rng.standard_normal(shape, dtype=np.float32)

    def shot(self, lam: np.ndarray) -> np.ndarray:
        if lam.shape != self.shot_z.shape:
            raise ValueError(f"noise drawn for {self.shot_z.shape}, exposure is {lam.shape}")
        out, lam, small = _normal_shot(lam, self.shot_z)
        if small.any():
            u = ndtr(self.shot_z[small].astype(np.float64))
            out[small] = poisson_quantile(u, lam[small]).astype(np.float32)
        return out


def noise_streams(seed: int) -> tuple[np.random.SeedSequence, np.random.SeedSequence]:
    """The seeding rule that ``simulate`` and the emulated rig share: from one seed, a
    stream for the methods' shared :class:`SensorNoise` and a stream whose children seed
    the measuring subframes, one each."""
    exposure, subframes = np.random.SeedSequence(seed).spawn(2)
    return exposure, subframes


def expose(
    lam_e: np.ndarray,
    rig: RigParams,
    noise: np.random.Generator | SensorNoise,
    gain: float = 1.0,
) -> np.ndarray:
    """Expected electrons -> digital numbers through the full sensor chain (float32 DN,
    black-level subtracted: the code range is ``[-black_level_dn, max_dn]``).

    ``noise`` is a generator (a fresh, independent draw) or a :class:`SensorNoise` shared
    with other exposures of the same pixels. ``gain`` scales the conversion gain (the
    measurement camera's ``measure_gain``).
    """
    shared = isinstance(noise, SensorNoise)
    e = noise.shot(lam_e) if shared else shot_noise(lam_e, noise)
    np.minimum(e, rig.full_well_e, out=e)
    if rig.read_noise_e > 0:
        z = noise.read_z if shared else noise.standard_normal(e.shape, dtype=np.float32)
        e += np.float32(rig.read_noise_e) * z
    e *= rig.gain_dn_per_e * gain if gain != 1.0 else rig.gain_dn_per_e
    np.rint(e, out=e)
    np.clip(e, -rig.black_level_dn, rig.max_dn, out=e)
    return e


def bin_may_clip(per_sub_dn: np.ndarray, rig: RigParams) -> np.ndarray:
    """Where a measuring bin may hold a clipped subframe: (..., C) -> (...) bool.

    ``per_sub_dn`` is a bin's sum divided by its number of subframes (the mean code of
    one subframe). Each subframe spreads about that mean by its shot noise; the bin is
    suspect when the 3-sigma shot tail reaches :attr:`RigParams.saturation_dn`, where
    codes may be clipped (the test the VET image gets, to which this reduces without
    shot noise). In any channel: the channels of a pixel are fitted together. One test
    for everyone who reads the bins (hdr-static, flow, the deblur misfit).
    """
    g = np.float32(rig.gain_dn_per_e)
    sat = np.float32(rig.saturation_dn)
    per_sub_dn = np.asarray(per_sub_dn)
    least = _least_may_clip(per_sub_dn.dtype, g, sat)
    if least is not None:  # (one comparison: the same booleans)
        return any_channel(per_sub_dn >= least)
    return any_channel(_clip_tail(per_sub_dn, g) >= sat)


def _clip_tail(per_sub_dn: np.ndarray, g: np.float32) -> np.ndarray:
    """The 3-sigma shot tail of :func:`bin_may_clip`, in ``per_sub_dn``'s precision."""
    shot_dn = np.sqrt(np.maximum(per_sub_dn, 0) * g)  # g * sqrt(electrons)
    return per_sub_dn + np.float32(3.0) * shot_dn


@functools.lru_cache(maxsize=64)
def _least_may_clip(dtype: np.dtype, g: np.float32, sat: np.float32):
    """The least value ``x`` of the floating ``dtype`` whose :func:`_clip_tail` reaches
    ``sat``, or None where no such threshold stands for the test (a non-float dtype, a
    gain or saturation that is not positive and finite).

    The tail is a non-decreasing function of ``x`` as computed (each of its operations
    rounds monotonically), negative below 0 and at least ``x`` above it, so the test
    holds exactly from that value up: it is found by bisection over the dtype's positive
    values (in their bit patterns' order), from the same operations on 0-d arrays.
    """
    if dtype.kind != "f" or dtype.itemsize not in (4, 8):
        return None
    if not (np.isfinite(g) and g > 0 and np.isfinite(sat) and sat > 0):
        return None
    bits = np.dtype(f"u{dtype.itemsize}")

    def reaches(k: int) -> bool:
        x = np.array(k, bits).view(dtype)
        return bool(_clip_tail(x, g) >= sat)

    lo, hi = 0, int(np.array(sat, dtype).view(bits))  # (0 falls short; sat itself reaches)
    if reaches(lo) or not reaches(hi):
        return None
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if reaches(mid) else (mid, hi)
    return np.array(hi, bits).view(dtype)[()]


def channel_mean(
    frame: np.ndarray, dtype: np.typing.DTypeLike = None, out: np.ndarray | None = None
) -> np.ndarray:
    """Mean over the last (channel) axis of (..., C), from whole channel planes (numpy's
    reduction over a short contiguous axis is much slower; ``bench_foundation`` times
    both): the channels summed in order in ``dtype`` (by default the array's, which must
    then be floating), then divided by C, into ``out`` if given. For a float array, the
    numbers of ``frame.mean(axis=-1)``."""
    dt = np.dtype(frame.dtype if dtype is None else dtype)
    c = frame.shape[-1]
    if c == 1:
        if out is None:
            return frame[..., 0].astype(dt)
        np.copyto(out, frame[..., 0], casting="unsafe")
        return out
    out = np.add(frame[..., 0], frame[..., 1], out=out, dtype=dt)
    for k in range(2, c):
        np.add(out, frame[..., k], out=out, dtype=dt)
    out /= dt.type(c)
    return out


def any_channel(mask: np.ndarray) -> np.ndarray:
    """``mask.any(axis=-1)`` of a boolean (..., C), from whole channel planes."""
    out = mask[..., 0].copy()
    for k in range(1, mask.shape[-1]):
        out |= mask[..., k]
    return out


def brightest_channel(frame: np.ndarray) -> np.ndarray:
    """Per-pixel maximum over channels of (H, W, C) (or (H, W) as is).

    Elementwise ``np.maximum`` over channel planes, faster than ``frame.max(axis=2)``,
    which reduces a short contiguous axis (``make bench``, bench_foundation, times both).
    """
    if frame.ndim == 2:
        return frame
    if frame.shape[2] == 1:
        return frame[:, :, 0]
    out = np.maximum(frame[:, :, 0], frame[:, :, 1])
    for c in range(2, frame.shape[2]):
        np.maximum(out, frame[:, :, c], out=out)
    return out


def cells_at(
    homography: np.ndarray, lcos_cells: tuple[int, int], x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """Row-major index of the LCoS cell whose area contains each sensor point ``(x, y)``
    (pixel coordinates, any equal shapes) through the cell -> pixel ``homography``:
    int64 of ``x``'s shape, ``cells_w * cells_h`` (never closed) outside the LCoS."""
    cw, ch = lcos_cells
    hinv = np.linalg.inv(np.asarray(homography, dtype=np.float64))
    x = np.asarray(x, np.float64)
    cell = hinv @ np.stack([x.ravel(), np.asarray(y, np.float64).ravel(), np.ones(x.size)])
    cx = np.floor(cell[0] / cell[2]).astype(np.int64)
    cy = np.floor(cell[1] / cell[2]).astype(np.int64)
    inside = (cx >= 0) & (cx < cw) & (cy >= 0) & (cy < ch)
    return np.where(inside, cy * cw + cx, cw * ch).reshape(x.shape)


def cells_near(
    homography: np.ndarray,
    lcos_cells: tuple[int, int],
    x: np.ndarray,
    y: np.ndarray,
    margin_px: float,
) -> np.ndarray:
    """The cells each sensor point ``(x, y)`` could lie in with the homography known
    within ``margin_px``: :func:`cells_at` of the point and of its eight neighbours at
    that distance, (x.size, 9) int64, column 4 the point's own."""
    d = (-margin_px, 0.0, margin_px)
    return np.stack(
        [cells_at(homography, lcos_cells, x + dx, y + dy).ravel() for dy in d for dx in d],
        axis=1,
    )


class CellMap:
    """Which LCoS cell governs each sensor pixel, through the calibration homography.

    ``pixel_cell[y, x]`` is the row-major cell index (``cy * cells_w + cx``) whose area
    contains the pixel centre, or ``n_cells`` (a sentinel, never closed) where the pixel
    lies outside the LCoS footprint. ``points`` (two (H, W) arrays) gives each pixel's
    position in the homography's sensor coordinates instead of its own centre (the
    measurement camera's pixels seen on the VET sensor, :mod:`stages.optics`).
    """

    def __init__(
        self,
        homography: np.ndarray,
        lcos_cells: tuple[int, int],
        shape: tuple[int, int],
        points: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        h, w = shape
        cw, ch = lcos_cells
        self.shape = shape
        self.lcos_cells = (cw, ch)
        self.n_cells = cw * ch
        if points is None:
            yy, xx = np.mgrid[0:h, 0:w]
            points = (xx + 0.5, yy + 0.5)
        idx = cells_at(homography, (cw, ch), points[0], points[1])
        self.pixel_cell = idx.reshape(h, w).astype(np.int32)
        flat = self.pixel_cell.ravel()
        self._order = np.argsort(flat, kind="stable").astype(np.int64)
        sorted_cells = flat[self._order]
        self._present, self._starts = np.unique(sorted_cells, return_index=True)
        self._starts = self._starts.astype(np.int64)

    @classmethod
    def for_rig(cls, rig: RigParams, shape: tuple[int, int]) -> CellMap:
        return cls(np.asarray(rig.homography), rig.lcos_cells, shape)

    def cell_max(self, values: np.ndarray) -> np.ndarray:
        """Per-cell maximum of a per-pixel (H, W) array; cells with no pixel get -inf.

        Returns ``ndarray of shape (n_cells + 1,)``; the last entry is the sentinel.
        """
        out = np.full(self.n_cells + 1, -np.inf, dtype=np.float32)
        gathered = values.ravel()[self._order]
        out[self._present] = np.maximum.reduceat(gathered, self._starts)
        return out

    def cell_min(self, values: np.ndarray) -> np.ndarray:
        out = np.full(self.n_cells + 1, np.inf, dtype=np.float32)
        gathered = values.ravel()[self._order]
        out[self._present] = np.minimum.reduceat(gathered, self._starts)
        return out

    def to_pixels(self, per_cell: np.ndarray) -> np.ndarray:
        """Broadcast a per-cell array (length ``n_cells + 1``) back to (H, W)."""
        return per_cell[self.pixel_cell]


#: A host step whose crossed pixels name more cells than this fraction of the grid finds
#: them by marking the cells and scanning the marks; fewer, by sorting.
MARK_CELLS_ABOVE = 1 / 64


class ClosureController:
    """The host's threshold logic: accumulate measuring subframes, close cells.

    Call :meth:`step` once per measuring subframe ``k`` (DN, (H, W) or (H, W, C)); it
    returns the cells newly commanded closed. ``close_subframe[c]`` is the subframe index
    from which cell ``c`` is closed (it integrated subframes ``0 .. close_subframe - 1``),
    with ``NEVER`` for cells still open.

    A cell closes on its brightest pixel: its maximum running sum reaches the threshold
    exactly when any one of its pixels does, so each step only looks at pixels that
    crossed (:class:`stages.crossings.CrossingScan`: one subtract, one compare, one scan
    over the frame) instead of reducing every cell. A pixel is retired once it has
    crossed, so it never triggers again; the other pixels of a cell it closed retire when
    they cross in turn (their cell is found closed and skipped), which costs less than
    retiring every pixel of each closed cell at once.

    On a measurement camera of its own (:class:`stages.optics.MeasureGeometry`),
    ``extras`` (CSR ``(starts, cells)``, pixel -> further cells it governs: cells smaller
    than a pixel) closes those cells with the pixel, and ``dn_scale`` (H, W) flat-fields
    the camera's gain and vignetting (a pixel's running sum is compared with ``threshold /
    dn_scale``, which is the flat-fielded sum's test without scaling every frame).
    ``remaining_dn`` (H, W) is what each pixel still has to gather.
    """

    NEVER = np.iinfo(np.int32).max
    _RETIRED = np.float32(3.0e38)  # (a remaining sum that no subframe reaches)

    def __init__(
        self,
        rig: RigParams,
        cellmap: CellMap,
        extras: tuple[np.ndarray, np.ndarray] | None = None,
        dn_scale: np.ndarray | None = None,
    ):
        self.rig = rig
        self.cellmap = cellmap
        self.dn_scale = None if dn_scale is None else np.asarray(dn_scale, np.float32)
        self._extras = None
        self._keep = None
        if extras is not None and extras[1].size:
            self._extras = (np.asarray(extras[0], np.int64), np.asarray(extras[1], np.int64))
            counts = np.diff(self._extras[0])
            self._keep = counts > 0  # pixels that govern extra cells
        h, w = cellmap.shape
        # What each pixel still has to gather before its cell closes (the threshold less
        # its running sum), so that each step is one subtract and one compare with 0.
        self.remaining_dn = np.empty((h, w), np.float32)
        self._flat = self.remaining_dn.reshape(-1)
        self.close_subframe = np.full(cellmap.n_cells + 1, self.NEVER, dtype=np.int32)
        self.threshold_dn = np.float32(rig.threshold_dn)
        self.remaining_dn[...] = self.threshold_dn
        if self.dn_scale is not None:  # (flat-fielding the sums: a threshold per pixel)
            with np.errstate(divide="ignore"):
                self.remaining_dn[...] = np.minimum(self.threshold_dn / self.dn_scale, 3.0e38)
        # Pixels outside the LCoS footprint (sentinel cell) can never close: retire them.
        sentinel = cellmap.pixel_cell.reshape(-1) == cellmap.n_cells
        if self._keep is not None:  # ... unless they govern cells of their own
            sentinel &= ~self._keep
        self._flat[sentinel] = self._RETIRED
        self._scan = CrossingScan(self._flat)
        self._marks = np.zeros(cellmap.n_cells + 1, bool)  # (scratch: cells of one step)

    def step(self, frame_dn: np.ndarray, k: int) -> np.ndarray:
        """Add subframe ``k``; return indices of cells that crossed the threshold."""
        pix = self._scan(brightest_channel(frame_dn))
        if pix.size == 0:
            return pix
        new = self._open_cells_of(pix)
        self.close_subframe[new] = k + 1 + self.rig.latency_subframes
        return new

    def _open_cells_of(self, pix: np.ndarray) -> np.ndarray:
        """Retire pixels ``pix`` (ascending) that crossed; return the open cells they
        govern (int64, ascending, each once)."""
        self._flat[pix] = self._RETIRED
        new = self.cellmap.pixel_cell.reshape(-1)[pix]
        if self._extras is not None:
            starts, cells = self._extras
            sel = pix[self._keep[pix]]
            if sel.size:  # the cells each selected pixel governs, gathered at once
                counts = starts[sel + 1] - starts[sel]
                first = np.repeat(starts[sel] - (np.cumsum(counts) - counts), counts)
                new = np.concatenate([new, cells[first + np.arange(int(counts.sum()))]])
        n = self.cellmap.n_cells
        if new.size > MARK_CELLS_ABOVE * n:  # many: marked on the cells, found in one scan
            self._marks[new] = True
            out = np.flatnonzero(self._marks[:n])
            self._marks[new] = False
            return out[self.close_subframe[out] == self.NEVER]
        new = new[self.close_subframe[new] == self.NEVER]  # (the sentinel never closes)
        new = np.sort(new, kind="stable")  # (nearly sorted: pixels come in raster order)
        new = new[np.concatenate((new[:1] == new[:1], new[1:] != new[:-1]))]
        return new[new < n].astype(np.int64)

    def open_pixels(self, j: int) -> np.ndarray:
        """Boolean (H, W): pixels whose cell is open during subframe ``j``."""
        return self.cellmap.to_pixels(self.close_subframe > j)

    def exposure_time(self) -> np.ndarray:
        """Per-pixel closure time in seconds (the frame length where never closed)."""
        t = np.minimum(
            self.close_subframe.astype(np.float64) * self.rig.subframe_s, self.rig.frame_s
        ).astype(np.float32)
        return self.cellmap.to_pixels(t)


def radiance_scale(
    scene_luminance_p999: float, rig: RigParams, reach_subframes: float = 1.0
) -> float:
    """Electrons per second (at the VET sensor) per scene unit, chosen so that the
    scene's 99.9th-percentile luminance reaches the threshold in ``reach_subframes``
    measuring subframes (DESIGN.md §2: one; more renders a dimmer scene)."""
    if not np.isfinite(scene_luminance_p999) or scene_luminance_p999 <= 0:
        raise ValueError("scene has no positive luminance to set the radiance scale from")
    if not np.isfinite(reach_subframes) or reach_subframes <= 0:
        raise ValueError("the subframes to reach the threshold must be a positive number")
    return rig.threshold_e / (
        reach_subframes * rig.subframe_s * rig.measure_fraction * scene_luminance_p999
    )
