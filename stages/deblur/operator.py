"""The forward blur operator of a VET capture and its exact adjoint.

Model (DESIGN.md §1, with a per-pixel constant velocity ``u(x)`` px/s so that the image
motion is ``D(x, t) = u(x) t``)::

    I(x)/g - d W  =  sum_s  w_s(x) L0(x - u(x) t_s(x))

where ``L0`` is the scene at t = 0 (electrons per second at the VET sensor) and the
samples ``s`` discretise the pixel's exposure windows: its cell is open (weight 1) over
the subframes before its closure time ``T(x)`` and leaks (weight ``eps``) over the rest
of the frame, including the tail after the last whole subframe. Each window is split into
``n`` groups of consecutive subframes, each group represented by one sample at its mean
time with weight equal to its duration; ``n`` is chosen per pixel so that the samples lie
at most ``step_px`` apart along the trajectory. With ``step_px`` small enough to give one
sample per subframe the model is exactly :func:`stages.simulate.simulate`'s (which samples
the scene at each subframe's mid-time); coarser grouping replaces the motion inside a
group by its mean position, an error far below the bilinear interpolation's.

``L0`` is sampled bilinearly at positions rounded to 1/32 px (OpenCV's interpolation
grid, on which the simulator's warps sample), with coordinates reflected at the image
border (OpenCV's ``BORDER_REFLECT``, as the simulator renders translations).

Layered motion with occlusion. A velocity field with only a few distinct values (at
most :data:`MAX_LAYERS`: a global translation, a still background with moving objects,
the layered estimate of :mod:`stages.deblur.layers`, or the simulator's true motion) is
read as **layers on the t = 0 grid**: the scene point ``y`` of layer ``k`` (``label(y) =
k``) is at ``y + v_k t`` at time ``t``. A pixel ``x`` then sees, at each sample time, the
front-most layer that covers it, ``k`` such that ``label(x - v_k t) = k`` (moving layers
smaller in front of larger; a layer does not cover a pixel from outside the image), and
the background layer (the largest, reflected at the border like a global translation)
where none does. This models occlusion and
disocclusion exactly where a per-pixel constant velocity cannot: a still pixel that an
object passes over integrates the object while it is covered, and the pixels an object
uncovers show the background. A field with many distinct values (dense optical flow)
keeps the per-pixel reading ``L0(x - u(x) t)``.

The operator is a :class:`scipy.sparse.csr_matrix` of shape ``(H W, H W)`` (rows:
observed pixels, columns: pixels of ``L0``) built once per motion estimate; its adjoint
is the transpose, exact by construction. Several channels share it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .assembly import (
    POSITION_STEPS,
    Growing,
    chunks,
    corners,
    expand_stencils,
    moved,
    near_half,
    stencil_groups,
    sum_rows,
)
from .convolution import ConvolutionSplit, SplitOperator

#: A velocity field with at most this many distinct values is read as layers.
MAX_LAYERS = 8


@dataclass
class Layers:
    """A velocity field as layers on the t = 0 grid (see the module docstring).

    Attributes
    ----------
    label : ndarray of shape (H, W), int32
        Layer of each scene point at t = 0.
    velocity : ndarray of shape (K, 2), float64
        Velocity of each layer, px/s.
    front : list of int
        Layers tested front to back (every layer but the background).
    background : int
        The layer seen where no other one covers a pixel.
    """

    label: np.ndarray
    velocity: np.ndarray
    front: list[int]
    background: int
    trajectory: tuple[np.ndarray, np.ndarray] | None = None

    def displacement(self, t: np.ndarray | float) -> np.ndarray:
        """Each layer's displacement at time(s) ``t``: (K, 2) for a scalar ``t``, else
        (K, ..., 2) px. ``velocity * t`` unless a ``trajectory`` ``(times (M,), disp
        (K, M, 2))`` is given, which is interpolated linearly (held past its ends)."""
        t = np.asarray(t, np.float64)
        if self.trajectory is None:
            return self.velocity.reshape(-1, *([1] * t.ndim), 2) * t[..., None]
        times, disp = self.trajectory
        out = np.empty((disp.shape[0], *t.shape, 2))
        for k in range(disp.shape[0]):
            for a in range(2):
                out[k, ..., a] = np.interp(t, times, disp[k, :, a])
        return out

    def max_speed(self) -> float:
        """Fastest speed of any layer at any time, px/s."""
        if self.trajectory is None:
            return float(np.hypot(self.velocity[:, 0], self.velocity[:, 1]).max())
        times, disp = self.trajectory
        if len(times) < 2:
            return 0.0
        v = np.diff(disp, axis=1) / np.maximum(np.diff(times), 1e-12)[None, :, None]
        return float(np.hypot(v[..., 0], v[..., 1]).max())


def motion_layers(velocity: np.ndarray, max_layers: int = MAX_LAYERS) -> Layers | None:
    """Read a velocity field with few distinct values as :class:`Layers`, else None."""
    h, w = velocity.shape[:2]
    flat = np.ascontiguousarray(velocity.reshape(-1, 2), np.float32)
    first = flat[0]
    if np.all(flat == first):
        return Layers(np.zeros((h, w), np.int32), first.astype(np.float64)[None], [], 0)
    # Distinct values without sorting the whole field when there are many.
    sample = np.unique(flat[:: max(1, flat.shape[0] // 4096)], axis=0)
    if len(sample) > max_layers:
        return None
    vals, inv, counts = np.unique(flat, axis=0, return_inverse=True, return_counts=True)
    if len(vals) > max_layers:
        return None
    bg = int(np.argmax(counts))
    front = [int(k) for k in np.argsort(counts, kind="stable") if k != bg]
    return Layers(inv.reshape(h, w).astype(np.int32), vals.astype(np.float64), front, bg)


@dataclass
class Window:
    """One exposure window per pixel: ``[start, end)`` seconds with a weight.

    Attributes
    ----------
    start, end : ndarray of shape (H, W) or float
        Window bounds in seconds (``end <= start`` means empty).
    weight : ndarray of shape (H, W) or float
        Transmittance over the window (1 open, ``eps`` closed, or a light fraction).
    """

    start: np.ndarray | float
    end: np.ndarray | float
    weight: np.ndarray | float


def vet_windows(
    T: np.ndarray, frame_s: float, subframe_s: float, n_subframes: int, leakage: float
) -> list[Window]:
    """Exposure windows of the VET sensor: open until ``T``, leaking after it.

    The tail after the last whole subframe is its own window so that its sample sits at
    its own mid-time, as in the simulator.
    """
    t_grid = n_subframes * subframe_s
    T = np.asarray(T, np.float64)
    open_end = np.minimum(T, t_grid)
    wins = [Window(0.0, open_end, 1.0), Window(open_end, t_grid, float(leakage))]
    if frame_s - t_grid > 1e-9:
        tail_open = T >= frame_s * (1 - 1e-6)
        wins.append(Window(t_grid, frame_s, np.where(tail_open, 1.0, float(leakage))))
    return wins


def blur_matrix(
    velocity: np.ndarray,
    windows: Sequence[Window],
    step_px: float = 1.0,
    max_samples: int = 64,
    min_dt: float | None = None,
    layers: Layers | None | str = "read",
    split_shape: tuple[int, int] | None = None,
) -> sp.csr_matrix | ConvolutionSplit:
    """Assemble the blur operator for one image as a sparse matrix.

    Parameters
    ----------
    velocity : ndarray of shape (H, W, 2)
        Per-pixel velocity ``(u, v)`` in px/s; ``D(x, t) = u(x) t``.
    windows : sequence of Window
        Exposure windows summed into each observed pixel.
    step_px : float
        Largest distance along the trajectory between two samples of a window, pixels.
    max_samples : int
        Cap on samples per pixel and window.
    min_dt : float, optional
        Shortest time a sample may represent (e.g. one subframe: no point in resolving
        motion within one); default none.
    layers : Layers or None, optional
        ``motion_layers(velocity)`` when the caller has it (several operators of one
        motion), or the motion's layers along their trajectories; by default it is read
        here. One layer without a trajectory says the velocity is the same everywhere.

    split_shape : (H, W), optional
        The image's shape, to return the operator as shifted convolutions and the rows
        they miss (:class:`~stages.deblur.convolution.ConvolutionSplit`) where its
        assembly's plan has kernels worth it: only those other rows are assembled, the
        matrix is never made. Otherwise, and by default, the matrix.

    Returns
    -------
    scipy.sparse.csr_matrix of shape (H W, H W), float32
        ``y = A @ L0.ravel()`` gives the model's electrons for each pixel when ``L0`` is
        in electrons per second (or its split, with ``split_shape``).
    """
    h, w = velocity.shape[:2]
    n = h * w
    if isinstance(layers, str):
        layers = motion_layers(velocity)
    by_layer = layers is not None and (len(layers.velocity) > 1 or layers.trajectory is not None)
    flat = velocity.reshape(n, 2)
    # Per-pixel numbers are kept as one number where they are alike everywhere (a uniform
    # velocity, a window given as one number), read through (N,) views of stride 0.
    # (One layer that is not along a path: motion_layers found every value the same.)
    uniform = not by_layer and n > 0 and (layers is not None or bool(np.all(flat == flat[0])))
    vel = flat[:1] if uniform else flat
    vel = vel.astype(np.float64)
    vx, vy = vel[:, 0], vel[:, 1]
    if by_layer:
        # Samples along the fastest layer's path: any layer may cover the pixel.
        speed = np.float64(layers.max_speed())
    else:
        speed = np.hypot(vx, vy)
    wins = []
    per_px = np.zeros(1 if uniform else n, np.int64)
    for win in windows:
        a, b, wt = (np.asarray(v, np.float64).reshape(-1) for v in (win.start, win.end, win.weight))
        dur = np.maximum(b - a, 0.0)
        ns = np.ceil(speed * dur / step_px).astype(np.int64)
        if min_dt:
            ns = np.minimum(ns, np.maximum(np.floor(dur / min_dt), 1).astype(np.int64))
        ns = np.clip(ns, 1, max_samples)
        ns = np.where((dur <= 0) | (wt == 0), 0, ns)
        per_px = per_px + ns
        wins.append(tuple(np.broadcast_to(v, (n,)) for v in (a, dur, wt, ns)))
    per_px = np.broadcast_to(per_px, (n,))
    vx, vy = (None, None) if by_layer else (np.broadcast_to(v, (n,)) for v in (vx, vy))
    del vel, flat
    motion = (vx, vy, layers if by_layer else None)
    plan = None if by_layer else _stencil_plan(vx, vy, windows, wins, h, w)
    if plan is not None:
        s_rows, s_gid, reps = plan
        r_cols, r_vals, r_counts, tie = _row_entries(reps, wins, motion, h, w, ties=True)
        if not tie.any():  # (else, rarely, every row one by one)
            generic = np.ones(n, bool)
            generic[s_rows] = False
            g_rows = np.flatnonzero(generic)
            del generic
            parts = [
                _row_entries(g_rows[i0:i1], wins, motion, h, w) for i0, i1 in chunks(per_px[g_rows])
            ]
            g_parts = [np.concatenate([p[i] for p in parts]) for i in range(3)] if parts else []
            del parts
            if not g_parts:
                g_parts = [np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0, np.int64)]
            generic = (g_rows, g_parts[2], g_parts[0], g_parts[1])
            # (What the matrix is made of, for its split into convolutions:
            # stages.deblur.convolution.)
            stencils = Stencils(s_rows, s_gid, reps, r_counts, r_cols, r_vals)
            if split_shape is not None:
                nnz = np.zeros(n, np.int64)
                nnz[g_rows] = g_parts[2]
                nnz[s_rows] = r_counts[0] if len(reps) == 1 else r_counts[s_gid]
                split = ConvolutionSplit.of_plan(
                    nnz,
                    stencils,
                    split_shape,
                    lambda left, rest: expand_stencils(
                        n,
                        generic,
                        (s_rows[left], s_gid[left], reps, r_counts, r_cols, r_vals),
                        rows=rest,
                    ),
                )
                if split is not None:
                    return split
            M = expand_stencils(n, generic, (s_rows, s_gid, reps, r_counts, r_cols, r_vals))
            M.stencils = stencils
            return M
    # Row by row, in chunks of pixels. The index and value arrays grow geometrically, a
    # few large blocks (not one small part per chunk kept alive among the chunks'
    # temporaries, which fragments the heap). (Column indices are below n: int32 for any
    # frame under 2**31 pixels.)
    indptr = np.zeros(n + 1, np.int64)
    out = Growing(2 * int(per_px.sum()) + 1)
    for c0, c1 in chunks(per_px):
        indices, data, counts = _row_entries(np.arange(c0, c1), wins, motion, h, w)
        indptr[c0 + 1 : c1 + 1] = np.cumsum(counts) + out.nnz
        out.append(indices, data)
    indices, data = out.finish()
    itype = np.int32 if out.nnz < 2**31 - 1 else np.int64
    return sp.csr_matrix(
        (data, indices.astype(itype, copy=False), indptr.astype(itype)), shape=(n, n)
    )


def _row_entries(pix: np.ndarray, wins: list, motion: tuple, h: int, w: int, ties: bool = False):
    """The rows of pixels ``pix`` (sorted int64): ``(columns int32, values float32, entries
    per row)``, each row's columns sorted, and with ``ties`` a bool per row: some sample
    of its path lies within 1e-6 of a rounding tie of the position grid (see
    :func:`stages.deblur.assembly.expand_stencils`). ``wins``: per window ``(start,
    duration, weight, samples)`` per pixel; ``motion``: ``(vx, vy, layers)``, the
    per-pixel velocity or (``layers`` not None) the layers."""
    vx, vy, layers = motion
    m = len(pix)
    py, px = np.divmod(pix, w)
    parts = []
    tie = np.zeros(m, bool) if ties else None
    for a, dur, wt, ns in wins:
        cnt = ns[pix]
        n_s = int(cnt.sum())
        if n_s == 0:
            continue
        # Per-pixel quantities repeated over the pixel's samples (the same numbers as
        # computed per sample, without gathering).
        local = np.repeat(np.arange(m), cnt)
        k = np.arange(n_s) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        a_p, dur_p = a[pix], dur[pix]
        dt_px = dur_p / np.maximum(cnt, 1)
        dt = np.repeat(dt_px, cnt)
        t = np.repeat(a_p, cnt) + (k + 0.5) * dt
        del k, dt
        weight = np.repeat(wt[pix] * dt_px, cnt)
        pxs, pys = np.repeat(px, cnt), np.repeat(py, cnt)
        if layers is not None:
            x, y = _layered_positions(layers, pxs, pys, t, h, w)
        else:
            reach = float(np.abs(a_p + dur_p).max()) + float(np.abs(a_p).max())
            x = moved(pxs, vx[pix], cnt, t, reach)
            y = moved(pys, vy[pix], cnt, t, reach)
            for v, pos in ((vx, x), (vy, y)) if ties else ():
                if pos is not None:
                    near = near_half(np.repeat(v[pix], cnt) * t * POSITION_STEPS)
                    tie |= np.bincount(local[near], minlength=m) > 0
        del t
        parts.append((local, cnt, *corners(x, y, pxs, pys, weight, h, w)))
    if parts:
        out = sum_rows(parts, m, w, h * w)
    else:
        out = (np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(m, np.int64))
    return (*out, tie) if ties else out


@dataclass(frozen=True)
class Stencils:
    """Rows of a blur matrix that are a representative row shifted with their pixel (see
    :func:`stages.deblur.assembly.expand_stencils`): ``rows`` (S,) sorted, the ``group``
    of each, the representative row of each group ``reps`` (G,), and the
    representatives' entries (``counts`` per representative, ``cols``, ``vals``)."""

    rows: np.ndarray
    group: np.ndarray
    reps: np.ndarray
    counts: np.ndarray
    cols: np.ndarray
    vals: np.ndarray


