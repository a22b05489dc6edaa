"""Assembly of the blur operator's sparse rows (:func:`stages.deblur.operator.blur_matrix`).

Each row of the operator sums the bilinear corners of its pixel's samples along the
pixel's path. :func:`corners` turns sample positions into corners and weights,
:func:`sum_rows` sums a set of rows' corners into CSR rows (columns sorted, duplicates
summed in float64, then float32). Rows that read the same pattern shifted with their
pixel (a uniform velocity and the same exposure windows, away from the border) are
expanded from one representative row each by :func:`expand_stencils`, which gives the
same numbers as assembling them one by one (:func:`tie_free` guards the rounding).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

#: Samples per chunk while assembling a matrix (bounds the temporary memory), and the
#: most pixels a chunk may hold.
CHUNK_SAMPLES = 1 << 17
CHUNK_PIXELS = 1 << 16

#: Most stencil groups :func:`stencil_groups` keeps (more: rows are assembled one by one).
MAX_STENCILS = 4096

#: Sample positions are rounded to 1/POSITION_STEPS px: OpenCV's bilinear warps
#: (``INTER_BITS`` = 5), with which the simulator renders the motion, use that grid.
POSITION_STEPS = 32


def reflect(i: np.ndarray, n: int) -> np.ndarray:
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


def moved(p: np.ndarray, v: np.ndarray, cnt: np.ndarray, t: np.ndarray, reach: float):
    """``p - v t`` per sample (``v`` per pixel, repeated ``cnt`` times), or None where that
    rounds to ``p`` on the position grid for every sample (``|v t| < 0.49 / POSITION_STEPS``
    with ``|t| <= reach``: a vanishing component of the motion)."""
    if v.size == 0 or float(np.abs(v).max()) * reach * POSITION_STEPS < 0.49:
        return None
    return p - np.repeat(v, cnt) * t


def on_grid(x: np.ndarray | None, p: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Positions ``x`` rounded to the position grid: (integer part int64, fraction
    float64, or None where every fraction is zero). ``x`` None: the pixels ``p``."""
    if x is None:
        return p, None
    x = np.rint(x * POSITION_STEPS) / POSITION_STEPS
    x0 = np.floor(x)
    x -= x0
    return x0.astype(np.int64), x if float(x.max()) > 0 else None


def corners(x, y, px: np.ndarray, py: np.ndarray, weight: np.ndarray, h: int, w: int):
    """Bilinear corners of the sample positions ``x, y`` (px; None: the sample's pixel
    ``px``, ``py`` along that axis) with the samples' weights.

    Positions are rounded to OpenCV's interpolation grid (as the simulator's warps
    sample): a motion along one axis with a vanishing component along the other then
    keeps one row (or column) of bilinear weights, not two. Returns ``(xs, ys, ws)``:
    the reflected corner columns and rows (int64; two each, or one where the other's
    weight is zero for every sample) and the weights (float64) of the corners ``(y, x)``
    for ``y`` in ``ys`` and ``x`` in ``xs``, in that order.
    """
    x0, fx = on_grid(x, px)
    y0, fy = on_grid(y, py)
    del x, y
    # The products of the four-corner form, ((1 - fx)(1 - fy)) weight, ..., in its order
    # and association (a zero fraction's factor of 1 left out: the same numbers).
    if fy is None:
        if fx is None:
            ws = [weight.copy()]
        else:
            gx = 1 - fx
            gx *= weight
            fx *= weight
            ws = [gx, fx]
    else:
        gy = 1 - fy
        if fx is None:
            gy *= weight
            fy *= weight
            ws = [gy, fy]
        else:
            gx = 1 - fx
            g = gx * gy
            g *= weight
            ws = [g]
            g = fx * gy
            g *= weight
            ws.append(g)
            del gy
            gx *= fy
            gx *= weight
            ws.append(gx)
            fx *= fy
            fx *= weight
            ws.append(fx)
    xa, xb = reflect_pair(x0, w)
    ya, yb = reflect_pair(y0, h)
    # (The weights above are in the order (ya, xa), (ya, xb), (yb, xa), (yb, xb).)
    return [xa] if fx is None else [xa, xb], [ya] if fy is None else [ya, yb], ws


