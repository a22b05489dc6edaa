"""Does a set of translating layers describe the motion? The check against a dense field."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...cluster import in_order
from .alignment import layer_cost

#: The layered model is rejected when the dense long-baseline field explains this share
#: (or more) of what motion explains in the bins that the layers leave unexplained
#: (:func:`layered_model_check`). Where the layers describe the motion they explain the
#: bins better than the noisy dense field, and the share is negative.
LAYERED_MISS_SHARE = 0.05
#: ... and when motion explains at least this much of the bins at all (mean truncated
#: chi-square per bin and point, confidence-weighted; a still scene explains nothing).
LAYERED_MIN_GAIN = 0.2
#: Gaussian (working-grid px) of the confidence-weighted smoothing of the dense field.
DENSE_SMOOTH_PX = 2.0


@dataclass
class ModelCheck:
    """How well motion fields explain the measuring bins (:func:`layered_model_check`).

    Costs are confidence-weighted means of the truncated chi-square of the motion-
    compensated bins about their median, per bin and point (a little under 1 where the bins
    hold only noise); lower explains the bins better.
    """

    zero: float  # no motion
    layered: float  # the layered estimate
    dense: float  # the smoothed dense long-baseline field
    missed_share: float  # (layered - dense) / (zero - dense): what the layers miss
    fits: bool  # the layered model stands (else a dense field describes the motion)
    #: Where the layers do not fit: the affine field fitted to the dense one (H, W, 2),
    #: and what it misses of what the dense field explains, as ``missed_share``.
    affine: np.ndarray | None = None
    affine_share: float = float("nan")


def visible_points(label: np.ndarray, vels: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Per bin, whether each scene point of t = 0 is in front at its position, (B, H, W).

    The blur operator's own reading of the layers decides
    (:func:`stages.deblur.operator.motion_layers`, whose front-most covering layer a
    pixel sees): the point ``y`` of layer ``k`` is at the pixel ``x = y + v_k c_b`` in
    bin ``b`` and is seen there if that pixel then shows ``y``, not a point of a layer
    in front of it.
    """
    from ..operator import _layered_positions, motion_layers

    h, w = label.shape
    field = np.asarray(vels, np.float32)[label]
    vis = np.ones((len(centres), h, w), bool)
    layers = motion_layers(field)
    if layers is None or not layers.front:  # one layer: nothing hides anything
        return vis
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    for b, c in enumerate(centres):
        px = np.rint(xx + field[..., 0] * c)
        py = np.rint(yy + field[..., 1] * c)
        sx, sy = _layered_positions(layers, px, py, np.full((h, w), float(c)), h, w)
        vis[b] = (np.abs(sx - xx) <= 0.5 + 1e-6) & (np.abs(sy - yy) <= 0.5 + 1e-6)
    return vis


def layered_model_check(
    lv: np.ndarray,
    slv: np.ndarray,
    label: np.ndarray,
    vels: np.ndarray,
    dense: np.ndarray,
    conf: np.ndarray,
    centres: np.ndarray,
) -> ModelCheck:
    """Does the layered motion explain the bins as well as a dense field does?

    The layered model (a few rigidly translating layers) cannot describe a rotation, a
    zoom or a non-rigid motion: there it settles on the one translation that fits best
    and deblurs along wrong paths, which is worse than not deblurring. The dense
    long-baseline field follows any smooth motion, noisily. Both fields (and no motion)
    are scored by how well the bins, resampled along them, agree
    (:func:`.alignment.layer_cost`, whose noise normalisation makes noise score alike
    under every field), averaged over the confident points away from the border (points whose paths
    leave the image are scored by neither). The layered model is rejected when the
    dense field explains at least :data:`LAYERED_MISS_SHARE` of the motion's effect that
    the layers miss, ``(layered - dense) / (zero - dense)``, and motion explains at
    least :data:`LAYERED_MIN_GAIN` at all. ``make bench`` (bench_layers,
    bench_motion_models) prints the share for the shared scenes' still captures,
    translations, objects and rotations.

    Where the layers do not fit, the affine field fitted to the smoothed dense one
    (confidence-weighted, robust) is scored too (``affine``, ``affine_share``).

    The layered field is scored with its occlusions (a point hidden behind a layer in
    front of it is no evidence, :func:`visible_points`), as the blur operator models them; the
    dense field, which cannot describe them, is scored on every bin.

    ``label`` (H, W) and ``vels`` (K, 2) are the layers, ``dense`` an (H, W, 2) field and
    ``conf`` (H, W) weights, all on the grid of ``lv``.
    """
    from ...flow import smooth_by_confidence

    vels = np.asarray(vels, np.float32)
    layered = vels[label]
    smooth = smooth_by_confidence(dense, conf, DENSE_SMOOTH_PX, min_weight=1e-6)
    reach = max(float(np.abs(layered).max()), float(np.abs(smooth).max())) * float(np.max(centres))
    band = int(np.ceil(reach)) + 2
    wt = np.zeros_like(conf, dtype=np.float64)
    h, w = conf.shape
    if h > 2 * band and w > 2 * band:
        wt[band : h - band, band : w - band] = conf[band : h - band, band : w - band]
    if wt.sum() <= 0:
        return ModelCheck(0.0, 0.0, 0.0, 0.0, True)
    wt /= wt.sum()

    def cost(field: np.ndarray, visible: np.ndarray | None = None) -> float:
        per_point = layer_cost(lv, slv, field, centres, trunc=25.0, visible=visible)
        return float((per_point * wt).sum())

    def score(k: int) -> float:  # (no motion, the layers with their occlusions, dense)
        if k == 1:
            return cost(layered, visible_points(label, vels, centres))
        return cost(np.zeros(2) if k == 0 else smooth)

    zero, lay, den_cost = in_order(score, 3)  # (each its own: on the process's threads)
    gain = zero - den_cost
    share = (lay - den_cost) / gain if gain > 0 else 0.0
    fits = not (gain >= LAYERED_MIN_GAIN and share >= LAYERED_MISS_SHARE)
    check = ModelCheck(zero, lay, den_cost, float(share), fits)
    if not fits:  # is it one affine field (a rotation, a zoom)?
        from ..affine import fit_affine

        check.affine = fit_affine(smooth, float(np.max(centres)), weights=wt).field
        check.affine_share = float((cost(check.affine) - den_cost) / gain)
    return check