def _compact(v: np.ndarray) -> np.ndarray:
    """``v`` (N,), or its one number (1,) when it is a view of stride 0."""
    return v[:1] if v.strides == (0,) else v


def _stencil_plan(vx, vy, windows: Sequence[Window], wins: list, h: int, w: int):
    """Rows that read their group's pattern shifted with their pixel (see
    :func:`stages.deblur.assembly.expand_stencils`): pixels away from the border by more
    than their path's reach, grouped by equal velocity and exposure windows. Returns
    :func:`stages.deblur.assembly.stencil_groups`' answer (None: no such plan)."""
    n = h * w
    used = [(_compact(a), _compact(d)) for a, d, _w, ns in wins if _compact(ns).any()]
    t_lo = min((float(a.min()) for a, _d in used), default=0.0)
    t_hi = max((float((a + d).max()) for a, d in used), default=0.0)
    # On the (H, W) grid: a pixel's column and row broadcast from (1, W) and (H, 1), and
    # a velocity given as one number as one number.
    eligible = np.ones((h, w), bool)
    for v, p, size in (
        (vx, np.arange(w, dtype=np.int64).reshape(1, w), w),
        (vy, np.arange(h, dtype=np.int64).reshape(h, 1), h),
    ):
        v = _compact(v)
        v = v.reshape(h, w) if v.size == n and n > 1 else v.reshape(1, 1)
        far = max(abs(t_lo), abs(t_hi))
        still = np.abs(v) * (far * POSITION_STEPS) < 0.49  # (the path keeps its pixel)
        if t_lo >= 0:  # displacement -v t for t in [0, t_hi]
            lo, hi = np.minimum(-v * t_hi, 0.0), np.maximum(-v * t_hi, 0.0)
        else:
            lo, hi = -np.abs(v) * far, np.abs(v) * far
        eligible &= still | ((p + lo - 1 >= 0) & (p + hi + 2 <= size - 1))
    eligible = eligible.reshape(n)
    keys, seen = [vx, vy], set()
    for win in windows:
        for val in (win.start, win.end, win.weight):
            if np.ndim(val) and id(val) not in seen:
                seen.add(id(val))
                keys.append(np.asarray(val).reshape(-1))
    return stencil_groups(keys, eligible)


