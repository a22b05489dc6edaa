"""Deblur: estimate the sharp HDR scene at t = 0 and the motion from a moving VET capture.

Two methods share the forward model of :mod:`stages.deblur.operator`:

``vet`` (default, :mod:`stages.deblur.joint`)
    Layered motion (still background and translating layers, with occlusion) estimated
    from all the measuring bins (:mod:`stages.deblur.layers`); where the motion is not
    layered (the layers' model check), one affine field (a rotation, a zoom:
    :mod:`stages.deblur.affine`) or dense flow; a camera shake along measured paths;
    the affine field and a camera path refined on the misfit; noise-weighted
    (Poisson-Gaussian) misfit on the VET image and the measuring bins, conjugate-gradient
    image solves with iteratively reweighted robust weights, an edge-preserving relative
    prior; only pixels whose integration path moves are re-estimated, the rest keep
    hdr-static (the maximum-likelihood value of their VET data).
``paper`` (:mod:`stages.deblur.paper`)
    The published method of Uda et al. (2016): least-squares misfit on I, Laplacian
    smoothness on the image and on both motion components, a histogram-intersection prior
    on image-gradient histograms, steepest descent from Farnebäck flow.

References
----------
S. Uda, F. Sakaue, J. Sato, "Variable exposure time imaging for obtaining unblurred HDR
images", IPSJ Trans. Computer Vision and Applications 8, 2016.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from ..formats.capture import Capture, provenance_entry
from ..formats.hdr import HDRImage
from ..hdr_static import hdr_static, reconstruction
from ..measure_grid import register_measure
from .bins_first import bins_first
from .operator import Layers

if TYPE_CHECKING:
    from ..cluster import ClientSoon

log = logging.getLogger(__name__)

METHODS = ("vet", "paper")
MOTION_INITS = ("layers", "paths", "farneback", "dis", "truth", "zero")
#: What a Dask worker imports to solve a tile (imported as its cluster starts).
TILE_MODULES = (
    "stages.deblur.tiles",
    "stages.deblur.joint",
    "stages.deblur.problem",
    "stages.deblur.image_step",
)
#: The default deblur looks for a changing camera path on frames of at most this many
#: pixels (its registration holds 48 group images of the frame: 0.27 GB at 1280 x 1024).
PATHS_MAX_PIXELS = 1 << 21


def output_to_rate(cap: Capture, radiance: np.ndarray) -> np.ndarray:
    """Inverse of :func:`stages.hdr_static.rate_to_output_units` (to electrons/s)."""
    scale = cap.radiance_scale
    if scale:
        return radiance * np.float32(scale)
    return radiance / np.float32(cap.rig.gain_dn_per_e)


def initial_motion(cap: Capture, motion_init: str) -> np.ndarray:
    """Start velocity field (H, W, 2) px/s (:func:`start_motion` without its model)."""
    return start_motion(cap, motion_init)[0]


def start_motion(cap: Capture, motion_init: str) -> tuple[np.ndarray, str]:
    """Start velocity field (H, W, 2) px/s, and the motion model it follows.

    ``layers``: the layered estimate of :mod:`stages.deblur.layers` (a still background
    and rigidly translating layers, from long-baseline flow pooled over all measuring
    bins; model ``layers``), unless its model check finds that a dense field explains
    the bins clearly better (a rotation, a zoom, a non-rigid motion:
    :func:`stages.deblur.layers.layered_model_check`), in which case one affine field
    fitted to the dense one where it explains the bins about as well
    (:data:`stages.deblur.affine.AFFINE_MISS_SHARE`; model ``affine``, whose six
    parameters the solve refines), else the ``dis`` start (model ``dense``);
    ``farneback``/``dis``: dense flow between bins
    (:func:`stages.flow.estimate_velocity`; model ``dense``);
    ``truth``: the simulator's true motion; ``zero``: none. Flow-based starts are zero when
    the measuring bins pass the still-scene test of :func:`stages.flow.moving_mask`. The
    layered estimate is not gated by that test: it has its own guards against inventing
    motion (a layer needs a mode of the confident velocities and points with clear
    evidence), and the test calls still a moving object whose texture is too faint for
    any pixel's bins to disagree on their own (``builtin:interior`` with the object on the
    wall below the lamp, ``object:0,128,160,128:40,10`` at 320x256), whose velocity the
    layered estimate still finds.
    """
    if motion_init == "truth":
        if cap.truth_motion is None:
            raise InputError("--motion-init truth needs a simulated capture with its true motion")
        return cap.truth_motion.astype(np.float32), "truth"
    if motion_init == "zero":
        return np.zeros((*cap.shape, 2), np.float32), "zero"
    if motion_init not in ("layers", "farneback", "dis"):
        raise InputError(
            f"unknown motion initialisation {motion_init!r}; choose from {', '.join(MOTION_INITS)}"
        )
    if motion_init == "layers":
        from .layers import estimate_layers

        est = estimate_layers(cap)  # (time bins of a stream, as it reads them)
        if est.check is None or est.check.fits:
            return est.velocity, "layers"
        from .affine import AFFINE_MISS_SHARE

        if est.check.affine is not None and est.check.affine_share <= AFFINE_MISS_SHARE:
            log.info(
                "deblur: the motion is one affine field (it misses %.0f%% of what a dense"
                " field explains); refining its six parameters",
                100 * max(est.check.affine_share, 0.0),
            )
            return est.check.affine, "affine"
        log.info(
            "deblur: the motion is not layered (a dense field explains %.0f%% of what the"
            " layers miss); starting from dense flow",
            100 * est.check.missed_share,
        )
        motion_init = "dis"
    from ..flow import estimate_velocity, motion_bins, moving_mask

    cap = motion_bins(cap)  # the flow works on time bins of a stream
    if moving_mask(cap).mean() < 0.01:  # the bins agree with a still scene: no motion to find
        return np.zeros((*cap.shape, 2), np.float32), "dense"
    vel, _conf = estimate_velocity(cap, motion_init)
    return suppress_small_motion(vel), "dense"


def changing_motion(cap: Capture, main_only: bool = False):
    """Layers along measured paths when the capture keeps its stream and its motion
    changes within the frame (:mod:`stages.deblur.layers.paths`), else None. With
    ``main_only``, only when the path most of the frame follows changes (camera shake:
    :attr:`~stages.deblur.layers.paths.TilePaths.main_changing`)."""
    if not cap.keeps_stream:
        return None
    from .layers.paths import path_layers, tile_paths

    tp = tile_paths(cap.measure, cap.measure_times, cap.rig)
    if not (tp.main_changing if main_only else tp.changing):
        return None
    return path_layers(tp, float(cap.meta.get("integration_s", cap.rig.frame_s)))


def _max_speed(velocity: np.ndarray, layers: Layers | None) -> float:
    """The fastest image motion, px/s: of the layers along their paths when given, else
    of the velocity field (H, W, 2)."""
    if layers is not None:
        return layers.max_speed()
    if velocity.size == 0:
        return 0.0
    return float(np.sqrt(np.max(velocity[..., 0] ** 2 + velocity[..., 1] ** 2)))


def _tiled(tile: int | str | None, shape: tuple[int, int], channels: int = 3) -> bool:
    """Whether ``deblur(..., tile=tile)`` solves a frame of ``shape`` (of ``channels``
    colour channels) in tiles."""
    from .tiles import resolve_tile

    size = resolve_tile(tile, shape, channels)
    return size is not None and max(shape) > size


def truth_layers(cap: Capture):
    """The simulator's true motion along paths as :class:`~stages.deblur.operator.Layers`
    with their trajectories, or None when the capture has none (constant velocities)."""
    tt = cap.meta.get("truth_trajectory")
    if cap.truth_layers is None or not isinstance(tt, dict):
        return None
    from .operator import Layers

    times = np.asarray(tt["times"], np.float64)
    disp = np.asarray(tt["disp"], np.float64)
    label = cap.truth_layers.astype(np.int32)
    counts = np.bincount(label.ravel(), minlength=disp.shape[0])
    bg = int(np.argmax(counts))
    front = [int(k) for k in np.argsort(counts, kind="stable") if k != bg and counts[k] > 0]
    span = max(float(times[-1]), 1e-12)
    return Layers(label, disp[:, -1] / span, front, bg, trajectory=(times, disp))


def deblur_mask(static_mask: np.ndarray, L: np.ndarray, L_init: np.ndarray) -> np.ndarray:
    """The mask of a deblurred image (codes of :data:`stages.formats.hdr.MASK_CODES`).

    hdr-static's codes hold where the deblur kept its value. Where the deblur replaced a
    pixel (``L`` differs from hdr-static's ``L_init``, both (H, W, C)), code 3 (the
    noise-equivalent radiance) no longer describes the value and becomes 0, and code 4
    (hdr-static's doubtful recovery of a moving pixel) becomes 1: the deblur's motion
    explains the data, and the value comes from the measuring images; codes 1 (the VET
    pixel saturated, so the value comes from the measuring images) and 2 (a lower bound,
    which the deblur keeps) still hold. Returns a new (H, W) uint8 array.
    """
    mask = static_mask.copy()
    replaced = np.any(L != L_init, axis=2)
    mask[replaced & (mask == 3)] = 0
    mask[replaced & (mask == 4)] = 1
    return mask


#: Speeds below this (px/s; under two pixels of travel in a 1 s frame) are flow noise
#: for the purpose of deblurring and are set to zero, so a still scene stays still.
MIN_SPEED_PX_S = 2.0


def suppress_small_motion(vel: np.ndarray, min_speed: float = MIN_SPEED_PX_S) -> np.ndarray:
    """Zero the velocity where it is below ``min_speed``: deblur must not invent motion."""
    speed = np.hypot(vel[..., 0], vel[..., 1])
    if speed.size == 0 or not np.any(speed >= min_speed):
        return np.zeros_like(vel)
    return np.where((speed < min_speed)[..., None], 0.0, vel).astype(np.float32)


def deblur(
    cap: Capture,
    method: str = "vet",
    motion_init: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    options: object | None = None,
    truth_cb: Callable[[np.ndarray], float] | None = None,
    fuse_still: bool | str | None = None,
    motion: np.ndarray | None = None,
    motion_model: str = "given",
    tile: int | str | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    release_stream: bool = False,
    motion_paths: Layers | None = None,
    client_soon: ClientSoon | None = None,
) -> tuple[HDRImage, np.ndarray]:
    """Deblur a VET capture.

    Parameters
    ----------
    cap : Capture
        A VET capture (method ``vet``) with its exposure time image and, for motion
        estimation, measuring images.
    method : {'vet', 'paper'}
        The default joint method or the published one.
    motion_init : {'layers', 'paths', 'farneback', 'dis', 'truth', 'zero'}, optional
        Where the motion starts; default ``layers`` for the default method and Farnebäck
        (the paper's choice) for the published one. ``layers`` on a capture that keeps
        its stream, of at most :data:`PATHS_MAX_PIXELS` pixels (in one piece or in tiles),
        follows layers along paths measured from the stream when the path most of the frame follows changes within the frame (camera
        shake: :func:`changing_motion` with ``main_only``); ``paths`` (experimental) when
        any region's does, else ``layers``; its detector also fires on some
        constant-velocity objects, where it does worse.
    progress : callable, optional
        ``progress(done, total)``.
    options : JointOptions or PaperOptions, optional
        Tuning of the method.
    truth_cb : callable, optional
        Called with intermediate images in electrons/s, for error-vs-iteration figures.
    fuse_still : {None, 'auto', True, False}
        Method ``vet``: which value pixels that no moving path touches take
        (``JointOptions.fuse_still``). ``None`` or ``'auto'`` (the default): the
        maximum-likelihood value of the VET image and the measuring images together when
        the motion moves some pixel, hdr-static's when it moves none (a still capture
        comes out as hdr-static). ``True``: always the fused value (``vet deblur
        --fuse-still``); ``False``: always hdr-static's (``--keep-still``). In ``vet
        batch``: ``--param deblur.fuse_still=true|false|auto``. The image's metadata
        ``still_pixels`` says which they took (``fused`` or ``hdr-static``; ``none``
        where every pixel moves).
    motion : ndarray of shape (H, W, 2), optional
        A start motion in px/s given by the caller (``motion_init`` is then ignored and
        the metadata's ``motion_model`` says ``motion_model``, by default ``given``; with
        ``truth`` still pixels are not singled out, as for ``motion_init='truth'``).
    tile : int, 'auto' or 'none', optional
        Method ``vet``: solve in overlapping tiles of at most ``tile`` x ``tile`` pixels
        (:mod:`stages.deblur.tiles`), the motion estimated once for the whole frame;
        memory is then bounded by a tile. ``'auto'``: tiles on large frames
        (:func:`stages.deblur.tiles.resolve_tile`). None, ``'none'`` or a tile covering
        the frame: one solve.
    workers, scheduler :
        Tiles run in-process (``workers`` 1, no ``scheduler``), else as Dask tasks on an
        embedded LocalCluster of ``workers`` processes or on ``scheduler``, started (and
        its workers importing the solve) while the motion is estimated
        (:class:`~stages.cluster.ClientSoon`, passed on as ``client_soon``).
    release_stream : bool
        The caller needs no more of ``cap.measure``: method ``vet`` sets it to None once
        it has made the time bins it fits (in one piece or for the tiles), so that the
        whole measuring stream is not held through the solve (``vet deblur`` does this;
        the rest of ``cap`` is untouched).

    motion_paths : Layers, optional
        With ``motion``: that motion as layers along their paths (a tile's crop of the
        frame's measured camera path); the solve follows the paths (model ``layer-paths``).

    Returns
    -------
    image : HDRImage
        Radiance at t = 0 in the units of hdr-static (scene units for simulated
        captures, else DN/s), with hdr-static's mask and the capture's T.
    velocity : ndarray of shape (H, W, 2)
        The estimated motion, px/s (``D(x, t) = u(x) t``).
    """
    if method not in METHODS:
        raise InputError(f"unknown deblur method {method!r}; choose from {', '.join(METHODS)}")
    if cap.method != "vet":
        raise InputError(f"deblur needs a VET capture, not a {cap.method!r} one")
    if fuse_still == "auto":
        fuse_still = None
    if fuse_still not in (None, True, False):
        raise InputError(f"fuse_still must be true, false or auto, not {fuse_still!r}")
    if fuse_still is not None and method != "vet":
        raise InputError("choosing what still pixels take applies to the vet method only")
    motion_init = motion_init or ("layers" if method == "vet" else "farneback")
    n_measure = 0 if cap.measure is None else cap.measure.shape[0]
    if n_measure < 2 and motion_init not in ("truth", "zero"):  # (the estimates need two)
        raise InputError(
            f"capture has {n_measure or 'no'} measuring image{'s' * (n_measure != 1)}; motion "
            "cannot be estimated from fewer than two (--motion-init zero assumes none)"
        )
    if (
        client_soon is None
        and method == "vet"
        and (workers > 1 or scheduler is not None)
        and _tiled(tile, cap.shape, len(cap.channels))
    ):
        from ..cluster import ClientSoon

        with ClientSoon(workers, scheduler, warm=TILE_MODULES) as soon:
            return deblur(
                cap,
                method=method,
                motion_init=motion_init,
                progress=progress,
                options=options,
                truth_cb=truth_cb,
                fuse_still=fuse_still,
                motion=motion,
                motion_model=motion_model,
                tile=tile,
                workers=workers,
                scheduler=scheduler,
                release_stream=release_stream,
                motion_paths=motion_paths,
                client_soon=soon,
            )
    solve_progress = None
    if progress is not None:  # the motion estimate counts as the first step
        progress(0, 1)
        solve_progress = lambda done, total: progress(done + 1, total + 1)  # noqa: E731

    t_start = time.perf_counter()
    # A real rig's measurement camera: its images onto the VET grid, with their noise
    # (stages.optics), for hdr-static and the motion estimate; the misfit fits its bins
    # through the camera's sampling (stages.deblur.problem.observations, from the capture
    # as recorded).
    recorded = cap
    cap = register_measure(cap)
    streamed = cap.keeps_stream
    fit = None  # (the misfit's bins, where made before the motion estimate: bins_first)
    static = hdr_static(recorded, registered=cap)
    if cap.models_lcos:  # on the whole frame, for tiles cropped from it too
        from .problem import effective_T as _effective_T

        cap = replace(
            cap, ideal_T=_effective_T(cap, float(cap.meta.get("integration_s", cap.rig.frame_s)))
        )
    L_init = output_to_rate(cap, static.radiance).astype(np.float32)
    layers = None
    if motion is None and motion_init == "truth":
        layers = truth_layers(cap)
    if motion is not None:
        if motion.shape != (*cap.shape, 2):
            raise InputError(f"the given motion is {motion.shape}, not {(*cap.shape, 2)}")
        vel0 = motion.astype(np.float32)
        if motion_paths is not None:
            if motion_paths.label.shape != cap.shape:
                raise InputError("the given motion's layers do not match the capture's size")
            layers = motion_paths
    else:
        if motion_init == "paths":
            layers = changing_motion(cap)
        elif (
            motion_init == "layers"
            and method == "vet"
            and cap.shape[0] * cap.shape[1] <= PATHS_MAX_PIXELS
        ):
            layers = changing_motion(cap, main_only=True)
        if layers is not None and motion_init in ("paths", "layers"):
            vel0 = layers.velocity[layers.label].astype(np.float32)
            motion_model = "layer-paths"
        else:
            source = cap
            if release_stream and method == "vet" and motion_init in ("paths", "layers"):
                fit, source = bins_first(cap, recorded, options) or (None, cap)
            vel0, motion_model = start_motion(
                source, "layers" if motion_init == "paths" else motion_init
            )
            del source
    rig = cap.rig
    tf = float(cap.meta.get("integration_s", rig.frame_s))
    from ..cluster import trim_heap
    from .problem import bin_step, fit_bins, vet_step

    trim_heap()  # (what the motion estimate freed, before the bins are made beside the stream)

    # Time bins of a stream that the misfit reads: short enough for the motion to blur
    # none of them by more than a fraction of a pixel.
    n_fit = fit_bins(_max_speed(vel0, layers), tf, rig.n_subframes, cap.shape[0] * cap.shape[1])
    # ... each sampled along the motion as finely as the frame's size allows.
    n_bins = n_fit if streamed else (0 if cap.measure is None else cap.measure.shape[0])
    spacing = bin_step(_max_speed(vel0, layers), tf, n_bins, cap.shape[0] * cap.shape[1])
    # ... and the VET image's along a camera path.
    along_path = layers is not None and layers.trajectory is not None
    vet_spacing = vet_step(_max_speed(vel0, layers), tf, cap.shape[0] * cap.shape[1], along_path)
    # Pixels saturated in the VET image and in the first bin: only a lower bound is known.
    # (Those saturated in the VET image alone are measured by the bins, which the default
    # method fits; the paper's method, which fits I only, keeps their hdr-static value.)
    bound_only = static.mask == 2
    saturated = np.isin(static.mask, (1, 2, 4)) if method == "paper" else bound_only
    from .problem import effective_T, observations

    # What both methods take: the start image and motion, and the capture's timing.
    start = (L_init, vel0, effective_T(cap, tf), tf, rig.subframe_s, rig.leakage)
    if method != "vet":
        tile = None
    tiled = _tiled(tile, cap.shape, len(cap.channels))
    if tiled:
        from .joint import JointOptions
        from .tiles import deblur_in_tiles, resolve_tile

        tile = resolve_tile(tile, cap.shape, len(cap.channels))
        opts = options if options is not None else JointOptions()
        if fuse_still is not None:
            opts = replace(opts, fuse_still=fuse_still)
        if opts.step_px_bins is None:  # (a tile's is the frame's)
            opts = replace(opts, step_px_bins=spacing)
        if opts.step_px is None:
            opts = replace(opts, step_px=vet_spacing)
        tiles_cap = cap
        if fit is not None:
            tiles_cap = fit
        elif not cap.rig.ideal_geometry and recorded.measure is not None:
            # The tiles fit the camera's bins on its grid, each the pixels that see it
            # (stages.deblur.camera_grid); the bins registered onto the VET grid start them.
            from .camera_grid import CameraBins

            if release_stream and recorded is not cap:  # (registered: made again from the bins)
                cap.measure = None
            binned = recorded.time_bins(n_fit, consume=release_stream)
            tiles_cap = replace(
                register_measure(binned),
                ideal_T=cap.ideal_T,
                camera_bins=CameraBins.of(cap.rig, binned.measure),
            )
        elif opts.use_measure and not opts.stream_fit and cap.keeps_stream:
            # The bins each tile would fit, made once: a tile's crop of them is what it
            # would bin from its crop of the stream, in less memory; made in the stream's
            # memory when the caller lets it go.
            if release_stream and recorded is not cap:
                recorded.measure = None
            tiles_cap = cap.time_bins(n_fit, consume=release_stream)
        if release_stream and tiles_cap.measure is not recorded.measure:
            cap.measure = None
            recorded.measure = None
        radiance, tiling = deblur_in_tiles(
            deblur,
            tiles_cap,
            vel0,
            motion_model,
            opts,
            tile,
            workers,
            scheduler,
            solve_progress,
            paths=layers if layers is not None and layers.trajectory is not None else None,
            soon=client_soon,
        )
        name = "vet-deblur"
        params = {"fuse_still": "auto" if opts.fuse_still is None else bool(opts.fuse_still)}
        extra = {"still_pixels": tiling.pop("still_pixels"), "tiles": tiling}
        if tiles_cap.measure is not None and not tiles_cap.keeps_stream:
            extra["fit_bins"] = int(tiles_cap.measure.shape[0])
        L, vel = output_to_rate(cap, radiance), vel0
    elif method == "vet":
        from .joint import JointOptions, deblur_joint

        opts = options if options is not None else JointOptions()
        if fuse_still is not None:
            opts = replace(opts, fuse_still=fuse_still)
        if opts.step_px_bins is None:  # (a tile's is the frame's)
            opts = replace(opts, step_px_bins=spacing)
        if opts.step_px is None:
            opts = replace(opts, step_px=vet_spacing)
        # The motion estimated here is refined as the model allows; a given motion (the
        # truth, a tile's share of a frame's) is kept.
        opts = replace(
            opts,
            affine_motion=opts.affine_motion and motion is None and motion_model == "affine",
            path_motion=opts.path_motion and motion is None and motion_model == "layer-paths",
            layer_motion=opts.layer_motion and motion is None and motion_model == "layers",
        )
        fit_src = recorded if fit is None else fit
        if fit is None and opts.use_measure and not opts.stream_fit and recorded.keeps_stream:
            if release_stream and recorded is not cap:
                cap.measure = None
            # (the bins the misfit reads, as it bins them; in the stream's memory when let go)
            fit_src = recorded.time_bins(n_fit, consume=release_stream)
        if release_stream and fit_src.measure is not recorded.measure:
            # The motion and the bins are made: the stream is done with (before the
            # observations are made, so they are never held beside it).
            cap.measure = None
            recorded.measure = None
        obs = observations(
            fit_src, use_measure=opts.use_measure, stream=opts.stream_fit, n_bins=n_fit
        )
        del fit_src  # (the observations hold what they need of the bins)
        if release_stream:  # (a capture of time bins, let go once observed)
            cap.measure = recorded.measure = None
        report: dict = {}
        L, vel = deblur_joint(
            obs,
            *start,
            saturated,
            opts,
            progress=solve_progress,
            truth_cb=truth_cb,
            still=~np.any(vel0 != 0, axis=2) if motion_model not in ("truth", "affine") else None,
            report=report,
            layers=layers,
        )
        name = "vet-deblur"
        params = {"fuse_still": "auto" if opts.fuse_still is None else bool(opts.fuse_still)}
        extra = {"still_pixels": report["still_pixels"]}
        if obs.yb is not None:
            extra["fit_bins"] = len(obs.windows_b)
    else:
        from .paper import PaperOptions, deblur_paper

        opts = options if options is not None else PaperOptions()
        obs = observations(cap, use_measure=False)
        L, vel = deblur_paper(
            obs,
            *start,
            static,
            saturated,
            opts,
            progress=solve_progress,
            truth_cb=truth_cb,
        )
        name = "vet-deblur-paper"
        params, extra = {}, {}  # (the paper's prior smooths every pixel)
    # Pixels hdr-static could only bound keep its value (the deblur has no data there).
    L = np.where(bound_only[..., None], np.maximum(L, L_init), L)
    mask = deblur_mask(static.mask, L, L_init)
    image = reconstruction(
        cap,
        L,
        mask,
        name,
        provenance_entry("deblur", method=method, motion_init=motion_init, **params),
        motion_init=motion_init,
        motion_model=motion_model,
        runtime_s=round(time.perf_counter() - t_start, 3),
        **extra,
    )
    return image, vel
