"""Burst merge: the HDR+ align-and-merge of a capture's measuring subframes alone.

A comparison method every user can run (``vet deblur --method burst``, ``vet evaluate``
row ``burst-merge``): what an off-the-shelf burst pipeline makes of the rig's own short,
sharp, noisy measuring subframes, ignoring the VET image. It follows Hasinoff et al.
(2016); :func:`burst_merge` reads as its outline (align every frame, merge, convert).

Alignment (§4, :mod:`stages.burst.alignment`): the reference is the first frame (the scene
nearest t = 0, which vet's outputs show); each frame is aligned to it tile by tile,
coarse to fine, on a Gaussian pyramid of the frames' channel mean, in whole pixels.

Merge (§5, :mod:`stages.burst.merge`): overlapping tiles merged in the 2-D frequency
domain, each frame pulled toward the reference by the pairwise robust Wiener shrinkage,
in two passes (toward frame 0, then toward the first pass's merge), then the spatial
denoising; strips of tiles, every frame's at once, bound the memory.

A real rig (DESIGN.md §1): its measurement camera has its own pixel grid, gain and
vignetting. The frames are flat-fielded (:class:`stages.optics.MeasureGeometry`: the
camera's gain and vignetting divided out), aligned and merged on the camera's own grid,
each pixel's noise scaled as the flat-fielding scales it, and the merge is then brought
onto the VET grid through the camera's geometry (homography and distortion, bilinear:
:meth:`stages.optics.MeasureGeometry.register`, as
:func:`stages.measure_grid.register_measure` brings a stream; inverting the camera's
sampling instead, :func:`stages.measure_grid.fit_bin`, sharpens but amplifies the
noise of the dark). Frames the rig dropped are absent from the stream; its trigger
offset is in their times.

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
from typing import TYPE_CHECKING

import numpy as np

from ..formats.capture import Capture, provenance_entry
from ..formats.hdr import HDRImage
from ..rig import RigParams
from .alignment import PYRAMID_LEVELS, TILE, align, pyramid
from .merge import FrameNoise, TileGrid, merge_strips

if TYPE_CHECKING:
    from ..optics import MeasureGeometry

__all__ = ["TILE", "align", "burst_hdr", "burst_merge", "merge_frames"]


def burst_merge(
    frames: np.ndarray,
    times: np.ndarray,
    rig: RigParams,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """Align and merge measuring frames of the VET sensor's grid (module docstring).

    Parameters
    ----------
    frames : ndarray of shape (K, H, W, C)
        DN, black level subtracted; any numeric type. Each may sum several subframes.
    times : ndarray of shape (K, 2)
        ``[start, end)`` of each frame, seconds.
    rig : RigParams
    progress : callable, optional
        ``progress(done, total)`` as frames are aligned and strips merged.

    Returns
    -------
    rate : ndarray of shape (H, W, C), float32
        Electrons per second at the VET sensor.
    info : dict
        ``frames`` merged and ``mean_shrink`` (of the second pass: ``|A D|`` summed over
        ``|D|`` summed, over every run of frames and tile; 0 all averaged, 1 all
        rejected).
    """
    mean_dn, info = merge_frames(frames, times, rig, progress=progress)
    return to_rate(mean_dn, times, rig), info


def merge_frames(
    frames: np.ndarray,
    times: np.ndarray,
    rig: RigParams,
    camera: MeasureGeometry | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, dict]:
    """The merge of ``frames`` (K, H, W, C) DN on their own grid: mean DN of one frame,
    (H, W, C) float32, and the info of :func:`burst_merge`.

    ``camera``: the frames are a real rig's measurement camera's, on its grid; each is
    flat-fielded (``camera.flat``: its gain and vignetting divided out) before it is
    aligned and merged, and each pixel's shot and read variances are scaled by ``1 / v``
    and ``1 / v^2`` (``v`` its vignetting), as the flat-fielding scales them.
    """
    k_n, h, w, _ = frames.shape
    grid = TileGrid(h, w)
    dur = np.diff(np.asarray(times, np.float64), axis=1)[:, 0]
    n_sub = float(np.maximum(np.rint(dur / rig.subframe_s), 1)[0])
    flat = None if camera is None else camera.flat
    q = np.ones((h, w)) if camera is None else 1.0 / camera.vign.astype(np.float64)
    noise = FrameNoise(
        gain=float(rig.gain_dn_per_e),
        read_dn2=n_sub * (float(rig.gain_dn_per_e) * float(rig.read_noise_e)) ** 2 + 1.0 / 12,
        shot=grid.tile_means(q),
        read=grid.tile_means(q * q),
    )
    half = k_n - 1  # (progress: the alignment of each frame, then the strips merged)

    def step(done: int) -> None:
        if progress:
            progress(done, 2 * half)

    disps = align_frames(frames, grid, flat, step)
    return merge_strips(frames, disps, noise, flat, lambda i, n: step(half + half * i // n))


def _grey(frame: np.ndarray, flat: np.ndarray | None) -> np.ndarray:
    """A frame's channel mean, flat-fielded, (H, W) float32."""
    g = np.asarray(frame, np.float32).mean(axis=2)
    return g if flat is None else g * flat


