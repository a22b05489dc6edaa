"""The default deblur: noise-weighted joint estimation of the sharp image and the motion.

Minimises over the scene at t = 0, ``L0`` (electrons/s), and a velocity field ``u``
(px/s; layers with occlusion or a dense field, see :mod:`stages.deblur.operator`)::

    sum_x  w(x) rho(A(u) L0 - y)^2                      VET image, Poisson-Gaussian weights
  + sum_b sum_x  w_b(x) rho(A_b(u) L0 - y_b)^2          measuring bins (less blurred, noisier)
  + lam sum_edges  P_e c_e ((L0_i - L0_j) / ref_e)^2    edge-preserving relative smoothness
  + alpha |grad u|^2                                    smooth motion
  + mu sum_bound (L0 - L_static)^2 / L_static^2         pixels only bounded keep hdr-static

by alternation: the image step is a linear least-squares problem solved with
Jacobi-preconditioned conjugate gradients (:func:`~stages.deblur.problem.pcg`), warm
started; the weights ``rho`` (Cauchy, on normalised residuals) and the smoothness's edge
weights ``c_e`` (Charbonnier on the relative gradient) are re-estimated between steps
(iteratively reweighted least squares), which discounts the pixels the motion model
cannot explain. ``P_e`` is the data precision of the edge's pixels, so ``lam`` is
dimensionless: the weight of the prior relative to one pixel's own data, and the
smoothing is the same at every brightness (a relative, log-like prior suited to HDR).
The edge weights' scale is ``edge_rel`` (relative), lowered to ``edge_snr`` times a
pixel's relative shot noise where the pixel gathered enough light for that to be
smaller, so that low-contrast texture the data resolve is not smoothed away.

Motion. The motion comes from :mod:`stages.deblur.layers` (a still background and
rigidly translating layers, with occlusion, estimated from all the measuring bins over
long baselines); a global translation's velocity is refined on the misfit between
image steps (:func:`stages.deblur.layer_steps.layer_step`), objects over a still
background keep theirs; the dense Gauss-Newton steps on ``u``
(:func:`stages.deblur.motion_steps.motion_step`) are taken only with ``update_motion=True`` (``make bench``,
bench_layers, prints the velocities found and the share of the frame given the wrong
layer). Coarse to fine:
the motion is estimated on a grid of at most
:data:`stages.deblur.layers.MAX_WORK_PX` pixels and refined coarse-to-fine in velocity,
and the layer boundaries are then placed at full resolution
(:func:`stages.deblur.layers.labels.refine_boundaries`). The image is solved first on
2 x 2 blocks (:mod:`stages.deblur.pyramid`: the exact summed rows of each
block, an eighth of the work per iteration), and hdr-static times the prolonged
(log-domain) coarse correction starts the full-resolution solve
(``JointOptions.levels``), which then needs one outer step fewer (``make bench`` prints
the error against the fine iterations).

Only the pixels that a moving integration path touches are re-estimated
(:func:`~stages.deblur.still_pixels.moving_support`). A pixel whose paths do not move
sees only its own point of the scene, and its column of every operator holds only its
own static row, so its noise-weighted maximum-likelihood value from all its data (the
VET image and the measuring bins) has a closed form
(:func:`~stages.deblur.still_pixels.fuse_still`); the VET data alone give hdr-static's.
(A real rig's bins, fitted through the measurement camera's sampling, see a still
pixel's neighbours too: there the closed form starts the still pixels and the solve
fits them, with no smoothness between two of them.) ``JointOptions.fuse_still`` decides
which a still pixel takes:

* ``None`` (the default): the fused value whenever the motion moves some pixel, and
  hdr-static's, untouched, when it moves none. A capture in which deblur finds no
  motion comes out exactly as hdr-static (deblur invents nothing on a still scene);
  one with motion is reconstructed from all its data, the moving pixels by the solve
  and the still ones by :func:`~stages.deblur.still_pixels.fuse_still`.
* ``True``: always fused, a still capture too (``vet deblur --fuse-still``).
* ``False``: never; still pixels keep hdr-static (``vet deblur --keep-still``).

``make bench`` (bench_fusion) measures what it trades: the change to hdr-static on a
still scene, and the dark-pixel and still-pixel errors of each choice on scenes with a
moving object.
Pixels the VET sensor saturated carry no weight in the VET term (clipped data) and are
estimated from the measuring bins and the paths crossing them; only those clipped in
the first bin too, for which hdr-static has no more than a lower bound, are anchored
to it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from .camera_grid import bins_on_vet_grid
from .image_step import bin_weights, solve_image
from .joint_options import JointOptions
from .operator import Layers, motion_layers
from .path_steps import robust_misfit
from .problem import (
    BIN_STEP_COARSE,
    VET_STEP_COARSE,
    Observations,
    build_operators,
)
from .stacked import diag_normal, product
from .still_pixels import fuse_still, moving_support
from .stream import StreamTerm, layer_motion, stream_term

log = logging.getLogger(__name__)


def _robust(r: np.ndarray, w: np.ndarray, k: float) -> np.ndarray:
    """Cauchy weights ``w / (1 + r^2 w / k^2)`` (in place in one temporary)."""
    z2 = r * r
    z2 = np.multiply(z2, w, out=z2 if z2.dtype == np.result_type(z2, w) else None)
    z2 /= k * k
    z2 += 1.0
    return np.divide(w, z2, out=z2)


def build_stream(src: tuple, velocity: np.ndarray, layers: Layers | None = None) -> StreamTerm:
    """The stream's term (:func:`stages.deblur.stream.stream_term`) for a motion:
    ``layers`` when given, else the velocity field read as layers or as a dense field."""
    measure, times, rig = src
    if layers is None:
        layers = motion_layers(velocity)
    return stream_term(measure, times, rig, *layer_motion(layers, velocity))


def _coarse_start(
    obs,
    L_init,
    velocity,
    T,
    frame_s,
    subframe_s,
    leakage,
    saturated,
    opts,
    progress=None,
    layers=None,
):
    """Start of the fine solve: hdr-static times the coarse level's correction (H W, C).

    ``progress(done, total)`` is the coarse solve's."""
    from dataclasses import replace

    from .pyramid import block_sum, coarsen, prolong_correction, restrict_mean

    h, wd, c = obs.shape
    h2, w2 = h // 2, wd // 2
    cobs, t_c = coarsen(obs, T, frame_s, leakage)
    if obs.stream is not None:
        cobs.stream = obs.stream.coarsen()
    L_c0 = restrict_mean(L_init.astype(np.float64))
    vel_c = (velocity[: 2 * h2 : 2, : 2 * w2 : 2] / 2.0).astype(np.float32)
    layers_c = None
    if layers is not None:
        traj = layers.trajectory
        layers_c = Layers(
            layers.label[: 2 * h2 : 2, : 2 * w2 : 2],
            layers.velocity / 2.0,
            layers.front,
            layers.background,
            trajectory=None if traj is None else (traj[0], traj[1] / 2.0),
        )
    sat_c = block_sum(saturated.astype(np.int32)) > 0
    # The coarse level only starts the moving pixels: still ones are fused, if asked, at
    # full resolution.
    copts = replace(
        opts,
        levels=opts.levels - 1,
        history=[],
        update_motion=False,
        affine_motion=False,
        path_motion=False,
        layer_motion=False,
        fuse_still=False,
    )
    L_c, _ = deblur_joint(
        cobs,
        L_c0.astype(np.float32),
        vel_c,
        t_c,
        frame_s,
        subframe_s,
        leakage,
        sat_c,
        copts,
        progress=progress,
        layers=layers_c,
    )
    # Multiplicative (log-domain) correction: an additive one, interpolated across a
    # bright edge, drives the dark pixels beside it negative.
    tiny = 1e-30
    ratio = np.log(np.maximum(L_c.astype(np.float64), tiny) / np.maximum(L_c0, tiny))
    corr = prolong_correction(ratio, (h, wd))
    return (L_init.astype(np.float64) * np.exp(corr)).reshape(h * wd, c)


