"""Rig physics and the simulator against known answers."""

from __future__ import annotations

import numpy as np
import pytest

from stages.motion import ObjectMotion, Translate, parse_motion
from stages.physics import (
    CellMap,
    ClosureController,
    SensorNoise,
    expose,
    poisson_quantile,
    shot_noise,
)
from stages.rig import RigParams
from stages.scenes import Scene
from stages.simulate import Radiance, simulate


def flat_scene(value: float, w: int = 40, h: int = 32) -> Scene:
    return Scene(np.full((h, w, 1), value, np.float32), ["Y"], "flat")


@pytest.mark.parametrize("lam", [0.5, 5.0, 29.0, 31.0, 400.0, 5000.0])
def test_shot_noise_has_poisson_mean_and_variance(lam, rng):
    x = shot_noise(np.full(200_000, lam, np.float32), rng)
    assert x.mean() == pytest.approx(lam, rel=0.01, abs=0.01)
    assert x.var() == pytest.approx(lam, rel=0.03)


@pytest.mark.parametrize("lam", [0.5, 5.0, 29.0, 31.0, 400.0, 5000.0])
def test_shared_noise_has_poisson_mean_and_variance(lam, rng):
    x = SensorNoise((200_000,), rng).shot(np.full(200_000, lam, np.float32))
    assert x.mean() == pytest.approx(lam, rel=0.01, abs=0.01)
    assert x.var() == pytest.approx(lam, rel=0.03)
    if lam < 30:  # exact Poisson counts below the normal approximation's threshold
        assert np.all(x == np.round(x))


def test_poisson_quantile_matches_scipy(rng):
    from scipy import stats

    lam = rng.uniform(0, 30, 50_000)
    lam[:100] = 0.0
    u = rng.uniform(0, 1, lam.shape)
    np.testing.assert_array_equal(poisson_quantile(u, lam), stats.poisson.ppf(u, lam))


def test_shared_noise_couples_exposures(rng):
    """Common random numbers: the same expected electrons give the same DN; more light
    never gives fewer electrons in any pixel."""
    rig = RigParams(sensor_size=(4, 4))
    noise = SensorNoise((100_000,), rng)
    lam = rng.uniform(0, 200, 100_000).astype(np.float32)
    a = expose(lam, rig, noise)
    np.testing.assert_array_equal(a, expose(lam.copy(), rig, noise))
    assert np.all(noise.shot(lam * np.float32(1.5)) >= noise.shot(lam))
    with pytest.raises(ValueError, match="noise drawn for"):
        noise.shot(lam[:10])


def test_expose_clips_at_full_well_and_adc(rng):
    rig = RigParams(sensor_size=(4, 4))
    dn = expose(np.full(1000, 1e6, np.float32), rig, rng)
    assert dn.max() == rig.max_dn
    dark = expose(np.zeros(100_000, np.float32), rig, rng)
    # Read noise only: 5 e- rms at 0.4095 DN/e- ~ 2 DN rms, unbiased thanks to the pedestal.
    assert abs(dark.mean()) < 0.02
    assert dark.std() == pytest.approx(5 * rig.gain_dn_per_e, rel=0.05)
    assert dark.min() < 0


def test_cell_map_default_homography_tiles_the_sensor():
    rig = RigParams(sensor_size=(1280, 1024))
    cm = CellMap.for_rig(rig, (1024, 1280))
    assert (
        cm.pixel_cell.min() == 0
        and cm.pixel_cell.max() == rig.lcos_cells[0] * rig.lcos_cells[1] - 1
    )
    # 1280/1024 = 1.25 px per cell across, 1024/600 = 1.71 down: pixel centres x = 2.5
    # and 3.5 fall in cell 2; rows y = 0.5 and 1.5 both in cell row 0.
    assert cm.pixel_cell[0, 2] == cm.pixel_cell[0, 3] == 2
    assert cm.pixel_cell[0, 0] == cm.pixel_cell[1, 0] == 0


def test_cell_closes_on_its_brightest_pixel():
    # 2x2 pixels per cell; one bright pixel makes the whole cell close.
    rig = RigParams(sensor_size=(4, 4), lcos_cells=(2, 2), latency_subframes=1)
    cm = CellMap.for_rig(rig, (4, 4))
    ctrl = ClosureController(rig, cm)
    frame = np.zeros((4, 4, 1), np.float32)
    frame[0, 0] = rig.threshold_dn  # top-left cell's brightest pixel reaches theta at once
    new = ctrl.step(frame, 0)
    assert list(new) == [0]
    t = ctrl.exposure_time()
    assert np.all(t[:2, :2] == pytest.approx(2 * rig.subframe_s))  # end of subframe 0 + 1 latency
    assert np.all(t[2:, :] == pytest.approx(rig.frame_s))