def reflect_pair(i0: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``reflect(i0, n)`` and ``reflect(i0 + 1, n)``."""
    if i0.size and int(i0.min()) >= 0 and int(i0.max()) < n - 1:
        return i0, i0 + 1  # (all inside: the common case)
    return reflect(i0, n), reflect(i0 + 1, n)


#: Largest dense accumulator of :func:`sum_rows`, in multiples of its entries.
DENSE_BOX_FACTOR = 4


def row_origin(parts, rows: int, axis: int) -> np.ndarray:
    """Per row, the smaller first-corner coordinate along ``axis`` (0: x, 1: y) of its
    first and last sample in each window of ``parts`` (see :func:`sum_rows`): for a path
    that does not fold back, its smallest coordinate (0 for rows with no sample)."""
    big = np.iinfo(np.int64).max
    lo = np.full(rows, big, np.int64)
    for _local, cnt, *corner, _ws in parts:
        has = cnt > 0
        last = np.cumsum(cnt)[has] - 1
        first = last - (cnt[has] - 1)
        c = corner[axis][0]
        lo[has] = np.minimum(lo[has], np.minimum(c[first], c[last]))
    lo[lo == big] = 0
    return lo


def sum_rows(parts, rows: int, w: int, n: int):
    """One chunk's rows in CSR form: each row's columns sorted, duplicates summed.

    ``parts``: per window ``(local row of each sample, samples per row, corner xs,
    corner ys, corner weights)`` (:func:`corners`). A row's corners lie near its path:
    the entries are accumulated (in float64) into a dense box of rows and columns per
    row (its origin from :func:`row_origin`, its size the largest any row of the chunk
    needs), whose non-zeros in order are the row's sorted columns. Where that box would
    be far larger than the entries (a long path along both axes), scipy sums them
    instead. Returns ``(indices int32, data float32, entries per row)``.
    """
    entries = sum(len(p[0]) * len(p[4]) for p in parts)
    org_x, org_y = row_origin(parts, rows, 0), row_origin(parts, rows, 1)
    # Corner offsets from the row's origin, and their range over the chunk.
    offsets = []
    lo_x = lo_y = np.iinfo(np.int64).max
    hi_x = hi_y = -lo_x
    for local, cnt, xs, ys, ws in parts:
        ox, oy = np.repeat(org_x, cnt), np.repeat(org_y, cnt)
        dxs = [xx - ox for xx in xs]
        dys = [yy - oy for yy in ys]
        del ox, oy
        for d in dxs:
            lo_x, hi_x = min(lo_x, int(d.min())), max(hi_x, int(d.max()))
        for d in dys:
            lo_y, hi_y = min(lo_y, int(d.min())), max(hi_y, int(d.max()))
        offsets.append((local, dxs, dys, ws))
    bw, bh = hi_x - lo_x + 1, hi_y - lo_y + 1
    box = bw * bh
    keys, vals = [], []
    if rows * box <= DENSE_BOX_FACTOR * entries + rows:
        for local, dxs, dys, ws in offsets:
            base = local * box
            base -= lo_y * bw + lo_x
            i = 0
            for dy in dys:
                row_base = base + dy * bw if bh > 1 else base
                for dx in dxs:
                    keys.append(row_base + dx)
                    vals.append(ws[i])
                    i += 1
        del offsets
        acc = np.bincount(np.concatenate(keys), np.concatenate(vals), minlength=rows * box)
        del keys, vals
        nz = np.flatnonzero(acc)
        data = acc[nz].astype(np.float32)
        del acc
        r = nz // box
        off = nz - r * box
        if bh > 1:
            dy = off // bw
            off -= dy * bw
            cols = (org_y[r] + (dy + lo_y)) * w + org_x[r] + (off + lo_x)
        else:
            cols = (org_y[r] + lo_y) * w + org_x[r] + (off + lo_x)
        return cols.astype(np.int32), data, np.bincount(r, minlength=rows)
    del offsets
    loc = []
    for local, _cnt, xs, ys, ws in parts:
        i = 0
        for yy in ys:
            for xx in xs:
                keep = ws[i] > 0  # (the corners' zero weights are no entries)
                loc.append(local[keep])
                keys.append((yy * w + xx)[keep])
                vals.append(ws[i][keep])
                i += 1
    blk = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(loc), np.concatenate(keys))), shape=(rows, n)
    )
    blk.sum_duplicates()  # (in float64, as the dense box)
    return blk.indices.astype(np.int32), blk.data.astype(np.float32), np.diff(blk.indptr)


def mapped(n: int, dtype: type) -> np.ndarray:
    """An uninitialised array of ``n`` items in an anonymous memory map of its own."""
    import mmap

    itemsize = np.dtype(dtype).itemsize
    return np.frombuffer(mmap.mmap(-1, n * itemsize), dtype, count=n)


class Growing:
    """Column index (int32) and float32 value arrays appended to, grown by half when full.

    Each array is its own anonymous memory map: the pages of the capacity not yet
    filled are never touched, so they take address space but no resident memory; the
    filled part is returned as a view (no final copy); and the map goes back to the
    system as a whole when the matrix is freed (an array on the heap, among the
    assembly's temporaries, would pin them).
    """

    def __init__(self, capacity: int):
        self.indices = mapped(max(capacity, 1), np.int32)
        self.data = mapped(max(capacity, 1), np.float32)
        self.nnz = 0

    def append(self, indices: np.ndarray, data: np.ndarray) -> None:
        end = self.nnz + len(indices)
        if end > len(self.indices):
            cap = max(end, len(self.indices) * 3 // 2)
            for name in ("indices", "data"):
                old = getattr(self, name)
                new = mapped(cap, old.dtype)
                new[: self.nnz] = old[: self.nnz]
                setattr(self, name, new)
        self.indices[self.nnz : end] = indices
        self.data[self.nnz : end] = data
        self.nnz = end

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        """The filled parts of the arrays (views)."""
        return self.indices[: self.nnz], self.data[: self.nnz]


def chunks(samples: np.ndarray) -> list[tuple[int, int]]:
    """Ranges ``[i0, i1)`` of a list of rows with ``samples`` samples each: at most
    :data:`CHUNK_SAMPLES` samples (a row with more is a chunk of its own) and at most
    :data:`CHUNK_PIXELS` rows."""
    n = len(samples)
    ends = np.cumsum(samples)
    out = []
    i0 = 0
    while i0 < n:
        before = int(ends[i0 - 1]) if i0 else 0
        i1 = int(np.searchsorted(ends, before + CHUNK_SAMPLES, side="right"))
        i1 = min(max(i1, i0 + 1), i0 + CHUNK_PIXELS, n)
        out.append((i0, i1))
        i0 = i1
    return out


def near_half(q: np.ndarray) -> np.ndarray:
    """Where ``q`` is within 1e-6 of a half-integer, bool (a rounding tie on the position
    grid that a pixel's own coordinate could tip; see :func:`expand_stencils`)."""
    return np.abs(q - np.floor(q) - 0.5) < 1e-6


def stencil_groups(keys: list[np.ndarray], eligible: np.ndarray):
    """The ``eligible`` rows grouped by equal values of every array in ``keys`` (each of
    shape (N,)): ``(rows (R,) int64 sorted, group of each (R,), first row of each group
    (G,))``, or None when under half of the rows are eligible or there are more than
    :data:`MAX_STENCILS` groups."""
    rows = np.flatnonzero(eligible)
    if 2 * len(rows) < len(eligible) or len(rows) == 0:
        return None
    code = np.zeros(len(rows), np.int64)
    varies = False
    for k in keys:
        if k.strides == (0,):  # (one number for all the rows)
            continue
        vals = k[rows]
        if vals.min() == vals.max():
            continue
        varies = True
        u, inv = np.unique(vals, return_inverse=True)
        if len(u) > MAX_STENCILS:
            return None
        code = np.unique(code * len(u) + inv, return_inverse=True)[1]
        if int(code.max()) >= MAX_STENCILS:
            return None
    if not varies:
        return rows, code, rows[:1]
    _u, first, gid = np.unique(code, return_index=True, return_inverse=True)
    return rows, gid.astype(np.int64), rows[first]


def expand_stencils(n: int, generic, stencil, rows: np.ndarray | None = None) -> sp.csr_matrix:
    """The (N, N) CSR matrix of rows assembled one by one and rows that are a
    representative row shifted with their pixel; with ``rows`` (sorted, holding every
    stencil row and every generic row with entries), those rows alone, (len(rows), N).

    ``generic``: ``(rows (R,) sorted, entries per row, columns, values)`` of the rows
    assembled one by one (each row's entries together, in row order). ``stencil``:
    ``(rows (S,) sorted, group of each, representative row of each group (G,), entries
    per representative, their columns, their values)``; a row of group ``g`` reads the
    columns of its representative ``r`` moved by ``row - r`` (the representative and its
    rows are away from the border, where no index is reflected) and the same values.
    """
    g_rows, g_counts, g_cols, g_vals = generic
    s_rows, s_gid, reps, r_counts, r_cols, r_vals = stencil
    # One list of sources: the generic rows' entries, then the representatives' entries
    # with their columns as offsets from their pixel. Each row reads a run of it, plus
    # its own pixel index for a stencil row.
    r_start = np.cumsum(r_counts) - r_counts
    src_cols = np.concatenate(
        [g_cols.astype(np.int64), r_cols.astype(np.int64) - np.repeat(reps, r_counts)]
    )
    src_vals = np.concatenate([g_vals, r_vals])
    g_start = np.cumsum(g_counts) - g_counts
    m, g_at, s_at = n, g_rows, s_rows  # (the matrix's rows, where each row goes)
    if rows is not None:
        has = g_counts > 0
        g_rows, g_counts, g_start = g_rows[has], g_counts[has], g_start[has]
        m, g_at, s_at = rows.size, np.searchsorted(rows, g_rows), np.searchsorted(rows, s_rows)
    counts = np.zeros(m, np.int64)
    start = np.zeros(m, np.int64)
    shift = np.zeros(m, np.int64)
    counts[g_at] = g_counts
    start[g_at] = g_start
    counts[s_at] = r_counts[s_gid]
    start[s_at] = len(g_cols) + r_start[s_gid]
    shift[s_at] = s_rows
    indptr = np.zeros(m + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    nnz = int(indptr[-1])
    indices = mapped(max(nnz, 1), np.int32)[:nnz]
    data = mapped(max(nnz, 1), np.float32)[:nnz]
    step = 8 * CHUNK_SAMPLES  # (entries per block of rows, bounding the temporaries)
    i0 = 0
    while i0 < m:
        i1 = int(np.searchsorted(indptr, indptr[i0] + step, side="right")) - 1
        i1 = min(max(i1, i0 + 1), m)
        p0, p1 = int(indptr[i0]), int(indptr[i1])
        c = counts[i0:i1]
        src = np.repeat(start[i0:i1] - (indptr[i0:i1] - p0), c)
        src += np.arange(p1 - p0)
        col = src_cols[src]
        col += np.repeat(shift[i0:i1], c)
        indices[p0:p1] = col
        data[p0:p1] = src_vals[src]
        i0 = i1
    itype = np.int32 if nnz < 2**31 - 1 else np.int64
    return sp.csr_matrix(
        (data, indices.astype(itype, copy=False), indptr.astype(itype)), shape=(m, n)
    )
