"""A real rig's measuring bins on the measurement camera's own grid.

The measurement camera (:class:`stages.optics.MeasureGeometry`) samples the light on the
VET grid bilinearly where each of its pixels looks, vignetting included. Its bins are
fitted where it recorded them: each bin's operator is that sampling times the bin's blur
on the VET grid (:func:`stages.deblur.problem.build_operators`), so neither an
interpolation nor an inversion onto the VET grid (:mod:`stages.measure_grid`) stands
between the data and the misfit, and each bin pixel keeps its own noise. The motion
steps, which linearise on the VET grid, read the bins' residuals through
:func:`bins_on_vet_grid`.

A tile of a frame (:mod:`stages.deblur.tiles`) fits the camera pixels whose light its box
holds whole (:meth:`CameraBins.crop`): a rectangle of the camera's grid, the sampling's
columns those of the box, the pixels that see past it weighted 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..rig import RigParams


def camera_sampling(rig: RigParams) -> tuple[sp.csr_matrix, tuple[int, int]]:
    """The measurement camera's response on the VET grid, and its grid (Hm, Wm).

    Row ``u`` (a camera pixel, row-major) holds the bilinear weights of the VET pixels
    its centre lands among (:meth:`stages.optics.MeasureGeometry.operator`) times the
    camera's vignetting there: a bin pixel records ``(v S x)_u`` electrons at the camera's
    gain for the light ``x`` the bin's blur brings to the VET grid (dark current apart),
    the simulator's camera exactly. scipy CSR (Hm Wm, H W) float32.
    """
    from ..optics import MeasureGeometry

    geom = MeasureGeometry(rig)
    sampling = (sp.diags(geom.vign.ravel()) @ geom.operator()).tocsr().astype(np.float32)
    return sampling, geom.shape_m


def bins_on_vet_grid(
    sampling: sp.csr_matrix | None,
    shape: tuple[int, int, int],
    rb: np.ndarray | None,
    wb: np.ndarray | None,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Bin residuals ``rb`` and weights ``wb`` (B rows each) as the VET grid, of shape
    ``shape`` (H, W, C), sees them.

    Without a camera's ``sampling`` (the bins on the VET grid) they are themselves. Through the camera's sampling ``S`` they are
    per bin ``d = diag(S^T W S)`` and ``S^T W r / d`` ((B H W, C) each): the same
    gradient ``S^T W r`` of the misfit for any linearisation on the VET grid, and the
    diagonal of its normal matrix (the motion steps' Gauss-Newton terms).
    """
    S = sampling
    if S is None or rb is None:
        return rb, wb
    h, w, c = shape
    m = S.shape[0]
    nb = rb.shape[0] // m
    ST = S.T.tocsr()
    S2T = S.multiply(S).T.tocsr()
    r_out = np.empty((nb * h * w, c), np.float32)
    w_out = np.empty((nb * h * w, c), np.float32)
    for b in range(nb):
        rows = slice(b * m, (b + 1) * m)
        wgt = np.asarray(wb[rows], np.float32)
        d = S2T @ wgt
        g = ST @ (wgt * np.asarray(rb[rows], np.float32))
        out = slice(b * h * w, (b + 1) * h * w)
        w_out[out] = d
        r_out[out] = np.where(d > 0, g / np.where(d > 0, d, 1), 0)
    return r_out, w_out


@dataclass
class CameraBins:
    """A real rig's measuring bins as its camera recorded them, with its sampling.

    ``measure`` (B, hm, wm, C) DN: a rectangle of the camera's grid (the whole of it for a
    frame); ``sampling`` CSR (hm wm, h w) float32: :func:`camera_sampling`'s rows of those
    pixels on an (h, w) box of the VET grid; ``valid`` (hm, wm) bool: the pixels whose
    light the box holds whole (the others' rows are 0 and their weights must be 0).
    """

    measure: np.ndarray
    sampling: sp.csr_matrix
    valid: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """(hm, wm): the rectangle of the camera's grid."""
        return self.valid.shape

    @classmethod
    def of(cls, rig: RigParams, measure: np.ndarray) -> CameraBins:
        """The whole camera grid's bins ``measure`` (B, Hm, Wm, C) of ``rig``."""
        sampling, grid = camera_sampling(rig)
        if measure.shape[1:3] != grid:
            raise ValueError(f"measuring bins {measure.shape[1:3]} are not the camera's {grid}")
        return cls(measure, sampling, np.ones(grid, bool))

    def crop(self, box: tuple[int, int, int, int], vet_shape: tuple[int, int]) -> CameraBins:
        """The bins seen by the box ``(y0, y1, x0, x1)`` of the (H, W) VET grid the
        sampling's columns index: the smallest rectangle of camera pixels holding every
        pixel whose sampled VET pixels all lie in the box, its sampling on the box's
        pixels (row-major), those that see past the box not valid."""
        y0, y1, x0, x1 = box
        h, w = vet_shape
        S = self.sampling.tocsr()
        if S.shape[1] != h * w:
            raise ValueError(f"the sampling has {S.shape[1]} columns, not {h}x{w}")
        n = S.shape[0]
        cy, cx = np.divmod(S.indices.astype(np.int64), w)
        inside = (cy >= y0) & (cy < y1) & (cx >= x0) & (cx < x1) & (S.data != 0)
        counts = np.diff(S.indptr)
        rows = np.repeat(np.arange(n), counts)
        held = np.bincount(rows, inside, minlength=n)
        nonzero = np.bincount(rows, S.data != 0, minlength=n)
        valid = (held == nonzero) & (nonzero > 0) & self.valid.ravel()
        valid = valid.reshape(self.shape)
        vy, vx = np.nonzero(valid)
        if vy.size == 0:  # no camera pixel sees into the box alone: one pixel, not valid
            vy, vx = np.zeros(1, int), np.zeros(1, int)
        r0, r1, c0, c1 = int(vy.min()), int(vy.max()) + 1, int(vx.min()), int(vx.max()) + 1
        keep = valid[r0:r1, c0:c1]
        wm_full = self.shape[1]
        pick = ((np.arange(r0, r1)[:, None] * wm_full) + np.arange(c0, c1)[None, :]).ravel()
        sub = S[pick].tocoo()
        sy, sx = np.divmod(sub.col.astype(np.int64), w)
        ok = keep.ravel()[sub.row] & (sy >= y0) & (sy < y1) & (sx >= x0) & (sx < x1)
        cols = (sy[ok] - y0) * (x1 - x0) + (sx[ok] - x0)
        sampling = sp.csr_matrix(
            (sub.data[ok], (sub.row[ok], cols)), shape=(pick.size, (y1 - y0) * (x1 - x0))
        )
        measure = np.ascontiguousarray(self.measure[:, r0:r1, c0:c1])
        return CameraBins(measure, sampling.astype(np.float32), keep.copy())
