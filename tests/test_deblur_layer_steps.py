"""Gauss-Newton steps on translating layers' velocities (stages/deblur/layer_steps.py)."""

from __future__ import annotations

import numpy as np

import stages.deblur as deblur_pkg
from stages.deblur import deblur
from stages.deblur.joint import JointOptions
from stages.metrics import measurable_floor, stops_error
from stages.scenes import builtin_chart
from tests.test_deblur_layers import _vet


def _off_by(cap, dv, monkeypatch):
    """The layered estimate replaced by the true global velocity plus ``dv`` px/s."""
    wrong = (cap.truth_motion + np.float32(dv)).astype(np.float32)
    monkeypatch.setattr(deblur_pkg, "start_motion", lambda c, init: (wrong, "layers"))


def test_a_global_translation_is_refined_on_the_misfit(monkeypatch):
    """A pan at 30 px/s of the chart, started 0.5 px/s off along x and 0.3 along y (the
    layered estimate's errors are of this size): the refined deblur moves the velocity
    towards the truth and is closer to the truth than the deblur that keeps the start."""
    cap = _vet(builtin_chart(160, 128), "translate:30,0", seed=0)
    floor = measurable_floor(cap.rig, cap.radiance_scale)

    def rms(img) -> float:
        err = stops_error(img.radiance, cap.truth, cap.T, cap.rig.frame_s, floor=floor)
        return err["all"]["rms"]

    _off_by(cap, (0.5, 0.3), monkeypatch)
    kept_img, kept_vel = deblur(cap, options=JointOptions(layer_motion=False))
    refined_img, refined_vel = deblur(cap)
    assert refined_img.meta["motion_model"] == "layers"
    v = np.unique(refined_vel.reshape(-1, 2), axis=0)
    assert len(v) == 1 and np.hypot(*(v[0] - (30.0, 0.0))) < 0.8 * np.hypot(0.5, 0.3), (
        v
    )  # (0.40 vs 0.58)
    assert np.all(kept_vel == np.float32([30.5, 0.3]))
    assert rms(refined_img) < 0.97 * rms(kept_img)  # (2.148 vs 2.275; oracle 1.613)


def test_objects_over_a_still_background_keep_their_velocity(monkeypatch):
    """With a still layer, the layers' velocities are kept (the module docstring)."""
    cap = _vet(builtin_chart(128, 96), "object:32,24,64,48:40,10", seed=0)
    _off_by(cap, (0.0, 0.0), monkeypatch)
    moving = np.any(cap.truth_motion != 0, axis=2)
    wrong = cap.truth_motion.copy()
    wrong[moving] += np.float32([1.0, 0.5])
    monkeypatch.setattr(deblur_pkg, "start_motion", lambda c, init: (wrong, "layers"))
    _img, vel = deblur(cap)
    np.testing.assert_array_equal(vel, wrong)
