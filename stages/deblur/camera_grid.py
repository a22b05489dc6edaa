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

from ..formats.capture import Capture
from ..physics import bin_may_clip


def camera_bins(
    cap: Capture, n_sub: np.ndarray, dur: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray, tuple[int, int]]:
    """A real rig's bins on the measurement camera's own grid, for the misfit.

    ``n_sub``, ``dur`` (B,): each bin's subframes and exposed seconds. A bin's pixel
    ``u`` records, in electrons at the camera's gain, ``v_u (S x)_u`` plus the dark
    current (``S`` the camera's bilinear sampling of the VET grid, ``v`` its vignetting,
    ``x`` the light the bin's blur brings to the VET grid), with the variance of that
    count (smoothed over 3 x 3 pixels, as the VET-grid bins') plus one read noise and
    quantisation step per subframe; 0 weight where a subframe may have clipped. The model
    is the simulator's camera exactly, so no inversion (and none of its noise
    correlation) stands between the data and the misfit.

    Returns the sampling ``v S`` (scipy CSR (Hm Wm, H W) float32), the bins minus the
    dark current (B Hm Wm, C) electrons, their inverse variances (B Hm Wm, C) and the
    camera's grid (Hm, Wm).
    """
    import cv2

    from ..optics import MeasureGeometry

    rig = cap.rig
    c = cap.measure.shape[-1]
    geom = MeasureGeometry(rig)
    hm, wm = geom.shape_m
    sampling = (sp.diags(geom.vign.ravel()) @ geom.operator()).tocsr().astype(np.float32)
    g = rig.gain_dn_per_e * rig.measure_gain
    read = rig.read_noise_e**2 + 1.0 / (12.0 * g * g)
    nb, m = cap.measure.shape[0], hm * wm
    yb = np.empty((nb * m, c), np.float32)
    wb = np.empty((nb * m, c), np.float32)
    for b in range(nb):
        rows = slice(b * m, (b + 1) * m)
        raw = np.asarray(cap.measure[b], np.float32)
        eb = raw.astype(np.float64) / g
        var = cv2.blur(np.maximum(eb, 0), (3, 3), borderType=cv2.BORDER_REPLICATE)
        var = var.reshape(eb.shape) + n_sub[b] * read
        wbb = 1.0 / var
        wbb[bin_may_clip(raw / np.float32(n_sub[b]), rig)] = 0.0
        wb[rows] = wbb.reshape(m, c)
        yb[rows] = (eb - rig.dark_current_e_s * dur[b]).reshape(m, c)
    return sampling, yb, wb, (hm, wm)


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