def _layered_positions(
    layers: Layers, px: np.ndarray, py: np.ndarray, t: np.ndarray, h: int, w: int
):
    """Scene positions seen by pixels ``(px, py)`` at times ``t``: front-most covering layer."""
    disp = layers.displacement(t)  # (K, *t.shape, 2)
    db = disp[layers.background]
    x = px - db[..., 0]
    y = py - db[..., 1]
    done = np.zeros(px.shape, bool)
    for k in layers.front:
        xk = px - disp[k][..., 0]
        yk = py - disp[k][..., 1]
        ix = np.floor(xk + 0.5).astype(np.int64)
        iy = np.floor(yk + 0.5).astype(np.int64)
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        hit = ~done & inside & (layers.label[np.clip(iy, 0, h - 1), np.clip(ix, 0, w - 1)] == k)
        x = np.where(hit, xk, x)
        y = np.where(hit, yk, y)
        done |= hit
    return x, y


def static_rows(A: sp.csr_matrix) -> np.ndarray:
    """Rows of ``A`` that see only their own pixel (a still integration path), bool (N,)."""
    n_rows = A.shape[0]
    nnz = np.diff(A.indptr)
    out = nnz == 0
    one = nnz == 1
    rows = np.arange(n_rows)
    cols = np.zeros(n_rows, np.int64)
    cols[one] = A.indices[A.indptr[:-1][one]]
    out |= one & (cols == rows % A.shape[1])
    return out


