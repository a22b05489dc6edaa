"""Tuning of the default deblur (:func:`stages.deblur.joint.deblur_joint`): its options
and their defaults, as ``vet deblur`` uses them."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class JointOptions:
    """Tuning of :func:`deblur_joint` (defaults used by ``vet deblur``)."""

    outer: int = 3
    cg_iters: int = 10
    final_cg_iters: int = 15
    lam: float = 0.15
    edge_rel: float = 0.08
    #: Edge scale in units of a pixel's relative noise, where below ``edge_rel`` (0: off).
    edge_snr: float = 3.0
    motion_alpha: float = 0.05
    motion_step_max: float = 8.0
    cauchy_k: float = 2.0
    update_motion: bool = False
    #: Refine a global affine motion (model ``affine``) by Gauss-Newton steps on its six
    #: parameters between image steps (:func:`stages.deblur.affine.affine_step`);
    #: :func:`stages.deblur.deblur` turns it off for other models and given motions.
    affine_motion: bool = True
    #: Outer steps when the affine motion is refined (each after the first refines it).
    affine_outer: int = 5
    #: Scale of each affine Gauss-Newton step (the image step absorbs part of a motion
    #: error, so a plain step falls short).
    affine_gain: float = 3.0
    #: Refine a camera path (one layer along a trajectory, model ``layer-paths``) by a
    #: Gauss-Newton step on its knots between image steps
    #: (:func:`stages.deblur.path_steps.path_step`); off as ``affine_motion`` is.
    path_motion: bool = True
    #: Outer steps when the camera path is refined (each after the first steps the path,
    #: kept only where the data then fit better: :class:`stages.deblur.path_steps.PathSearch`).
    path_outer: int = 6
    #: Refine the velocities of translating layers (model ``layers``) by Gauss-Newton
    #: steps between image steps (:func:`stages.deblur.layer_steps.layer_step`); off as
    #: ``affine_motion`` is.
    layer_motion: bool = True
    use_measure: bool = True
    #: Fit a stream capture through its aligned mean, not time bins (experimental).
    stream_fit: bool = False
    fuse_still: bool | None = None
    #: Sample spacing (px) of the VET image's operator; None: what
    #: :func:`stages.deblur.deblur` finds for the frame (:func:`stages.deblur.problem.vet_step`).
    step_px: float | None = None
    #: Sample spacing (px) of the measuring bins' operators; None: what
    #: :func:`stages.deblur.deblur` finds for the frame (:func:`stages.deblur.problem.bin_step`).
    step_px_bins: float | None = None
    levels: int = 1
    coarse_min_px: int = 48
    history: list = field(default_factory=list)


#: The smallest relative edge scale of the smoothness (``JointOptions.edge_snr``).
EDGE_REL_MIN = 0.01
