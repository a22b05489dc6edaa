"""The misfit's time bins made before the motion estimate, where that is lean: the stream
summed once, in its own memory, and the estimate reading its bins from those sums
(:mod:`stages.formats.stream_sums`) instead of from the stream held beside them."""

from __future__ import annotations

import numpy as np

from ..formats.capture import Capture
from ..formats.stream_sums import StreamSums


def bins_first(cap: Capture, recorded: Capture, options) -> tuple[Capture, StreamSums] | None:
    """The misfit's time bins of ``cap``'s stream made before the motion estimate, in the
    stream's own memory (which ``cap`` lets go), and the stream's sums that the estimate
    then reads in its place (:mod:`stages.formats.stream_sums`): where the bins' count
    does not depend on the motion (on a large frame the compute budget sets it,
    :func:`~stages.deblur.problem.fit_bins`) and their sums give the estimate's own bins
    to the bit. None elsewhere (then the stream is binned after the estimate, as it was
    read): a capture registered onto the VET grid, a fit that reads no bins."""
    from ..formats.capture import MOTION_BINS
    from ..formats.stream_sums import serves, summed_stream
    from .joint import JointOptions
    from .layers.estimate import TRACK_BINS
    from .problem import fit_bins

    opts = options if options is not None else JointOptions()
    if recorded is not cap or not cap.keeps_stream or not opts.use_measure or opts.stream_fit:
        return None
    tf = float(cap.meta.get("integration_s", cap.rig.frame_s))
    pixels = cap.shape[0] * cap.shape[1]
    n_fit = fit_bins(0.0, tf, cap.rig.n_subframes, pixels)
    if n_fit != fit_bins(np.inf, tf, cap.rig.n_subframes, pixels):
        return None
    if not serves(cap, n_fit, (MOTION_BINS, TRACK_BINS)):
        return None
    return summed_stream(cap, n_fit)
