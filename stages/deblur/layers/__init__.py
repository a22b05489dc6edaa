"""Layered motion estimation from the measuring images.

The motion model of the deblur is a few rigid layers, each translating at a constant
velocity over the 1 s frame (a still background, moving objects, or one global
translation): see :class:`stages.deblur.operator.Layers`. Dense optical flow between two
short, noisy measuring bins gives a noisy per-pixel velocity in the dark, and the
deblur's accuracy is limited by it; a layered model pools every pixel of a layer into
two numbers, so it is far more accurate where the model holds. The estimate
(:func:`estimate_layers`, in :mod:`.estimate`):

1. **Long baselines** (:mod:`.velocities`). Optical flow (Farnebäck or DIS) from the
   first measuring bin to every later bin, on the log-compressed, equalised bins of
   :mod:`.bins`; each flow is a displacement ``u (c_b - c_0)`` (``c_b`` the bin centres),
   so a per-pixel velocity is the least-squares fit of displacement against time over
   all pairs (long baselines dominate: their displacement is least affected by the
   flow's fixed error). Each long-baseline flow is also started from the displacement
   the shorter baseline before it predicts, and each pixel keeps whichever flow better
   explains the pair (a displacement of a sizeable share of the frame is beyond the
   flow's pyramid on its own). A pixel's confidence is its signal-to-noise ratio times
   texture times the agreement of the pairs.
2. **Modes** (:mod:`.velocities`). The confident velocities vote in a 2-D histogram
   (0.5 px/s cells); its peaks are the candidate layer velocities (a peak must hold
   :data:`MIN_MODE_SHARE` of the confident pixels); zero velocity is always a candidate.
3. **Refinement** (:mod:`.velocities`; this step and the next two read
   :data:`~.estimate.TRACK_BINS` time bins of a stream, steps 1 and 6 the motion bins).
   Each candidate's velocity is refined to
   sub-pixel-per-second precision by maximising the agreement of the motion-compensated
   bins (every bin sampled at ``y + v c_b`` should show the same scene point ``y``,
   :mod:`.alignment`) over the pixels that voted for it, weighted by their
   signal-to-noise ratio (coarse-to-fine pattern search); after the first assignment,
   again over each layer's interior. Moving layers then closer than
   :data:`SAME_LAYER_PX_S` are one layer.
4. **Assignment** (:mod:`.labels`). Each scene point at t = 0 takes the moving layer
   with the most evidence that the pixels along its path show it (a likelihood ratio
   against stillness pooled over a small neighbourhood,
   :func:`.alignment.track_score`); points without clear evidence
   (:data:`EVIDENCE_NATS`) are tested again over wider neighbourhoods
   (:data:`POOL_SIGMAS`, the threshold falling with the noise of the pooled mean), so
   that a dark, faintly textured moving region is found. With one moving layer, the
   points clear at no scale are labelled together by a minimum cut (:mod:`.potts`):
   each takes the layer its own evidence favours where a region's evidence in sum
   outweighs the boundary that makes (:data:`.labels.BOUNDARY_NATS` per neighbour
   pair), a default layer favoured by :data:`.labels.DEFAULT_PRIOR_NATS` a point: the
   still one if the scene has clearly still parts, else the moving layer most points
   clearly follow (a global motion). A corner of an object whose content holds little
   evidence on each point but a clear sum is then the object's. With several moving
   layers the points clear at no scale take the default layer (their misfit is what
   tells the model check that a field is no set of layers). The label map is then cleaned
   with a median filter. A layer slower than :data:`MIN_SPEED_PX_S` is still; one that
   keeps under 1% of the points is merged into the largest.
   Limitation: the evidence is in the measuring bins only (a pixel exposed the whole
   frame gathers the light of the sum of its bins, whatever the motion). Where a bin's
   read noise swamps the texture (a dark wall gathering a few electrons per pixel and
   bin), no scale makes the motion clear, and moving points there stay with the default
   (still) layer; ``make bench`` (bench_layers) prints the share of the frame with the
   wrong layer per scene and motion.
5. **Boundaries at full resolution** (:mod:`.labels`). Where the working grid is coarser
   than the capture, the labels within :data:`BOUNDARY_BAND_PX` of a layer boundary are
   decided again from the full-resolution bins (:func:`.labels.refine_boundaries`).
6. **Model check** (:mod:`.model_check`). A rotation, a zoom or a non-rigid motion is no
   set of translating layers: the estimate then settles on the translation that fits
   best, and deblurring along it is worse than not deblurring.
   :func:`layered_model_check` scores the layers (with their occlusions), the smoothed
   dense long-baseline field and no motion by how well the bins agree along them; where
   the dense field explains a clear share of what the layers miss
   (:data:`LAYERED_MISS_SHARE`), the estimate says so (``check.fits``) and deblur starts
   from dense flow instead (:func:`stages.deblur.start_motion`). ``make bench``
   (bench_layers, bench_motion_models) prints the share per scene and motion.

The result is a velocity field with a handful of distinct values that
:func:`stages.deblur.operator.blur_matrix` reads as layers with occlusion.
"""

from .estimate import MAX_WORK_PX, MIN_SPEED_PX_S, LayerEstimate, estimate_layers
from .labels import BOUNDARY_BAND_PX, EVIDENCE_NATS, POOL_SIGMAS, SAME_LAYER_PX_S
from .model_check import LAYERED_MIN_GAIN, LAYERED_MISS_SHARE, ModelCheck, layered_model_check
from .velocities import MIN_MODE_SHARE, dense_long_baseline

__all__ = [
    "BOUNDARY_BAND_PX",
    "EVIDENCE_NATS",
    "LAYERED_MIN_GAIN",
    "LAYERED_MISS_SHARE",
    "MAX_WORK_PX",
    "MIN_MODE_SHARE",
    "MIN_SPEED_PX_S",
    "POOL_SIGMAS",
    "SAME_LAYER_PX_S",
    "LayerEstimate",
    "ModelCheck",
    "dense_long_baseline",
    "estimate_layers",
    "layered_model_check",
]
