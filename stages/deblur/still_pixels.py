"""Pixels that no moving integration path touches: which they are, and the value all
their data give them (the default deblur re-estimates only the others)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .operator import moving_reach
from .problem import Observations
from .stacked import StackedOperator, product
from .stream import StreamTerm


def moving_support(
    A: sp.csr_matrix, Ab: StackedOperator | None = None, S: StreamTerm | None = None
) -> np.ndarray:
    """Pixels of ``L0`` that some moving integration path samples, bool (H W,).

    A row of the operator whose path does not move sees only its own pixel: the static
    model, for which the pixel's value has a closed form (hdr-static's from its VET data,
    or :func:`fuse_still`'s from all of it; see ``JointOptions.fuse_still``). Only the
    pixels that a moving path touches (the columns of the other rows) are re-estimated.
    """
    free = moving_reach(A)
    if Ab is not None:
        free |= Ab.moving_reach()
    if S is not None:  # the stream's rows see their neighbours where their kernel spreads
        free |= S.reached(S.moving())
    return free


def fuse_still(
    obs: Observations,
    A: sp.csr_matrix,
    Ab: StackedOperator | None,
    data_diag: np.ndarray,
    pixels: np.ndarray,
    fallback: np.ndarray,
) -> np.ndarray:
    """Maximum-likelihood value of still pixels from all their data, (P, C).

    ``pixels`` (H W,) bool must be outside :func:`moving_support`: each such pixel's
    column of ``A`` and of every bin's operator holds only its own static row, so the
    noise-weighted least-squares value from the VET image and the measuring bins together
    is ``(A^T w y + sum_b A_b^T w_b y_b) / diag(A^T w A + sum_b A_b^T w_b A_b)`` there
    (with the stream's term ``obs.stream`` in place of the bins when the capture keeps
    its stream: its row there is the identity). ``fallback`` is kept where no datum has
    weight (clipped everywhere).
    """
    rhs = product(A.T, (obs.w * obs.y).astype(np.float32)).astype(np.float64)
    if Ab is not None:
        rhs += Ab.mvt_weighted(obs.wb, obs.yb)
    if obs.stream is not None:
        rhs += obs.stream.adjoint(obs.stream.w * obs.stream.y)
    d = data_diag[pixels]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d > 0, rhs[pixels] / d, fallback)
