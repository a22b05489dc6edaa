"""What both deblur methods share: the data of a capture as electrons with their noise,
the blur operators for a motion estimate, image-gradient helpers and a multi-column
preconditioned conjugate-gradient solver.

Units: the unknown image ``L0`` is in electrons per second at the VET sensor (the
physics' natural unit); :func:`stages.hdr_static.rate_to_output_units` converts the result
to scene units (simulated captures) or DN/s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse as sp

from ..cluster import solve_threads
from ..formats.capture import Capture
from ..physics import bin_may_clip
from .convolution import ConvolutionSplit, SplitOperator
from .operator import Window, blur_matrix, motion_layers, vet_windows
from .stacked import StackedOperator
from .stream import StreamTerm


@dataclass
class Observations:
    """A capture's data in electrons, with inverse-variance weights.

    Attributes
    ----------
    y : ndarray of shape (H W, C)
        VET image minus the dark current, electrons.
    w : ndarray of shape (H W, C)
        Inverse variance (Poisson-Gaussian: signal + read + quantisation); 0 where the
        VET sensor saturated.
    yb : ndarray of shape (B H W, C) or None
        Measuring bins minus the dark current, electrons (at the measurement sensor);
        (B Hm Wm, C) on a real rig's camera grid (``sampling``).
    wb : ndarray of the shape of ``yb`` or None
        Their inverse variances; 0 where a subframe of the bin clipped.
    windows_b : list of list of Window
        Exposure windows of each bin (light fraction as weight).
    stream_src : tuple or None
        ``(measure (K, H, W, C) DN, times (K, 2) s, rig)``: a capture's whole measuring
        stream, observed through :mod:`stages.deblur.stream` (then ``yb`` is None: the
        subframes replace the bins, which would count the same light twice).
    stream : StreamTerm or None
        The stream's term for the current motion (built from ``stream_src``, or given:
        a coarse level's).
    sampling : scipy CSR of shape (Hm Wm, H W) or None
        A real rig's measurement camera (:meth:`stages.optics.MeasureGeometry.operator`
        times its vignetting): ``yb``, ``wb`` then lie on the camera's own grid, B rows
        of Hm Wm pixels, and each bin's operator is this matrix times the bin's blur
        (:func:`build_operators`). None: the bins lie on the VET grid.
    """

    shape: tuple[int, int, int]
    y: np.ndarray
    w: np.ndarray
    windows: list[Window]
    yb: np.ndarray | None
    wb: np.ndarray | None
    windows_b: list[list[Window]]
    stream_src: tuple | None = None
    stream: StreamTerm | None = None
    sampling: sp.csr_matrix | None = None
    #: (Hm, Wm): the camera's grid, with ``sampling``.
    meas_shape: tuple[int, int] | None = None


#: Fewest time bins the misfit reads of a capture that keeps its whole measuring stream
#: (twice the motion estimate's), and the most (:func:`fit_bins`).
FIT_BINS = 16
FIT_BINS_MAX = 64
#: Largest distance (px) the fastest motion may travel within one fit bin.
FIT_BIN_TRAVEL_PX = 0.5
#: Most fit bins times pixels: the bins' operators and their products grow with both, so
#: a large frame takes fewer bins (at least :data:`FIT_BINS`).
FIT_BIN_PIXELS = 1 << 24
#: Most samples of the bins' operators (per pixel, summed over the bins) times pixels
#: (:func:`bin_step`).
FIT_SAMPLE_PIXELS = 1 << 25
#: Finest and coarsest spacing (px along the motion) of the samples within a fit bin.
BIN_STEP_FINE = 0.2
BIN_STEP_COARSE = 1.5
#: Coarsest spacing of the VET image's samples (:func:`vet_step`; the finest is a fit
#: bin's).
VET_STEP_COARSE = 1.0


def fit_bins(
    max_speed_px_s: float, span_s: float, n_subframes: int, pixels: int | None = None
) -> int:
    """Time bins the misfit reads of a stream capture whose fastest motion is
    ``max_speed_px_s`` over a frame of ``span_s`` seconds and ``n_subframes`` subframes,
    ``pixels`` in all (H W).

    A bin sums its subframes at fixed pixels, so a motion blurs it by the distance it
    travels within the bin; the model states that blur, but what it removed from the
    data (detail finer than the travel, attenuated below the noise) no model brings
    back, while a burst merge aligns each subframe on its own. Bins short enough that
    the fastest motion travels at most :data:`FIT_BIN_TRAVEL_PX` within one keep that
    detail; the read noise they carry in all is the same whatever the binning (one per
    subframe). At least :data:`FIT_BINS`; at most :data:`FIT_BINS_MAX`, and
    :data:`FIT_BIN_PIXELS` over ``pixels`` (a compute budget: the operators' cost grows
    with bins times pixels), and bins of two subframes at least (a stream binned into
    single subframes would be the stream itself).
    """
    travel = max(float(max_speed_px_s), 0.0) * max(float(span_s), 0.0)
    n = int(np.ceil(travel / FIT_BIN_TRAVEL_PX)) if np.isfinite(travel) else FIT_BINS_MAX
    most = FIT_BINS_MAX if not pixels else min(FIT_BINS_MAX, FIT_BIN_PIXELS // int(pixels))
    return int(min(max(n, FIT_BINS), max(most, FIT_BINS), max(int(n_subframes) // 2, 1)))


def bin_step(max_speed_px_s: float, span_s: float, n_bins: int, pixels: int) -> float:
    """Spacing (px along the motion) of the samples of each fit bin's operator, for a
    frame of ``pixels`` (H W) whose fastest motion is ``max_speed_px_s`` over ``span_s``
    seconds, fitted through ``n_bins`` bins.

    A bin sums its subframes, each the scene at its own position (the simulator samples
    each at its mid-time); one sample per bin at the bin's mean position is a different
    blur (bilinear weights do not average linearly over sub-pixel shifts), an error that
    grows with the travel within a bin and varies with how the bins fall on the
    subframes. Samples :data:`BIN_STEP_FINE` apart (capped at one per subframe by the
    operator) make the bins' model the simulator's; that costs about ``travel / step``
    samples per pixel over all bins besides one per bin, so the spacing is as fine as
    :data:`FIT_SAMPLE_PIXELS` allows for the frame, and at most :data:`BIN_STEP_COARSE`.
    """
    travel = max(float(max_speed_px_s), 0.0) * max(float(span_s), 0.0)
    if not np.isfinite(travel):
        return BIN_STEP_COARSE
    allowed = FIT_SAMPLE_PIXELS / max(int(pixels), 1) - int(n_bins)
    step = travel / max(allowed, 1.0)
    return float(min(max(step, BIN_STEP_FINE), BIN_STEP_COARSE))


def vet_step(max_speed_px_s: float, span_s: float, pixels: int, along_path: bool) -> float:
    """Spacing (px along the motion) of the samples of the VET image's operator, for a
    frame of ``pixels`` (H W) whose fastest motion is ``max_speed_px_s`` over ``span_s``.

    A VET pixel sums the subframes it is open for, each the scene at its own position,
    as a fit bin does (:func:`bin_step`). Along a measured camera path (``along_path``)
    the path's anchor ``D(0)`` is fitted from the earliest samples, many of them bright
    VET pixels closed after a few subframes, whose one sample at the window's middle
    would bias it: there samples :data:`BIN_STEP_FINE` apart (at most one per subframe,
    by the operator) make the model the simulator's, within the
    :data:`FIT_SAMPLE_PIXELS` budget for the frame. Otherwise :data:`VET_STEP_COARSE`:
    with estimated layers (their velocities and boundaries a little off) the finer
    model fits worse (``make evaluate-stream``, the object rows).
    """
    if not along_path:
        return VET_STEP_COARSE
    travel = max(float(max_speed_px_s), 0.0) * max(float(span_s), 0.0)
    if not np.isfinite(travel):
        return VET_STEP_COARSE
    step = travel / max(FIT_SAMPLE_PIXELS / max(int(pixels), 1), 1.0)
    return float(min(max(step, BIN_STEP_FINE), VET_STEP_COARSE))


def observations(
    cap: Capture,
    use_measure: bool = True,
    stream: bool = False,
    n_bins: int = FIT_BINS,
    measure_grid: bool = True,
) -> Observations:
    """Turn a capture into electrons and noise weights (see :class:`Observations`).

    A capture with time bins is observed through its bins. One that keeps its whole
    measuring stream (:attr:`Capture.keeps_stream`) is observed through ``n_bins`` time
    bins of it (sums of its subframes, each bin's variance carrying one read noise per
    subframe; :func:`fit_bins` says how many a motion needs), or with ``stream`` through
    the stream's aligned mean (``stream_src``, :mod:`stages.deblur.stream`; experimental:
    on textured scenes and moving objects it still loses to the bins).

    A real rig's measurement camera (not the VET sensor's grid) has its bins observed on
    its own grid through its sampling (``Observations.sampling``) with ``measure_grid``;
    without, or when they were registered already, on the VET grid
    (:func:`stages.measure_grid.register_measure`: a stream interpolated, bins inverted
    through the sampling). A tile of a frame brings its camera pixels with it
    (``cap.camera_bins``, :class:`stages.deblur.camera_grid.CameraBins`), observed in place
    of its registered ``measure``.
    """
    rig = cap.rig
    g = rig.gain_dn_per_e
    h, w, c = cap.I.shape
    tf = float(cap.meta.get("integration_s", rig.frame_s))
    q = 1.0 / (12.0 * g * g)
    e = cap.I.astype(np.float64) / g
    y = e - rig.dark_current_e_s * tf
    wt = np.maximum(e, 0)
    del e
    wt += rig.read_noise_e**2 + q
    np.divide(1.0, wt, out=wt)  # inverse variance
    wt[cap.I >= np.float32(rig.saturation_dn)] = 0.0  # clipped: as hdr-static tests it
    wins = vet_windows(effective_T(cap, tf), tf, rig.subframe_s, rig.n_subframes, rig.leakage)
    yb = wb = None
    wins_b: list[list[Window]] = []
    if use_measure and cap.keeps_stream and not stream:
        cap = cap.time_bins(n_bins)
    # A real rig's bins stay on the measurement camera's grid, observed through its
    # sampling, at its gain (measure_grid); else they come onto the VET grid.
    camera = cap.camera_bins if measure_grid and use_measure else None
    g_bins = g
    if (
        camera is None
        and measure_grid
        and use_measure
        and not rig.ideal_geometry
        and cap.measure is not None
        and not cap.keeps_stream
        and cap.measure_noise is None
    ):
        from .camera_grid import CameraBins

        camera = CameraBins.of(rig, cap.measure)
    if camera is not None:
        g_bins = g * rig.measure_gain
    elif not rig.ideal_geometry and cap.measure is not None:
        from ..measure_grid import register_measure

        # Onto the VET grid with their noise: bins inverted through the camera's
        # sampling (interpolation would smooth them), a stream interpolated.
        cap = register_measure(cap, fit=not cap.keeps_stream)
    # A stream observed whole (the subframes replace the bins), or the bins.
    stream_src = (cap.measure, cap.measure_times, rig) if use_measure and cap.keeps_stream else None
    if (
        stream_src is None
        and use_measure
        and cap.measure is not None
        and cap.measure_times is not None
        and cap.measure.shape[0] > 0
    ):
        bins = cap.measure if camera is None else camera.measure
        nb, m = bins.shape[0], bins.shape[1] * bins.shape[2]
        n_sub, dur, wins_b = bin_timing(cap)
        shot_k = read_k = 1.0
        if camera is None and cap.measure_noise is not None:  # registered: interpolated
            shot_k, read_k = (v.astype(np.float64)[..., None] for v in cap.measure_noise)
        read = rig.read_noise_e**2 + 1.0 / (12.0 * g_bins * g_bins)
        import cv2

        # One bin at a time into float32 (B M, C) for M pixels of the bins' grid: no
        # float64 copy of all the bins.
        yb = np.empty((nb * m, c), np.float32)
        wb = np.empty((nb * m, c), np.float32)
        for b in range(nb):
            rows = slice(b * m, (b + 1) * m)
            eb = bins[b].astype(np.float64) / g_bins
            # Shot noise from the count smoothed over 3 x 3 pixels, not the pixel's own:
            # weights from each noisy count favour the low ones, a bias that grows as
            # bins get shorter.
            wbb = cv2.blur(np.maximum(eb, 0), (3, 3), borderType=cv2.BORDER_REPLICATE)
            wbb = wbb.reshape(eb.shape)  # (cv2 drops a single channel's axis)
            wbb *= shot_k
            wbb += n_sub[b] * read * read_k
            np.divide(1.0, wbb, out=wbb)  # inverse variance
            wbb[bin_may_clip(bins[b] / np.float32(n_sub[b]), rig)] = 0.0
            if camera is not None:
                wbb[~camera.valid] = 0.0  # (a tile's: pixels that see past it)
            wb[rows] = wbb.reshape(-1, c)
            del wbb
            eb -= rig.dark_current_e_s * dur[b]
            yb[rows] = eb.reshape(-1, c)
    return Observations(
        (h, w, c),
        y.reshape(h * w, c),
        wt.reshape(h * w, c),
        wins,
        yb,
        wb,
        wins_b,
        stream_src=stream_src,
        sampling=None if camera is None else camera.sampling,
        meas_shape=None if camera is None else camera.shape,
    )


def bin_timing(cap: Capture) -> tuple[np.ndarray, np.ndarray, list[list[Window]]]:
    """Per measuring bin: its subframes, the seconds it exposed, and its window (the light
    fraction as weight; a bin with a dropped subframe saw its span's light for fewer
    subframes, which leaves a gap in it)."""
    rig = cap.rig
    span = np.diff(cap.measure_times, axis=1)[:, 0]
    n_sub = cap.measure_counts().astype(np.float64)
    dur = n_sub * rig.subframe_s
    dur = np.where(n_sub == np.maximum(np.rint(span / rig.subframe_s), 1), span, dur)
    wins = [
        [Window(float(t0), float(t1), float(rig.measure_fraction * dur[b] / span[b]))]
        for b, (t0, t1) in enumerate(cap.measure_times)
    ]
    return n_sub, dur, wins


def effective_T(cap: Capture, tf: float) -> np.ndarray:
    """The exposure time the windows of the VET image take, (H, W) float32: the capture's
    T, or through a real rig's LCoS (switching ramp, per-cell leakage, relay blur:
    :func:`stages.optics.vet_exposure`) the T of the ideal shutter (mean leakage) that
    exposes a still pixel alike."""
    rig = cap.rig
    if not cap.models_lcos:
        return cap.T
    if cap.ideal_T is not None:
        return cap.ideal_T
    from ..optics import capture_leakage, vet_exposure

    eps_px = capture_leakage(rig, cap.shape, cap.cell_leakage)
    e = vet_exposure(cap.T, eps_px, tf, rig).astype(np.float64)
    t = (e - rig.leakage * tf) / (1.0 - rig.leakage)
    return np.clip(t, 0.0, tf).astype(np.float32)


def build_operators(
    obs: Observations,
    velocity: np.ndarray,
    step_px: float = 1.0,
    step_px_bins: float = 1.5,
    subframe_s: float | None = None,
    layers=None,
    lean: bool = True,
) -> tuple[sp.csr_matrix | SplitOperator, StackedOperator | None]:
    """Blur operators of the VET image and of the measuring bins for a motion
    (``layers``: the motion as :class:`~stages.deblur.operator.Layers` when the caller
    has them, e.g. with trajectories; else read from ``velocity``). Bins observed through
    a camera's sampling (``obs.sampling``) get its product with each blur.

    ``lean``: each operator whose assembly's plan has convolutions worth it
    (:mod:`stages.deblur.convolution`) is made as them and the rows they miss, its matrix
    never made (the VET image's as a :class:`~stages.deblur.convolution.SplitOperator`);
    else every operator is a matrix (the VET image's with its split beside it)."""
    from concurrent.futures import ThreadPoolExecutor

    if layers is None:
        layers = motion_layers(velocity)  # once for all the operators of this motion
    # The VET image's operator alone (its assembly's temporaries are the largest), then
    # the bins' on two threads: numpy work that mostly releases the GIL, whose
    # temporaries are small.
    # Its rows that are convolutions, applied as such (the groups of its assembly's plan:
    # an exposure time and a layer each; found among the rows they are rarely common
    # enough to pay for the search).
    A = blur_matrix(
        velocity,
        obs.windows,
        step_px=step_px,
        min_dt=subframe_s,
        layers=layers,
        split_shape=obs.shape[:2] if lean else None,
    )
    if isinstance(A, ConvolutionSplit):
        A = SplitOperator(A)
    else:  # (None where none are)
        A.convolution = ConvolutionSplit.of(A, obs.shape[:2], detect=False)
    if obs.yb is None:
        return A, None
    shape = obs.shape[:2] if obs.sampling is None else None

    def one_bin(wins, split=lean):
        # A bin's operator as convolutions, its matrix never made, where its assembly's
        # plan allows; else the matrix and, found among its rows, its split.
        M = blur_matrix(
            velocity,
            wins,
            step_px=step_px_bins,
            min_dt=subframe_s,
            layers=layers,
            split_shape=shape if split else None,
        )
        if isinstance(M, ConvolutionSplit):
            return M, M
        return M, None if shape is None else ConvolutionSplit.of(M, shape)

    with ThreadPoolExecutor(max_workers=min(2, solve_threads())) as pool:
        made = list(pool.map(one_bin, obs.windows_b))
        if not made:
            return A, None
        lean = [m for m, _ in made if isinstance(m, ConvolutionSplit)]
        if lean and len(lean) == len(made):  # (every bin as convolutions: no matrix held)
            return A, StackedOperator(lean)
        del lean
        if any(isinstance(m, ConvolutionSplit) for m, _ in made):  # (rarely: matrices for all)
            made = list(pool.map(lambda wins: one_bin(wins, split=False), obs.windows_b))
    mats, splits = [m for m, _ in made], [s for _, s in made]
    del made
    if obs.sampling is None:
        return A, StackedOperator(mats, image_shape=shape, splits=splits, release=True)
    return A, StackedOperator([(obs.sampling @ M).tocsr() for M in mats], mats)


def grad(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward differences of ``(H, W, C)`` (zero at the far border)."""
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, :-1] = img[:, 1:] - img[:, :-1]
    gy[:-1] = img[1:] - img[:-1]
    return gx, gy


def grad_adjoint(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Adjoint of :func:`grad` (minus the divergence)."""
    out = np.zeros_like(gx)
    out[:, :-1] -= gx[:, :-1]
    out[:, 1:] += gx[:, :-1]
    out[:-1] -= gy[:-1]
    out[1:] += gy[:-1]
    return out


def laplacian(img: np.ndarray) -> np.ndarray:
    """5-point Laplacian with replicated borders, ``(H, W, ...)``."""
    p = np.pad(img, [(1, 1), (1, 1)] + [(0, 0)] * (img.ndim - 2), mode="edge")
    return p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * img


def _row_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each row's dot product of two (C, N) arrays, (C,) (no (C, N) temporary)."""
    return np.einsum("ij,ij->i", a, b)


def pcg(
    apply_h: Callable[[np.ndarray], np.ndarray],
    b: np.ndarray,
    x0: np.ndarray,
    diag: np.ndarray,
    iters: int,
    tol: float = 1e-6,
    callback: Callable[[int, np.ndarray], None] | None = None,
    free: np.ndarray | None = None,
) -> np.ndarray:
    """Jacobi-preconditioned conjugate gradients, each row an independent system.

    Parameters
    ----------
    apply_h : callable
        ``x -> H x`` for ``x`` of the shape of ``b`` (H symmetric positive definite per
        row).
    b, x0, diag : ndarray of shape (C, N)
        Right-hand side, start, and the diagonal of H (preconditioner): a channel's
        unknowns contiguous, so that the vector updates and dot products run along them.
    iters : int
        Iterations.
    tol : float
        Stop when every row's preconditioned residual norm, ``sqrt(r M^-1 r)`` with ``M``
        the diagonal, falls below ``tol`` times its start.
    callback : callable, optional
        ``callback(k, x)`` after iteration ``k`` with the current ``x`` (C, N).
    free : ndarray of shape (N,), bool, optional
        Only these unknowns change (the others keep ``x0``): the system solved is ``H``
        restricted to them, with the fixed ones' contribution on the right-hand side.
    """
    x = x0.copy()
    r = b - apply_h(x)
    minv = 1.0 / np.maximum(diag, 1e-300)
    if free is not None:
        keep = free.reshape(1, -1)
        minv *= keep
        r *= keep
    z = minv * r
    p = z.copy()
    rz = _row_dots(r, z)
    stop = tol * tol * rz
    for k in range(iters):
        hp = apply_h(p)
        php = _row_dots(p, hp)
        alpha = np.where(php > 0, rz / np.where(php > 0, php, 1), 0.0)
        for c in range(x.shape[0]):  # (fused multiply-adds, in place, row by row)
            cv2.scaleAdd(p[c], float(alpha[c]), x[c], x[c])
            cv2.scaleAdd(hp[c], -float(alpha[c]), r[c], r[c])  # (fixed ones unread: z is 0)
        del hp
        if callback is not None:
            callback(k, x)
        np.multiply(minv, r, out=z)
        rz_new = _row_dots(r, z)
        if np.all(rz_new <= stop):
            break
        beta = np.where(rz > 0, rz_new / np.where(rz > 0, rz, 1), 0.0)
        rz = rz_new
        for c in range(p.shape[0]):  # p = z + beta p
            cv2.scaleAdd(p[c], float(beta[c]), z[c], p[c])
    return x