def moving_reach(A: sp.csr_matrix) -> np.ndarray:
    """The columns (pixels) that the rows of ``A`` reading more than their own pixel read,
    bool (N,) (the stored values are positive weights: a column is reached exactly where
    this product is non-zero, with no per-non-zero temporary); ``A`` may be a
    :class:`~stages.deblur.convolution.SplitOperator`."""
    if isinstance(A, SplitOperator):
        return A.moving_reach()
    moving = ~static_rows(A)
    if not moving.any():
        return np.zeros(A.shape[1], bool)
    return np.asarray(A.T @ moving.astype(np.float32)) != 0


def apply(A: sp.csr_matrix, image: np.ndarray) -> np.ndarray:
    """``A`` applied to each channel of an ``(H, W, C)`` image; returns ``(H, W, C)``."""
    h, w, c = image.shape
    return np.asarray(A @ image.reshape(h * w, c)).reshape(h, w, c)


def apply_adjoint(A: sp.csr_matrix, image: np.ndarray) -> np.ndarray:
    """The adjoint (transpose) of :func:`apply`."""
    h, w, c = image.shape
    return np.asarray(A.T @ image.reshape(h * w, c)).reshape(h, w, c)


#: Channels one ``cv2.remap`` call interpolates exactly: with more, OpenCV quantises the
#: float maps to 1/32 pixel.
REMAP_MAX_CHANNELS = 4


