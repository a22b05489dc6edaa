"""The global affine motion (stages/deblur/affine.py): its fit, its Gauss-Newton step,
and the default deblur of a rotation, which reads it as one affine field."""

from __future__ import annotations

import numpy as np
import pytest

import stages.deblur.affine as affine
from stages.deblur import deblur
from stages.deblur.affine import affine_field, basis, fit_affine
from stages.hdr_static import hdr_static
from stages.metrics import measurable_floor, stops_error
from stages.scenes import builtin_interior
from tests.test_deblur_layers import _vet


def test_the_fit_recovers_an_affine_field_through_outliers():
    rng = np.random.default_rng(3)
    theta = np.array([3.0, 0.5, -12.0, -2.0, 9.0, 0.25])
    field = affine_field(theta, (60, 80)).astype(np.float64)
    bad = rng.random((60, 80)) < 0.2  # a fifth of the flow wrong by up to 20 px/s
    noisy = field + bad[..., None] * rng.uniform(-20, 20, (60, 80, 2))
    fit = fit_affine(noisy, 1.0)
    np.testing.assert_allclose(fit.theta, theta, atol=0.05)
    assert fit.inlier_share == pytest.approx(1 - bad.mean(), abs=0.02)
    # Weights: a field agreeing only where weighted is fitted there.
    fit_w = fit_affine(noisy, 1.0, weights=(~bad).astype(float), iterations=1)
    np.testing.assert_allclose(fit_w.theta, theta, atol=1e-6)


def test_the_basis_is_centred_and_normalised():
    p = basis((4, 6))
    assert p.shape == (24, 3)
    np.testing.assert_allclose(p[:, 0], 1.0)
    assert p[:, 1].min() == pytest.approx(-0.5) and p[:, 2].min() == pytest.approx(-0.5)


def test_the_default_deblur_of_a_rotation_refines_one_affine_field(monkeypatch):
    # A rotation is not layered; its dense flow is noisy and shrinks the rotation. As one
    # affine field, refined on the misfit, the deblur comes closer to the oracle's: dark
    # RMS 0.438 (affine) against 0.467 (dense flow), oracle 0.380, hdr-static 0.615.
    cap = _vet(builtin_interior(256, 192), "rotate:4", seed=0)
    floor = measurable_floor(cap.rig, cap.radiance_scale)

    def dark_rms(radiance):
        return stops_error(radiance, cap.truth, cap.T, cap.rig.frame_s, floor=floor)["dark"]["rms"]

    img, vel = deblur(cap)
    assert img.meta["motion_model"] == "affine"
    fit = fit_affine(vel, 1.0, iterations=1)
    np.testing.assert_allclose(vel, fit.field, atol=1e-3)  # still one affine field
    monkeypatch.setattr(affine, "AFFINE_MISS_SHARE", -np.inf)
    dense, _ = deblur(cap)
    assert dense.meta["motion_model"] == "dense"
    assert dark_rms(img.radiance) < 0.96 * dark_rms(dense.radiance)
    assert dark_rms(img.radiance) < 0.75 * dark_rms(hdr_static(cap).radiance)