def test_closure_time_matches_the_threshold_arithmetic():
    """A flat still scene: every pixel crosses theta after n = ceil(theta / per-subframe)
    subframes and closes latency subframes later."""
    rig = RigParams(sensor_size=(40, 32), read_noise_e=0.0, dark_current_e_s=0.0)
    per_sub_e = rig.threshold_e / 9.5  # crosses during the 10th subframe
    scale = 1.0
    value = per_sub_e / rig.subframe_s
    cap = simulate(flat_scene(value), parse_motion("none"), rig, seed=1, radiance=Radiance(scale))[
        "vet"
    ]
    expected = (10 + rig.latency_subframes) * rig.subframe_s
    # Shot noise can move the crossing by a subframe for a few cells; the bulk is exact.
    frac = np.mean(np.isclose(cap.T, expected))
    assert frac > 0.9
    assert set(np.round(np.unique(cap.T) / rig.subframe_s).astype(int)) <= {10, 11, 12}


def test_reach_subframes_sets_when_the_p999_pixel_closes():
    """The radiance scale puts the scene's 99.9th-percentile luminance at the threshold
    after ``reach_subframes`` subframes: on a flat scene every pixel crosses then (shot
    noise: give or take one subframe) and closes the latency later."""
    rig = RigParams(sensor_size=(40, 32), read_noise_e=0.0, dark_current_e_s=0.0)
    scene = flat_scene(3.0)
    base = None
    for n in (1, 4, 8):
        cap = simulate(
            scene, parse_motion("none"), rig, seed=3, radiance=Radiance(reach_subframes=n)
        )["vet"]
        base = base or cap.radiance_scale
        assert cap.radiance_scale == pytest.approx(base / n, rel=1e-6)
        closes = np.round(cap.T / rig.subframe_s) - rig.latency_subframes
        assert np.all(np.abs(closes - n) <= 1), (n, np.unique(closes))
        assert np.median(closes) in (n, n + 1)
    with pytest.raises(ValueError, match="positive"):
        simulate(scene, parse_motion("none"), rig, radiance=Radiance(reach_subframes=0.0))


def test_leakage_and_dark_current_enter_the_vet_image():
    rig = RigParams(sensor_size=(40, 32), read_noise_e=0.0, leakage=0.01)
    value = rig.threshold_e / rig.subframe_s  # crosses in subframe 0, closes at 2 tau
    cap = simulate(
        flat_scene(value / 20), parse_motion("none"), rig, seed=2, radiance=Radiance(1.0)
    )["vet"]
    rate = value / 20
    t = cap.T[..., None]
    expect_e = rate * (t + rig.leakage * (rig.frame_s - t)) + rig.dark_current_e_s * rig.frame_s
    # Per pixel (each pixel has its own closure time); shot noise is ~1% per pixel.
    ratio = cap.I / rig.gain_dn_per_e / expect_e
    assert np.median(ratio) == pytest.approx(1.0, abs=0.003)


def test_simulate_is_deterministic_under_seed(small_scene):
    rig = RigParams(sensor_size=(96, 80))
    a = simulate(small_scene, parse_motion("translate:30,0"), rig, seed=7, measure_bins=2)["vet"]
    b = simulate(small_scene, parse_motion("translate:30,0"), rig, seed=7, measure_bins=2)["vet"]
    c = simulate(small_scene, parse_motion("translate:30,0"), rig, seed=8, measure_bins=2)["vet"]
    np.testing.assert_array_equal(a.I, b.I)
    np.testing.assert_array_equal(a.measure, b.measure)
    assert not np.array_equal(a.I, c.I)


def test_method_streams_are_independent_of_which_methods_run(small_scene):
    rig = RigParams(sensor_size=(96, 80))
    alone = simulate(small_scene, parse_motion("none"), rig, seed=4, methods=["long"])["long"]
    both = simulate(small_scene, parse_motion("none"), rig, seed=4, methods=["vet", "long"])["long"]
    np.testing.assert_array_equal(alone.I, both.I)


