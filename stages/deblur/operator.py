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

#: Pixels per chunk while assembling a matrix (bounds the temporary memory).
CHUNK_PIXELS = 1 << 12

#: Sample positions are rounded to 1/POSITION_STEPS px: OpenCV's bilinear warps
#: (``INTER_BITS`` = 5), with which the simulator renders the motion, use that grid.
POSITION_STEPS = 32

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


def _reflect(i: np.ndarray, n: int) -> np.ndarray:
    """Reflect integer indices into ``[0, n)`` like OpenCV's BORDER_REFLECT (fedcba|abcd)."""
    if n == 1:
        return np.zeros_like(i)
    lo, hi = (int(i.min()), int(i.max())) if i.size else (0, 0)
    if lo >= 0 and hi < n:
        return i  # (all inside: the common case, no copy)
    if lo >= -n and hi < 2 * n:  # (within one reflection: no modulo)
        return np.where(i < 0, -1 - i, np.where(i >= n, 2 * n - 1 - i, i))
    period = 2 * n
    i = np.mod(i, period)
    return np.where(i >= n, period - 1 - i, i)


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
) -> sp.csr_matrix:
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
        motion); by default it is read here.

    Returns
    -------
    scipy.sparse.csr_matrix of shape (H W, H W), float32
        ``y = A @ L0.ravel()`` gives the model's electrons for each pixel when ``L0`` is
        in electrons per second.
    """
    h, w = velocity.shape[:2]
    n = h * w
    vel = velocity.reshape(n, 2).astype(np.float64)
    if isinstance(layers, str):
        layers = motion_layers(velocity)
    by_layer = layers is not None and (len(layers.velocity) > 1 or layers.trajectory is not None)
    if by_layer:
        # Samples along the fastest layer's path: any layer may cover the pixel.
        speed = np.full(n, layers.max_speed())
    else:
        speed = np.hypot(vel[:, 0], vel[:, 1])
    wins = []
    for win in windows:
        # (Views: a window bound or weight given as one number takes no memory.)
        a = np.broadcast_to(np.asarray(win.start, np.float64), (h, w)).reshape(-1)
        b = np.broadcast_to(np.asarray(win.end, np.float64), (h, w)).reshape(-1)
        wt = np.broadcast_to(np.asarray(win.weight, np.float64), (h, w)).reshape(-1)
        dur = np.maximum(b - a, 0.0)
        ns = np.ceil(speed * dur / step_px).astype(np.int64)
        if min_dt:
            ns = np.minimum(ns, np.maximum(np.floor(dur / min_dt), 1).astype(np.int64))
        ns = np.clip(ns, 1, max_samples)
        ns[(dur <= 0) | (wt == 0)] = 0
        wins.append((a, dur, wt, ns))

    indptr = np.zeros(n + 1, np.int64)
    # The index and value arrays grow geometrically, a few large blocks (not one small
    # part per chunk kept alive among the chunks' temporaries, which fragments the heap).
    # (Column indices are below n: int32 for any frame under 2**31 pixels.)
    per_px = sum(float(ns.mean()) for *_, ns in wins) if n else 0.0
    out = _Growing(int(2 * per_px * n) + CHUNK_PIXELS)
    for c0 in range(0, n, CHUNK_PIXELS):
        c1 = min(n, c0 + CHUNK_PIXELS)
        rows_l, cols_l, vals_l = [], [], []
        for a, dur, wt, ns in wins:
            cnt = ns[c0:c1]
            total = int(cnt.sum())
            if total == 0:
                continue
            local = np.repeat(np.arange(c1 - c0), cnt)
            first = np.cumsum(cnt) - cnt
            k = np.arange(total) - np.repeat(first, cnt)
            pix = local + c0
            dt = dur[pix] / cnt[local]
            t = a[pix] + (k + 0.5) * dt
            weight = wt[pix] * dt
            py, px = np.divmod(pix, w)
            if by_layer:
                x, y = _layered_positions(layers, px, py, t, h, w)
            else:
                x = px - vel[pix, 0] * t
                y = py - vel[pix, 1] * t
            # Positions on OpenCV's interpolation grid (as the simulator's warps sample):
            # a motion along one axis with a vanishing component along the other then
            # keeps one row (or column) of bilinear weights, not two.
            x = np.rint(x * POSITION_STEPS) / POSITION_STEPS
            y = np.rint(y * POSITION_STEPS) / POSITION_STEPS
            x0 = np.floor(x)
            y0 = np.floor(y)
            fx = x - x0
            fy = y - y0
            x0 = x0.astype(np.int64)
            y0 = y0.astype(np.int64)
            xa, xb = _reflect(x0, w), _reflect(x0 + 1, w)
            ya, yb = _reflect(y0, h), _reflect(y0 + 1, h)
            # Corners with zero weight everywhere (a motion along one axis keeps one row
            # or column of bilinear weights) are skipped whole.
            has_fx, has_fy = bool(np.any(fx > 0)), bool(np.any(fy > 0))
            gx, gy = 1 - fx, 1 - fy
            ya *= w
            corners = [(ya, xa, gx * gy)]
            if has_fx:
                corners.append((ya, xb, fx * gy))
            if has_fy:
                yb *= w
                corners.append((yb, xa, gx * fy))
                if has_fx:
                    corners.append((yb, xb, fx * fy))
            for yy, xx, ww in corners:
                ww *= weight
                keep = ww > 0
                if keep.all():
                    rows_l.append(local)
                    cols_l.append(yy + xx)
                    vals_l.append(ww)
                else:
                    rows_l.append(local[keep])
                    cols_l.append((yy + xx)[keep])
                    vals_l.append(ww[keep])
        if rows_l:
            rows = np.concatenate(rows_l)
            cols = np.concatenate(cols_l)
            vals = np.concatenate(vals_l)
            blk = sp.csr_matrix((vals.astype(np.float32), (rows, cols)), shape=(c1 - c0, n))
            blk.sum_duplicates()
            indptr[c0 + 1 : c1 + 1] = blk.indptr[1:] + out.nnz
            out.append(blk.indices, blk.data)
        else:
            indptr[c0 + 1 : c1 + 1] = out.nnz
    indices, data = out.finish()
    itype = np.int32 if out.nnz < 2**31 - 1 else np.int64
    return sp.csr_matrix(
        (data, indices.astype(itype, copy=False), indptr.astype(itype)), shape=(n, n)
    )


def _mapped(n: int, dtype: type) -> np.ndarray:
    """An uninitialised array of ``n`` items in an anonymous memory map of its own."""
    import mmap

    itemsize = np.dtype(dtype).itemsize
    return np.frombuffer(mmap.mmap(-1, n * itemsize), dtype, count=n)


class _Growing:
    """Column index (int32) and float32 value arrays appended to, grown by half when full.

    Each array is its own anonymous memory map: the pages of the capacity not yet
    filled are never touched, so they take address space but no resident memory; the
    filled part is returned as a view (no final copy); and the map goes back to the
    system as a whole when the matrix is freed (an array on the heap, among the
    assembly's temporaries, would pin them).
    """

    def __init__(self, capacity: int):
        self.indices = _mapped(max(capacity, 1), np.int32)
        self.data = _mapped(max(capacity, 1), np.float32)
        self.nnz = 0

    def append(self, indices: np.ndarray, data: np.ndarray) -> None:
        end = self.nnz + len(indices)
        if end > len(self.indices):
            cap = max(end, len(self.indices) * 3 // 2)
            for name in ("indices", "data"):
                old = getattr(self, name)
                new = _mapped(cap, old.dtype)
                new[: self.nnz] = old[: self.nnz]
                setattr(self, name, new)
        self.indices[self.nnz : end] = indices
        self.data[self.nnz : end] = data
        self.nnz = end

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """The filled parts of the arrays (views)."""
        return self.indices[: self.nnz], self.data[: self.nnz]


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


def apply(A: sp.csr_matrix, image: np.ndarray) -> np.ndarray:
    """``A`` applied to each channel of an ``(H, W, C)`` image; returns ``(H, W, C)``."""
    h, w, c = image.shape
    return np.asarray(A @ image.reshape(h * w, c)).reshape(h, w, c)


def apply_adjoint(A: sp.csr_matrix, image: np.ndarray) -> np.ndarray:
    """The adjoint (transpose) of :func:`apply`."""
    h, w, c = image.shape
    return np.asarray(A.T @ image.reshape(h * w, c)).reshape(h, w, c)


def sample_trajectories(image: np.ndarray, velocity: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Matrix-free gather: ``image(x - u(x) t)`` for each time in ``times``.

    Parameters
    ----------
    image : ndarray of shape (H, W)
    velocity : ndarray of shape (H, W, 2), px/s
    times : ndarray of shape (S,), seconds

    Returns
    -------
    ndarray of shape (S, H, W), float32 (bilinear, border reflected)
    """
    import cv2

    h, w = image.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    out = np.empty((len(times), h, w), np.float32)
    img = np.ascontiguousarray(image, np.float32)
    for i, t in enumerate(times):
        mx = xx - velocity[..., 0] * np.float32(t)
        my = yy - velocity[..., 1] * np.float32(t)
        out[i] = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return out
