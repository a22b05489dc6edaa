"""A real rig's measuring bins fitted on the measurement camera's own grid
(stages.deblur.camera_grid, ``Observations.sampling``): known answers, seeded."""

from __future__ import annotations

import numpy as np
import pytest

from stages.deblur.camera_grid import bins_on_vet_grid
from stages.deblur.problem import build_operators, observations
from stages.deblur.pyramid import coarsen
from stages.formats.capture import Capture
from stages.optics import MeasureGeometry, rig_profile

W, H = 40, 32


def noiseless_capture(truth: np.ndarray, n_bins: int = 3) -> Capture:
    """A still capture of the realistic rig whose bins are the camera's noiseless render
    of ``truth`` (H, W, 1) electrons/s: each bin ``n_sub`` subframes of it."""
    rig = rig_profile("realistic", (W, H), read_noise_e=0.0, dark_current_e_s=0.0)
    geom = MeasureGeometry(rig)
    tau = rig.subframe_s
    n_sub = 4
    light = geom.render(truth * np.float32(tau * rig.measure_fraction))
    dn = light * np.float32(rig.gain_dn_per_e * rig.measure_gain * n_sub)
    times = np.array([[b * n_sub * tau, (b + 1) * n_sub * tau] for b in range(n_bins)])
    return Capture(
        I=np.full((H, W, 1), 100.0, np.float32),
        T=np.full((H, W), rig.frame_s, np.float32),
        channels=["Y"],
        rig=rig,
        measure=np.repeat(dn[None], n_bins, axis=0),
        measure_times=times,
        meta={"measure_subframes": [n_sub] * n_bins},
    )


def texture() -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return (2e3 * (1.5 + np.sin(xx / 1.7) * np.cos(yy / 2.3)))[..., None].astype(np.float32)


def test_the_model_reproduces_noiseless_bins_on_the_cameras_grid():
    """The bins' operators (sampling times blur) map the true image onto the recorded
    bins exactly, row for row of the camera's grid."""
    truth = texture()
    cap = noiseless_capture(truth)
    obs = observations(cap)
    assert obs.sampling is not None and obs.meas_shape == cap.rig.measure_shape
    assert obs.yb.shape == (3 * W * H, 1)  # (the realistic camera is the VET sensor's size)
    _A, Ab = build_operators(obs, np.zeros((H, W, 2), np.float32))
    model = Ab.mv(truth.reshape(-1, 1).astype(np.float64))
    assert np.allclose(model, obs.yb, rtol=1e-4, atol=1e-3)
    # Without the camera's grid: bins inverted onto the VET grid, which the model does
    # not reproduce everywhere (at the frame's edges the camera sees no VET pixel).
    reg = observations(cap, measure_grid=False)
    assert reg.sampling is None
    _A, Ab_reg = build_operators(reg, np.zeros((H, W, 2), np.float32))
    miss = np.abs(Ab_reg.mv(truth.reshape(-1, 1).astype(np.float64)) - reg.yb)
    assert miss.max() > 0.1 * np.abs(reg.yb).max()


def test_bins_on_the_vet_grid_keep_the_misfits_gradient():
    """``bins_on_vet_grid``: for any VET-grid change ``z``, sum(w_v r_v z) equals the camera
    grid's r^T W S z (the motion steps' gradient), and w_v is diag(S^T W S)."""
    cap = noiseless_capture(texture(), n_bins=2)
    obs = observations(cap)
    rng = np.random.default_rng(5)
    m = obs.sampling.shape[0]
    rb = rng.normal(size=(2 * m, 1)).astype(np.float32)
    wb = rng.uniform(0.5, 2.0, size=(2 * m, 1)).astype(np.float32)
    rv, wv = bins_on_vet_grid(obs.sampling, obs.shape, rb, wb)
    assert rv.shape == wv.shape == (2 * H * W, 1)
    S = obs.sampling.astype(np.float64)
    for b in range(2):
        z = rng.normal(size=H * W)
        cam = slice(b * m, (b + 1) * m)
        vet = slice(b * H * W, (b + 1) * H * W)
        lhs = float(np.sum(wv[vet, 0] * rv[vet, 0] * z))
        rhs = float(rb[cam, 0] @ (wb[cam, 0] * (S @ z)))
        assert lhs == pytest.approx(rhs, rel=1e-4)
        diag = np.asarray(S.multiply(S).T @ wb[cam, 0]).ravel()
        assert np.allclose(wv[vet, 0], diag, rtol=1e-5)
    assert bins_on_vet_grid(obs.sampling, obs.shape, None, None) == (None, None)