def test_methods_share_noise_where_they_expose_alike(small_scene):
    """A pixel exposed the whole frame through an open cell records the same value in the
    VET, long and adaptive-attenuation (transmittance 1) captures."""
    rig = RigParams(sensor_size=(96, 80))
    caps = simulate(
        small_scene,
        parse_motion("translate:30,0"),
        rig,
        seed=2,
        methods=["vet", "long", "adaptive-attenuation"],
        radiance=Radiance(reach_subframes=8),
    )
    vet, long_, adapt = caps["vet"], caps["long"], caps["adaptive-attenuation"]
    dark = vet.T >= rig.frame_s * (1 - 1e-6)
    open_ = dark & (adapt.transmittance >= 1)
    assert dark.sum() > 500 and open_.sum() > 500
    np.testing.assert_array_equal(vet.I[dark], long_.I[dark])
    np.testing.assert_array_equal(vet.I[open_], adapt.I[open_])
    assert not np.array_equal(vet.I, long_.I)


def test_truth_is_scene_at_t0_and_motion_field():
    rig = RigParams(sensor_size=(40, 32))
    sc = Scene(np.random.default_rng(0).random((32, 40, 1)).astype(np.float32) + 0.1, ["Y"], "r")
    cap = simulate(sc, ObjectMotion(5, 6, 10, 8, 40, 10), rig, seed=0)["vet"]
    np.testing.assert_array_equal(cap.truth, sc.radiance)
    assert np.all(cap.truth_motion[6:14, 5:15] == [40, 10])
    assert np.all(cap.truth_motion[:6] == 0)


def test_translate_moves_content_by_v_t():
    img = np.zeros((20, 30, 1), np.float32)
    img[10, 10] = 1.0
    moved = Translate(20.0, 0.0).render(img, 0.25)  # 5 px to the right
    assert moved[10, 15, 0] == pytest.approx(1.0)


def test_object_occludes_and_uncovers():
    img = np.zeros((20, 30, 1), np.float32)
    img[5:10, 5:10] = 1.0
    out = ObjectMotion(5, 5, 5, 5, 40.0, 0.0).render(img, 0.25)  # 10 px right
    assert out[7, 17, 0] == pytest.approx(1.0)  # object arrived
    assert out[7, 7, 0] == pytest.approx(1.0)  # uncovered area shows the still scene


@pytest.mark.parametrize(
    "bad", ["translate:1", "object:1,2,3:4,5", "spin:3", "translate:a,b", "object:0,0,0,5:1,1"]
)
def test_bad_motion_specs_are_refused(bad):
    from stages.errors import InputError

    with pytest.raises(InputError, match="invalid motion"):
        parse_motion(bad)


def test_rig_validation_speaks_sentences():
    from stages.errors import InputError

    with pytest.raises(InputError, match="leakage"):
        RigParams(leakage=1.5)
    with pytest.raises(InputError, match="unknown parameter"):
        RigParams.from_dict({"frame_s": 1.0, "warp_factor": 9})


@pytest.mark.parametrize("banded", [False, True])
@pytest.mark.parametrize("marks", [False, True])
def test_fast_controller_matches_a_plain_per_cell_max(rng, banded, marks, monkeypatch):
    """The incremental controller decides exactly like the textbook rule: close a cell
    once the maximum running sum over its pixels reaches theta (its scan on one thread,
    and in the bands on threads that large frames get; each step's cells found by sorting,
    and by marking them as steps with many crossings do)."""
    import stages.crossings
    import stages.physics

    monkeypatch.setattr(stages.physics, "MARK_CELLS_ABOVE", 0.0 if marks else 2.0)

    monkeypatch.setattr(stages.crossings, "BANDED_FROM_PIXELS", 0 if banded else 1 << 40)
    monkeypatch.setattr(stages.crossings, "SCAN_THREADS", 2)
    rig = RigParams(
        sensor_size=(50, 40),
        lcos_cells=(17, 11),
        homography=[[2.9, 0.2, 0.5], [-0.1, 3.6, 0.3], [0.0, 0.0, 1.0]],
    )
    cm = CellMap.for_rig(rig, (40, 50))
    ctrl = ClosureController(rig, cm)
    assert len(ctrl._scan._bands) == (2 if banded else 1)
    rates = rng.random((40, 50)).astype(np.float32) ** 3 * rig.threshold_dn / 8
    sums = np.zeros((40, 50), np.float32)
    ref_close = np.full(cm.n_cells + 1, ClosureController.NEVER, np.int32)
    for k in range(20):
        frame = rng.poisson(rates).astype(np.float32)
        sums += frame
        cmax = cm.cell_max(sums)
        crossed = np.flatnonzero(
            (cmax >= rig.threshold_dn) & (ref_close == ClosureController.NEVER)
        )
        crossed = crossed[crossed < cm.n_cells]
        ref_close[crossed] = k + 1 + rig.latency_subframes
        new = ctrl.step(frame, k)
        np.testing.assert_array_equal(np.sort(new), crossed)
    np.testing.assert_array_equal(ctrl.close_subframe, ref_close)
    assert 0 < (ref_close < ClosureController.NEVER).sum() < cm.n_cells


