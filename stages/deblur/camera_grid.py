"""A real rig's measuring bins on the measurement camera's own grid.

The measurement camera (:class:`stages.optics.MeasureGeometry`) samples the light on the
VET grid bilinearly where each of its pixels looks, vignetting included. Its bins are
fitted where it recorded them: each bin's operator is that sampling times the bin's blur
on the VET grid (:func:`stages.deblur.problem.build_operators`), so neither an
interpolation nor an inversion onto the VET grid (:mod:`stages.measure_grid`) stands
between the data and the misfit, and each bin pixel keeps its own noise. The motion
steps, which linearise on the VET grid, read the bins' residuals through
:func:`bins_on_vet_grid`.
"""

from __future__ import annotations

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