def test_the_coarse_level_reproduces_a_blockwise_constant_image():
    """One level coarser (2 x 2 blocks of both grids), an image constant on the VET
    grid's blocks is mapped onto the coarse bins exactly."""
    coarse_truth = texture()[::2, ::2]
    truth = np.repeat(np.repeat(coarse_truth, 2, axis=0), 2, axis=1)
    cap = noiseless_capture(truth)
    obs = observations(cap)
    cobs, _t = coarsen(obs, cap.T, cap.rig.frame_s, cap.rig.leakage)
    assert cobs.meas_shape == (H // 2, W // 2)
    assert cobs.sampling.shape == ((H // 2) * (W // 2), (H // 2) * (W // 2))
    _A, Ab = build_operators(cobs, np.zeros((H // 2, W // 2, 2), np.float32))
    model = Ab.mv(coarse_truth.reshape(-1, 1).astype(np.float64))
    assert np.allclose(model, cobs.yb, rtol=1e-4, atol=1e-2)


def test_still_pixels_fitted_through_the_sampling_take_no_smoothness():
    """solve_image with ``still`` covering every pixel fits them on their data alone: the
    prior's weight changes nothing, where without ``still`` it smooths the result."""
    from stages.deblur.image_step import solve_image
    from stages.deblur.joint import JointOptions

    truth = texture()
    cap = noiseless_capture(truth)
    obs = observations(cap)
    A, Ab = build_operators(obs, np.zeros((H, W, 2), np.float32))
    n = H * W
    start = np.full((n, 1), float(truth.mean()))
    ref = np.full((H, W, 1), float(truth.mean()))
    zeros = np.zeros((n, 1))
    expo = np.full((n, 1), cap.rig.frame_s)
    everywhere = np.ones(n, bool)

    def solve(lam: float, still: np.ndarray | None) -> np.ndarray:
        return solve_image(
            obs,
            A,
            Ab,
            obs.w,
            obs.wb,
            start,
            ref,
            zeros,
            zeros,
            JointOptions(lam=lam),
            200,
            expo,
            free=everywhere,
            still=still,
        )

    free_of_prior = solve(0.15, everywhere)
    assert np.allclose(free_of_prior, solve(50.0, everywhere), rtol=1e-6)
    assert not np.allclose(solve(0.15, None), solve(50.0, None), rtol=1e-3)


@pytest.mark.parametrize("box", [(5, 27, 8, 30), (0, 16, 20, 40), (0, H, 0, W)])
def test_a_tiles_camera_pixels_sample_its_box_as_the_frames_do(box):
    """``CameraBins.crop``: every camera pixel whose sampled VET pixels all lie in the box
    is kept, valid, with the frame's row on the box's pixels (so its model of any image
    is the frame's); the rectangle's other pixels are not valid and sample nothing."""
    from stages.deblur.camera_grid import CameraBins

    cap = noiseless_capture(texture())
    frame = CameraBins.of(cap.rig, cap.measure)
    y0, y1, x0, x1 = box
    tile = frame.crop(box, (H, W))
    hm, wm = tile.shape
    assert tile.measure.shape == (3, hm, wm, 1)
    assert tile.sampling.shape == (hm * wm, (y1 - y0) * (x1 - x0))
    rng = np.random.default_rng(7)
    x = rng.uniform(1, 2, size=(H, W))
    full = (frame.sampling @ x.ravel()).reshape(frame.shape)
    S = frame.sampling.tocsr()
    rows = np.repeat(np.arange(S.shape[0]), np.diff(S.indptr))
    cy, cx = np.divmod(S.indices, W)
    outside = ~((cy >= y0) & (cy < y1) & (cx >= x0) & (cx < x1)) & (S.data != 0)
    held = (np.bincount(rows, outside, minlength=S.shape[0]) == 0).reshape(frame.shape)
    # The rectangle holds every such pixel, and marks exactly them valid.
    assert tile.valid.sum() == held.sum() > 0
    model = (tile.sampling @ x[y0:y1, x0:x1].ravel()).reshape(tile.shape)
    vy, vx = np.nonzero(tile.valid)
    fy, fx = np.nonzero(held)
    r0, c0 = fy.min(), fx.min()
    assert np.array_equal(vy + r0, fy) and np.array_equal(vx + c0, fx)
    assert np.allclose(model[tile.valid], full[held], rtol=1e-5)
    assert np.all(model[~tile.valid] == 0)
    assert np.array_equal(tile.measure[:, tile.valid], cap.measure[:, held])


def test_a_tiles_observations_fit_its_camera_pixels_alone():
    """A tile's capture with camera bins is observed on them: the model reproduces its
    valid pixels' noiseless bins, and the pixels that see past the tile weigh 0."""
    from dataclasses import replace

    from stages.deblur.camera_grid import CameraBins
    from stages.deblur.tiles import Tile, crop_capture
    from stages.measure_grid import register_measure

    truth = texture()
    cap = noiseless_capture(truth)
    framed = replace(register_measure(cap), camera_bins=CameraBins.of(cap.rig, cap.measure))
    tile = Tile((0, 16, 0, 20), (0, 24, 0, 28))
    crop = crop_capture(framed, tile)
    assert crop.measure.shape[1:3] == (24, 28)  # (registered: the tile's own grid)
    obs = observations(crop)
    cam = crop.camera_bins
    assert obs.meas_shape == cam.shape and obs.sampling is cam.sampling
    _A, Ab = build_operators(obs, np.zeros((24, 28, 2), np.float32))
    model = Ab.mv(truth[:24, :28].reshape(-1, 1).astype(np.float64)).reshape(3, *cam.shape)
    data = obs.yb.reshape(3, *cam.shape)
    weight = obs.wb.reshape(3, *cam.shape)
    assert np.allclose(model[:, cam.valid], data[:, cam.valid], rtol=1e-4, atol=1e-3)
    assert np.all(weight[:, ~cam.valid] == 0) and np.all(weight[:, cam.valid] > 0)
