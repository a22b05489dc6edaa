"""The burst merge's robust merge in the frequency domain (Hasinoff et al. 2016, §5).

Overlapping :data:`TILE` x :data:`TILE` tiles (stride ``TILE / 2``, a raised cosine
window whose shifted copies sum to one) are merged in the 2-D frequency domain, each
alternate frame's tile ``T_z`` pulled toward the reference's ``T_0`` by the pairwise
robust Wiener shrinkage ``A_z = |D_z|^2 / (|D_z|^2 + c sigma^2)`` with ``D_z = T_0 -
T_z``: ``T~ = mean_z (T_z + A_z D_z)``, so a frequency that differs from the reference by
no more than the noise is averaged and one that differs more (an alignment failure, an
occlusion) keeps the reference. A measuring subframe holds a few electrons in the dark,
so one frame is a poor reference there: a second pass merges every frame (the first too)
again, pulled toward the first pass's merge instead (a reference ``sqrt(N)`` times less
noisy), with the noise of that merge's level. ``sigma^2`` is the tile's noise variance
per frequency from the sensor's noise model (shot noise at the reference tile's mean plus
a full read noise per subframe; Poisson-Gaussian, no estimate from the data). Then the
paper's spatial denoising: each merged frequency is shrunk by ``|T~|^2 / (|T~|^2 + c_s
sigma^2 / N)`` (``N`` frames merged), all but the tile's mean (its zero frequency:
shrinking that would bias dark tiles towards black). Tiles are overlap-added back.

The merge runs over strips of tile rows: every frame's tiles of a strip are gathered
through a strided view of the stream at their displacements, windowed and transformed in
one batched FFT (scipy.fft, :data:`FFT_WORKERS` threads), and both passes read the same
spectra, vectorised over frames and tiles; a strip holds at most about
:data:`STRIP_BYTES` of them (one tile row when a row alone is larger), which bounds the
memory at any frame size. (Summing runs of frames that the alignment puts at one
displacement before the transform would cut the work by the runs' length, but blurs what
the frames' sub-pixel offsets differ by: 15% more RMS error on a textured pan.)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.fft

from .alignment import TILE

#: Temporal robustness (the paper's c) and spatial denoising strengths.
C_TEMPORAL = 8.0
C_SPATIAL = 1.0
#: Tile spectra a strip of tile rows holds at most, bytes.
STRIP_BYTES = 96 << 20
#: Threads of the batched FFTs.
FFT_WORKERS = 2
#: Bytes of one tile's spectrum in one channel (complex64, half the frequencies).
SPECTRUM_BYTES = TILE * (TILE // 2 + 1) * 8


@dataclass(frozen=True)
class TileGrid:
    """The merge's tiles over an (h, w) frame: :data:`TILE` px at stride ``TILE / 2``,
    the frame padded by half a tile all round (every pixel under two tiles per axis, so
    the windows sum to one) and to whole tiles."""

    h: int
    w: int

    @property
    def step(self) -> int:
        return TILE // 2

    @property
    def padded(self) -> tuple[int, int]:
        """``(hp, wp)``: the padded frame, whole half-tiles."""
        s = self.step
        return (-(-(self.h + s) // s) * s + s, -(-(self.w + s) // s) * s + s)

    @property
    def tiles(self) -> tuple[int, int]:
        """``(n_ty, n_tx)``: tiles per column and per row."""
        hp, wp = self.padded
        return hp // self.step - 1, wp // self.step - 1

    def origins(self, axis: int) -> np.ndarray:
        """Each tile's first row (``axis`` 0) or column (1) in frame coordinates."""
        return np.arange(self.tiles[axis]) * self.step - self.step

    def pad(self, img: np.ndarray) -> np.ndarray:
        """An (h, w) image padded to :attr:`padded` (edges replicated), float32."""
        hp, wp = self.padded
        s = self.step
        pads = ((s, hp - self.h - s), (s, wp - self.w - s))
        return np.pad(np.asarray(img, np.float32), pads, mode="edge")

    def tile_means(self, img: np.ndarray) -> np.ndarray:
        """The mean of an (h, w) image over each tile, (n_ty, n_tx) float64."""
        s = self.step
        hp, wp = self.padded
        blocks = self.pad(img).astype(np.float64).reshape(hp // s, s, wp // s, s).sum(axis=(1, 3))
        return (blocks[:-1, :-1] + blocks[1:, :-1] + blocks[:-1, 1:] + blocks[1:, 1:]) / TILE**2


@dataclass(frozen=True)
class FrameNoise:
    """The noise of a frame's pixel (DN^2) as ``sigma^2`` reads it: ``gain * shot * mean
    + read_dn2 * read``, with per-tile factors ``shot`` and ``read`` (n_ty, n_tx): 1 on
    the VET sensor's grid, the flat-fielding's ``1 / v`` and ``1 / v^2`` on a camera with
    vignetting ``v``."""

    gain: float
    read_dn2: float
    shot: np.ndarray
    read: np.ndarray

    def sigma2(self, tiles: tuple[np.ndarray, np.ndarray], mean_dn: np.ndarray) -> np.ndarray:
        """Noise variance per frequency of the windowed tiles at ``tiles`` (rows,
        columns: (n,) each) whose pixels average ``mean_dn`` (n, C): (n, C, 1, 1)."""
        shot, read = self.shot[tiles][:, None], self.read[tiles][:, None]
        var = self.gain * shot * np.maximum(mean_dn, 0) + self.read_dn2 * read
        return (var * float(np.sum(WINDOW**2)))[..., None, None].astype(np.float32)


def window(n: int) -> np.ndarray:
    """Raised cosine whose copies shifted by ``n / 2`` sum to one, (n, n) float32."""
    x = np.arange(n)
    w1 = 0.5 - 0.5 * np.cos(2 * np.pi * (x + 0.5) / n)
    return np.outer(w1, w1).astype(np.float32)


WINDOW = window(TILE)


def strip_rows(n_frames: int, n_ty: int, n_tx: int, channels: int) -> list[slice]:
    """Tile rows in strips whose tiles, every frame's, fit :data:`STRIP_BYTES` as
    spectra (at least one row a strip)."""
    rows = max(1, STRIP_BYTES // (n_frames * n_tx * channels * SPECTRUM_BYTES))
    return [slice(r, min(n_ty, r + rows)) for r in range(0, n_ty, rows)]


def _crop_into(out: np.ndarray, frames: np.ndarray, y: tuple[int, int], x: tuple[int, int]) -> None:
    """Rows ``y[0]:y[1]`` and columns ``x[0]:x[1]`` of ``frames`` (K, H, W, C) into
    ``out`` (K, C, rows, columns), edges replicated past the frame's border."""
    h, w = frames.shape[1:3]
    iy, ix = (max(y[0], 0), min(y[1], h)), (max(x[0], 0), min(x[1], w))
    oy, ox = iy[0] - y[0], ix[0] - x[0]
    ny, nx = iy[1] - iy[0], ix[1] - ix[0]
    out[:, :, oy : oy + ny, ox : ox + nx] = frames[:, iy[0] : iy[1], ix[0] : ix[1]].transpose(
        0, 3, 1, 2
    )
    out[:, :, :oy] = out[:, :, oy : oy + 1]
    out[:, :, oy + ny :] = out[:, :, oy + ny - 1 : oy + ny]
    out[..., :ox] = out[..., ox : ox + 1]
    out[..., ox + nx :] = out[..., ox + nx - 1 : ox + nx]


def strip_tiles(
    frames: np.ndarray, d: np.ndarray, grid: TileGrid, r0: int, flat: np.ndarray | None
) -> np.ndarray:
    """Every frame's tiles of the strip of tile rows from ``r0``, each at its displacement
    ``d`` (K, nr, n_tx, 2) (edges replicated; each frame multiplied by ``flat`` (H, W)
    when given): (K nr n_tx, C, TILE, TILE) float32, frame-major."""
    k_n, _, _, c = frames.shape
    y0 = grid.origins(0)[r0 : r0 + d.shape[1]][None, :, None] + d[..., 0]
    x0 = grid.origins(1)[None, None, :] + d[..., 1]
    y = (int(y0.min()), int(y0.max()) + TILE)
    x = (int(x0.min()), int(x0.max()) + TILE)
    # The band the strip's tiles read, channels before rows so that a tile's rows are
    # whole.
    band = np.empty((k_n, c, y[1] - y[0], x[1] - x[0]), np.float32)
    _crop_into(band, frames, y, x)
    if flat is not None:
        crop = np.empty((1, 1, *band.shape[2:]), np.float32)
        _crop_into(crop, flat[None, :, :, None], y, x)
        band *= crop
    view = np.lib.stride_tricks.sliding_window_view(band, (TILE, TILE), axis=(2, 3))
    tiles = view[np.arange(k_n)[:, None, None], :, y0 - y[0], x0 - x[0]]
    return tiles.reshape(-1, c, TILE, TILE)


#: Tiles whose pull is computed at once (temporaries that stay in the caches).
PULL_CHUNK = 8


def pass_sum(
    ref: np.ndarray, spec: np.ndarray, sigma2: np.ndarray, stats: np.ndarray | None
) -> np.ndarray:
    """Per tile, ``sum_z (T_z + A_z D_z)`` over the frames with ``D_z = ref - T_z`` and
    ``A_z = |D_z|^2 / (|D_z|^2 + c sigma^2)`` (§5; ``ref`` (tiles, ...), ``spec`` (K,
    tiles, ...) the frames' spectra ``T_z``, ``sigma2`` (tiles, C, 1, 1)); with ``stats``
    (2,) ``sum |A_z D_z|`` and ``sum |D_z|`` are added to it."""
    out = np.array(spec[0])
    cs = np.float32(C_TEMPORAL) * sigma2
    for t0 in range(0, ref.shape[0], PULL_CHUNK):
        t = slice(t0, t0 + PULL_CHUNK)
        d = ref[t] - spec[:, t]
        mag = d.real * d.real
        mag += d.imag * d.imag
        a = mag / (mag + cs[t])
        if stats is not None:
            absd = np.sqrt(mag)
            stats += ((a * absd).sum(dtype=np.float64), absd.sum(dtype=np.float64))
        d *= a
        d += spec[:, t]
        out[t] = d.sum(axis=0)
    return out


def robust_merge(
    spec: np.ndarray,
    noise: FrameNoise,
    tiles: tuple[np.ndarray, np.ndarray],
    mean0: np.ndarray,
    stats: np.ndarray,
) -> np.ndarray:
    """The two passes of §5 and the spatial denoising on a strip's spectra ``spec`` (K,
    tiles, C, T, T/2+1), frame 0 the reference; ``tiles`` the strip's tiles (rows,
    columns) and ``mean0`` (tiles, C) the mean of frame 0's pixels under each. Returns
    (tiles, C, T, T/2+1)."""
    k_n = spec.shape[0]
    sigma2 = noise.sigma2(tiles, mean0)
    ref = pass_sum(spec[0], spec, sigma2, None) / k_n
    # Second pass: every frame (the first too) pulled toward the first pass's merge, a
    # reference far less noisy than one frame, with the noise of its own mean level.
    sigma2 = noise.sigma2(tiles, ref[..., 0, 0].real / float(WINDOW.sum()))
    merged = pass_sum(ref, spec, sigma2, stats) / k_n
    mag = merged.real**2 + merged.imag**2
    shrink = mag / (mag + np.float32(C_SPATIAL / k_n) * sigma2)
    shrink[..., 0, 0] = 1.0  # a tile's mean is kept: shrinking it would bias the dark
    merged *= shrink
    return merged


def merge_strips(
    frames: np.ndarray,
    disps: np.ndarray,
    noise: FrameNoise,
    flat: np.ndarray | None,
    progress: Callable[[int, int], None],
) -> tuple[np.ndarray, dict]:
    """Merge ``frames`` (K, H, W, C) at their tiles' displacements ``disps`` (K, n_ty,
    n_tx, 2) strip by strip and overlap-add: mean DN of one frame (H, W, C) float32, and
    ``{"frames": K, "mean_shrink": ...}`` (the second pass's ``|A D|`` summed over
    ``|D|`` summed over every frame and tile; 0 all averaged, 1 all rejected)."""
    k_n, h, w, c = frames.shape
    grid = TileGrid(h, w)
    s = grid.step
    n_ty, n_tx = grid.tiles
    # Tile (i, j)'s quadrant (a, b) lands on block (i + a, j + b) of a grid of half-tile
    # blocks (the windows' shifted copies sum to one).
    blocks = np.zeros((n_ty + 1, n_tx + 1, c, s, s), np.float32)
    stats = np.zeros(2)
    strips = strip_rows(k_n, n_ty, n_tx, c)
    for i, r in enumerate(strips):
        rows = np.arange(r.start, r.stop)
        tiles = (np.repeat(rows, n_tx), np.tile(np.arange(n_tx), len(rows)))
        pixels = strip_tiles(frames, disps[:, r], grid, r.start, flat)
        mean0 = pixels[: len(tiles[0])].mean(axis=(-2, -1))  # (frame 0's, unwindowed)
        pixels *= WINDOW
        spec = scipy.fft.rfft2(pixels, axes=(-2, -1), workers=FFT_WORKERS, overwrite_x=True)
        del pixels
        spec = spec.reshape(k_n, len(tiles[0]), *spec.shape[1:])
        merged = robust_merge(spec, noise, tiles, mean0, stats)
        back = scipy.fft.irfft2(merged, s=(TILE, TILE), axes=(-2, -1), workers=FFT_WORKERS)
        back = back.reshape(len(rows), n_tx, c, TILE, TILE)
        for a in (0, 1):
            for b in (0, 1):
                blocks[r.start + a : r.stop + a, b : b + n_tx] += back[
                    ..., a * s : (a + 1) * s, b * s : (b + 1) * s
                ]
        progress(i + 1, len(strips))
    hp, wp = grid.padded
    out = blocks.transpose(0, 3, 1, 4, 2).reshape(hp, wp, c)[s : s + h, s : s + w]
    shrink = float(stats[0] / max(stats[1], 1e-30))
    return np.ascontiguousarray(out), {"frames": int(k_n), "mean_shrink": round(shrink, 4)}