def align_frames(
    frames: np.ndarray, grid: TileGrid, flat: np.ndarray | None, progress: Callable[[int], None]
) -> np.ndarray:
    """Every frame's tile displacements onto frame 0 (:func:`stages.burst.alignment.align` on
    the merge's padded grid): (K, n_ty, n_tx, 2) int64 as ``(dy, dx)``, frame 0's zero."""
    ref_pyr = pyramid(grid.pad(_grey(frames[0], flat)), PYRAMID_LEVELS)
    disps = np.zeros((frames.shape[0], *grid.tiles, 2), np.int64)
    for k in range(1, frames.shape[0]):
        disps[k] = align(ref_pyr, grid.pad(_grey(frames[k], flat)))
        progress(k)
    return disps


def to_rate(mean_dn: np.ndarray, times: np.ndarray, rig: RigParams) -> np.ndarray:
    """Mean DN of one frame (of the VET rig's measurement sensor, black level
    subtracted) as the rate in electrons per second at the VET sensor, float32."""
    tau = float(np.diff(np.asarray(times, np.float64), axis=1).mean())
    e = mean_dn / float(rig.gain_dn_per_e) - float(rig.dark_current_e_s) * tau
    return (e / (tau * float(rig.measure_fraction))).astype(np.float32)


def burst_hdr(cap: Capture, progress: Callable[[int, int], None] | None = None) -> HDRImage:
    """The burst merge of a capture's measuring images as an HDR image (hdr-static's
    units, mask 0 everywhere, 3 where the merged rate is below one electron per frame of
    the measurement sensor's subframes, 2 where the reference clipped). A real rig's
    measuring images are merged on the measurement camera's grid and brought onto the
    VET grid through its geometry (module docstring)."""
    from ..errors import InputError
    from ..hdr_static import reconstruction

    if cap.measure is None or cap.measure_times is None or cap.measure.shape[0] < 2:
        raise InputError("a burst merge needs a capture with two or more measuring images")
    t0 = time.perf_counter()
    rig = cap.rig
    clipped = (np.asarray(cap.measure[0], np.float32) >= np.float32(rig.saturation_dn)).any(axis=2)
    own_grid = rig.ideal_geometry or cap.measure_noise is not None
    if own_grid:
        rate, info = burst_merge(cap.measure, cap.measure_times, rig, progress)
    else:
        from ..optics import MeasureGeometry

        geom = MeasureGeometry(rig)
        mean_dn, info = merge_frames(cap.measure, cap.measure_times, rig, geom, progress)
        # onto the VET grid through the camera's geometry (bilinear): register() takes
        # the camera's DN, so the flat field is taken off first.
        vet_dn = geom.register(mean_dn / geom.flat[..., None])
        rate = to_rate(vet_dn, cap.measure_times, rig)
        clipped = geom.register_mask(clipped)
    n = cap.measure.shape[0]
    dur = float(np.diff(cap.measure_times, axis=1).sum())
    floor = 1.0 / (dur * rig.measure_fraction)
    mask = np.zeros(cap.shape, np.uint8)
    mask[(rate < floor).any(axis=2)] = 3
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