def deblur_joint(
    obs: Observations,
    L_init: np.ndarray,
    velocity: np.ndarray,
    T: np.ndarray,
    frame_s: float,
    subframe_s: float,
    leakage: float,
    saturated: np.ndarray,
    opts: JointOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
    truth_cb: Callable[[np.ndarray], float] | None = None,
    still: np.ndarray | None = None,
    report: dict | None = None,
    layers: Layers | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint image and motion estimation (see the module docstring).

    Parameters
    ----------
    obs : Observations
    L_init : ndarray of shape (H, W, C)
        Start image, electrons/s (the hdr-static estimate); also the anchor of saturated
        pixels and the reference level of the relative smoothness.
    velocity : ndarray of shape (H, W, 2)
        Start motion, px/s.
    T : ndarray of shape (H, W)
        Exposure time image, seconds.
    frame_s, subframe_s, leakage : float
        Rig timing and LCoS leakage.
    saturated : ndarray of shape (H, W), bool
        Pixels for which hdr-static has only a lower bound (kept near it).
    opts : JointOptions
    progress : callable, optional
        ``progress(done, total)`` after each step.
    truth_cb : callable, optional
        Called with the image (H, W, C) after each image step; its return value is
        logged with the iteration in ``opts.history`` (benchmarks: error vs iterations).
    still : ndarray of shape (H, W), bool, optional
        Pixels known to be still (their velocity stays zero through the motion steps).
    report : dict, optional
        Filled with ``still_pixels``: what the pixels no moving path touches took,
        ``fused`` (the value of all their data, :func:`fuse_still`; see
        ``JointOptions.fuse_still``), ``hdr-static``, or ``none`` where every pixel
        moves (a global motion).
    layers : Layers, optional
        The motion as layers with their trajectories (a motion whose velocity changes
        within the frame); ``velocity`` is then their mean velocity and the motion is not
        updated.

    Returns
    -------
    L0 : ndarray of shape (H, W, C), electrons/s
    velocity : ndarray of shape (H, W, 2), px/s
    """
    import cv2

    opts = opts or JointOptions()
    h, wd, c = obs.shape
    n = h * wd
    start = None
    if report is not None:
        report["still_pixels"] = "hdr-static"
    if opts.path_motion:
        from .path_steps import PathSearch, single_path

        refine_path = single_path(layers)
        search = PathSearch()
    else:
        refine_path = False
    if refine_path:
        total = opts.path_outer + 1
    else:
        total = (opts.affine_outer if opts.affine_motion else opts.outer) + 1
    coarse = opts.levels > 0 and min(h, wd) >= 2 * opts.coarse_min_px and np.any(velocity != 0)
    # Progress counts the coarse start as `total` steps (whatever its own levels), then
    # the fine solve's steps.
    units = 2 * total if coarse else total
    if progress:
        progress(0, units)
    if coarse:
        sub = (lambda d, t: progress(d * total // max(t, 1), units)) if progress else None
        start = _coarse_start(
            obs, L_init, velocity, T, frame_s, subframe_s, leakage, saturated, opts, sub, layers
        )
    ref = np.stack(
        [cv2.GaussianBlur(L_init[..., k].astype(np.float32), (0, 0), 1.0) for k in range(c)], -1
    )
    ref = np.maximum(ref, np.percentile(ref, 1) + 1e-6).astype(np.float64)
    L = L_init.reshape(n, c).astype(np.float64)
    anchor = L.copy()
    sat = np.broadcast_to(saturated.reshape(n, 1), (n, c))
    anchor_w = np.where(sat, 1.0 / (0.01 * np.maximum(anchor, 1e-30)) ** 2, 0.0)
    vel = velocity.astype(np.float32)
    w, wb, ws = obs.w, obs.wb, None
    # Noise-equivalent floor (as hdr-static's): one electron over the pixel's exposure.
    expo = np.maximum(T, leakage * frame_s + (1 - leakage) * T).reshape(n, 1)
    floor = np.broadcast_to(1.0 / expo, (n, c))
    iters_done = 0
    built_for = built_layers = None
    affine_state: dict = {}
    layer_state: dict = {}
    for it in range(total):
        t0 = time.perf_counter()
        if built_for is None or not np.array_equal(built_for, vel) or layers is not built_layers:
            A, Ab = build_operators(
                obs,
                vel,
                step_px=opts.step_px or VET_STEP_COARSE,
                step_px_bins=opts.step_px_bins or BIN_STEP_COARSE,
                subframe_s=subframe_s,
                layers=layers,
            )
            if obs.stream_src is not None:
                obs.stream = build_stream(obs.stream_src, vel, layers)
            S = obs.stream
            free = moving_support(A, Ab, S)
            built_for = vel.copy()
            built_layers = layers
            # Preconditioner from the noise weights (the robust reweighting only lowers
            # them; the preconditioner need not follow exactly).
            data_diag = diag_normal(A, obs.w)
            if Ab is not None:
                data_diag += Ab.diag_normal(obs.wb)
            if S is not None:
                data_diag += S.diag_normal(S.w)
                ws = S.w
            if start is not None:
                L = np.where(free[:, None], np.maximum(start, floor), L)
                start = None
            fusing = (Ab is not None or S is not None) and (
                opts.fuse_still if opts.fuse_still is not None else bool(free.any())
            )
            fuse = ~free & ~saturated.reshape(n) if fusing else None
            if fusing and fuse.any():  # (a global motion leaves no pixel to fuse)
                L[fuse] = np.maximum(fuse_still(obs, A, Ab, data_diag, fuse, L[fuse]), floor[fuse])
            still_px = None
            if obs.sampling is not None and fusing and fuse.any():
                # Through a camera's sampling a still pixel's bins also see its
                # neighbours: the closed form above only starts it; the solve fits it.
                still_px, free = fuse, free | fuse
            if report is not None:
                report["still_pixels"] = (
                    "fused" if fusing and fuse.any() else "hdr-static" if not free.all() else "none"
                )
        if not free.any():
            log.debug("deblur: no pixel's integration path moves; the result is hdr-static")
            break
        tb = time.perf_counter()
        last = it == total - 1
        cg_iters = opts.final_cg_iters if last else opts.cg_iters

        def cb(k: int, x: np.ndarray, _base=iters_done, _free=free) -> None:
            if truth_cb is not None and (k % 5 == 4):
                xf = np.where(_free[:, None], np.maximum(x, floor), x)  # as the step's result
                opts.history.append(
                    (_base + k + 1, time.perf_counter(), truth_cb(xf.reshape(h, wd, c)))
                )

        bw = wb
        if Ab is not None and wb is not obs.wb:
            # The robust weights as the solve takes them, held in that form alone.
            bw, wb = bin_weights(Ab, wb, obs.yb), None
        L = solve_image(
            obs,
            A,
            Ab,
            w,
            bw,
            L,
            ref,
            anchor,
            anchor_w,
            opts,
            cg_iters,
            expo,
            callback=cb,
            free=free,
            data_diag=data_diag,
            ws=ws,
            still=still_px,
        )
        del bw
        iters_done += cg_iters
        L = np.where(free[:, None], np.maximum(L, floor), L)
        ts = time.perf_counter()
        if not last or refine_path:  # (the residuals of the image step's result)
            r = product(A, L).astype(np.float64) - obs.y
            rb = None
            if Ab is not None:
                rb = Ab.mv(L)
                rb -= obs.yb
            if refine_path:  # (the best state so far, this one or an earlier one)
                fit = robust_misfit(r, obs.w, rb, obs.wb, opts.cauchy_k)
                L, layers, r, rb, kept = search.keep_best(fit, L, layers, r, rb)
                if not kept:
                    vel = layers.velocity[layers.label].astype(np.float32)
                    log.debug("deblur: path step %d fitted worse; back to the best path", it)
        if not last:  # (the robust weights and the motion step serve the next solve)
            w = _robust(r, obs.w, opts.cauchy_k)
            if Ab is not None:
                wb = _robust(rb, obs.wb, opts.cauchy_k)
            if S is not None:
                ws = _robust(S.apply(L) - S.y, S.w, opts.cauchy_k)
            rb, wb_v = bins_on_vet_grid(obs.sampling, obs.shape, rb, wb)
            if refine_path:
                from .path_steps import anchor_image, path_step

                layers, d0 = path_step(obs, L, layers, r, w, rb, wb_v, frame_s, search.gain)
                if np.any(d0 != 0):  # (the residuals are the model's: it is unchanged)
                    L = anchor_image(L, (h, wd, c), d0)
                vel = layers.velocity[layers.label].astype(np.float32)
            elif opts.affine_motion and layers is None:
                from .affine import affine_step

                vel = affine_step(
                    obs, L, vel, r, w, rb, wb_v, T, frame_s, leakage, opts, affine_state
                )
            elif opts.layer_motion and layers is None:
                from .layer_steps import layer_step

                vel = layer_step(
                    obs, L, vel, r, w, rb, wb_v, T, frame_s, leakage, opts, layer_state
                )
            elif opts.update_motion:
                from .motion_steps import motion_step

                vel = motion_step(obs, L, vel, r, w, rb, wb_v, T, frame_s, leakage, opts)
                if still is not None:
                    vel[still] = 0.0
            del r, rb, wb_v  # (not held through the next solve)
        log.debug(
            "deblur: step %d build %.1fs solve %.1fs motion %.1fs",
            it,
            tb - t0,
            ts - tb,
            time.perf_counter() - ts,
        )
        if progress:
            progress(units - total + it + 1, units)
    if progress:  # (also when no pixel moves and the loop stopped early)
        progress(units, units)
    return L.reshape(h, wd, c).astype(np.float32), vel