def test_brightest_channel_is_the_per_pixel_maximum(rng):
    from stages.physics import brightest_channel

    rgb = rng.random((7, 9, 3)).astype(np.float32)
    np.testing.assert_array_equal(brightest_channel(rgb), rgb.max(axis=2))
    mono = rng.random((7, 9, 1)).astype(np.float32)
    np.testing.assert_array_equal(brightest_channel(mono), mono[..., 0])
    ints = rng.integers(-64, 4096, (5, 4, 3)).astype(np.int16)
    np.testing.assert_array_equal(brightest_channel(ints), ints.max(axis=2))


def test_bin_may_clip_flags_the_bins_whose_subframes_clip():
    # Known answer by sampling: bins of 16 subframes through the sensor chain. Below the
    # flag, hardly any subframe reaches a code that may be clipped; above it, many do.
    from stages.physics import bin_may_clip

    rig = RigParams()
    g = rig.gain_dn_per_e
    rng = np.random.default_rng(3)
    # The shot-free limit is the VET image's test.
    deep = RigParams(full_well_e=1e12)
    edge = np.array([[deep.saturation_dn - 0.1], [deep.saturation_dn]], np.float32)
    assert bin_may_clip(edge, deep).tolist() == [False, True]

    def bins(mean_dn):
        subs = np.stack(
            [expose(np.full((4000, 1), mean_dn / g, np.float32), rig, rng) for _ in range(16)]
        )
        return (subs >= rig.saturation_dn).any(axis=0)[:, 0].mean(), bin_may_clip(
            subs.mean(axis=0), rig
        ).mean()

    # Well below: no subframe near a clipped code, no bin flagged; well above: most
    # bins hold one, every bin flagged; at the flag (3967 DN here) one bin in ~50 does
    # (16 subframes, each 3 sigma from a clipped code), and half the bins are flagged.
    assert bins(3900.0) == (0.0, 0.0)
    clipped, flagged = bins(4040.0)
    assert clipped > 0.8 and flagged == 1.0
    clipped, flagged = bins(3967.0)
    assert 0.005 < clipped < 0.05 and 0.3 < flagged < 0.7


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("full_well", [None, 7301.0, 1e12])
def test_bin_may_clip_is_its_formula_to_the_bit(dtype, full_well):
    # The test runs as one comparison with the least value whose 3-sigma tail reaches a
    # clipped code: the same booleans as the formula, at every value of the dtype near
    # that threshold, at random values, and at the special ones.
    from stages.physics import _clip_tail, _least_may_clip, bin_may_clip

    rig = RigParams() if full_well is None else RigParams(full_well_e=full_well)
    g, sat = np.float32(rig.gain_dn_per_e), np.float32(rig.saturation_dn)
    least = _least_may_clip(np.dtype(dtype), g, sat)
    assert least is not None
    bits = np.dtype(f"u{np.dtype(dtype).itemsize}")
    k = int(np.array(least, dtype).view(bits))
    rng = np.random.default_rng(7)
    values = np.concatenate(
        [
            np.arange(k - 3000, k + 3000).astype(bits).view(dtype),
            rng.uniform(-50.0, 1.2 * float(sat), 100_000).astype(dtype),
            np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, sat, -sat, 1.0], dtype),
        ]
    ).reshape(-1, 3)
    expected = (_clip_tail(values, g) >= sat).any(axis=-1)
    got = bin_may_clip(values, rig)
    assert got.dtype == bool and got.shape == expected.shape
    np.testing.assert_array_equal(got, expected)
    assert expected.any() and not expected.all()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_channel_mean_and_any_are_numpys_to_the_bit(rng, dtype, channels):
    from stages.physics import any_channel, channel_mean

    frame = (rng.random((3, 17, 23, channels)) * 1e4).astype(dtype)
    got = channel_mean(frame)
    assert got.dtype == frame.mean(axis=-1).dtype
    np.testing.assert_array_equal(got, frame.mean(axis=-1))
    mask = frame > 0.8e4
    np.testing.assert_array_equal(any_channel(mask), mask.any(axis=-1))