def trajectory_sum(
    images: np.ndarray, velocity: np.ndarray, times: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """Matrix-free weighted gather: ``sum_s weights[s] * images(x - u(x) t_s)``.

    Parameters
    ----------
    images : ndarray of shape (H, W, K)
        Sampled together (one pair of maps per time for all ``K``).
    velocity : ndarray of shape (H, W, 2), px/s
    times : ndarray of shape (S,), seconds
    weights : ndarray broadcastable to (S, H, W)

    Returns
    -------
    ndarray of shape (H, W, K), float32 (bilinear, border reflected); the samples are
    summed as they are taken (no ``S x H x W x K`` array is held).
    """
    import cv2

    h, w, k = images.shape
    xx = np.arange(w, dtype=np.float32)[None, :]
    yy = np.arange(h, dtype=np.float32)[:, None]
    vx = np.ascontiguousarray(velocity[..., 0], np.float32)
    vy = np.ascontiguousarray(velocity[..., 1], np.float32)
    groups = [
        np.ascontiguousarray(images[..., g : g + REMAP_MAX_CHANNELS], np.float32)
        for g in range(0, k, REMAP_MAX_CHANNELS)
    ]
    wts = np.broadcast_to(weights, (len(times), h, w))
    out = np.zeros((h, w, k), np.float32)
    for i, t in enumerate(times):
        mx = xx - vx * np.float32(t)
        my = yy - vy * np.float32(t)
        wt = wts[i].astype(np.float32)[..., None]
        for g, img in zip(range(0, k, REMAP_MAX_CHANNELS), groups, strict=True):
            got = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
            out[..., g : g + img.shape[2]] += wt * got.reshape(h, w, -1)
    return out
