"""The burst-merge baseline (stages/burst/): units, alignment and merge against known
answers, and the command that runs it on a capture."""

from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from stages.burst import TILE, align, burst_merge
from stages.rig import RigParams
from vet_cli.main import cli

RIG = RigParams(sensor_size=(64, 48))


def _times(k: int) -> np.ndarray:
    tau = RIG.subframe_s
    return np.stack([np.arange(k) * tau, (np.arange(k) + 1) * tau], axis=1)


def _dn(rate_e_s: np.ndarray) -> np.ndarray:
    """Mean DN of one subframe at the measurement sensor for a VET-sensor rate."""
    tau = RIG.subframe_s
    return (rate_e_s * tau * RIG.measure_fraction + RIG.dark_current_e_s * tau) * np.float32(
        RIG.gain_dn_per_e
    )


def _texture(seed: int, h: int = 48, w: int = 64) -> np.ndarray:
    """A smooth random texture of rates, 1e4 .. 1e5 e-/s (seeded: the answer is known)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min())
    return (1e4 + 9e4 * img)[..., None]


def test_noiseless_still_frames_give_their_rate():
    rate = _texture(0)
    frames = np.repeat(_dn(rate)[None], 6, axis=0)
    got, info = burst_merge(frames, _times(6), RIG)
    assert info["frames"] == 6
    np.testing.assert_allclose(got, rate, rtol=0.03)
    assert abs(float(np.median(got / rate)) - 1.0) < 1e-3


def test_alignment_finds_a_whole_pixel_shift():
    import cv2

    ref = _texture(1, 96, 128)[..., 0]
    shifted = np.roll(ref, (3, -5), axis=(0, 1))  # content of ref at y is at y + (3, -5)
    pyr = [ref]
    while min(pyr[-1].shape) >= 2 * TILE and len(pyr) < 4:
        pyr.append(cv2.pyrDown(pyr[-1]))
    d = align(pyr, shifted)
    inner = d[2:-2, 2:-2].reshape(-1, 2)
    assert (inner == (3, -5)).all(axis=1).mean() > 0.95


def test_merge_of_moving_noisy_frames_is_the_scene_at_the_first_frame():
    """Frames of a scene moving 1 px a frame, with shot and read noise: the merge is
    closer to the scene at frame 0 than frame 0 alone and than the unaligned mean."""
    rng = np.random.default_rng(2)  # the noise draw
    k = 12
    rate = _texture(3, 48, 64 + k)
    g = RIG.gain_dn_per_e
    frames = []
    for j in range(k):
        mean_e = _dn(rate[:, j : j + 64]) / g
        e = rng.poisson(mean_e) + rng.normal(0, RIG.read_noise_e, mean_e.shape)
        frames.append((e * g).astype(np.float32))
    frames = np.stack(frames)
    got, _ = burst_merge(frames, _times(k), RIG)
    truth = rate[:, :64]
    inner = (slice(4, -4), slice(4, -4))

    def err(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.log2(np.maximum(x, 1) / truth)[inner] ** 2)))

    tau = RIG.subframe_s

    def to_rate(dn: np.ndarray) -> np.ndarray:
        return (dn / g - RIG.dark_current_e_s * tau) / (tau * RIG.measure_fraction)

    assert err(got) < 0.5 * err(to_rate(frames[0]))
    assert err(got) < 0.7 * err(to_rate(frames.mean(axis=0)))


def test_dark_still_frames_merge_to_nearly_the_noise_of_their_mean():
    """In the dark one subframe is a poor reference; the second pass merges toward the
    first pass's mean, so the merge is about as quiet as the plain mean of the frames."""
    rng = np.random.default_rng(4)  # the noise draw
    k = 40
    rate = np.full((48, 64, 1), 2000.0)  # ~ 8 electrons a subframe
    g = RIG.gain_dn_per_e
    mean_e = _dn(rate) / g
    frames = np.stack(
        [
            ((rng.poisson(mean_e) + rng.normal(0, RIG.read_noise_e, mean_e.shape)) * g)
            for _ in range(k)
        ]
    ).astype(np.float32)
    got, _ = burst_merge(frames, _times(k), RIG)
    tau = RIG.subframe_s
    plain = (frames.mean(axis=0) / g - RIG.dark_current_e_s * tau) / (tau * RIG.measure_fraction)
    assert abs(float(got.mean()) / 2000.0 - 1.0) < 0.05
    assert float(got.std()) < 1.3 * float(plain.std())


def test_deblur_method_burst_on_a_capture(tmp_path):
    from stages.formats import read_hdr

    cap = tmp_path / "cap.exr"
    runner = CliRunner()
    res = runner.invoke(
        cli,
        [
            "simulate",
            "builtin:chart",
            "--size",
            "64x48",
            "--motion",
            "translate:30,0",
            "-o",
            str(cap),
        ],
    )
    assert res.exit_code == 0, res.output
    out = tmp_path / "burst.exr"
    res = runner.invoke(cli, ["deblur", str(cap), "--method", "burst", "-o", str(out)])
    assert res.exit_code == 0, res.output
    img = read_hdr(str(out))
    assert img.meta["method"] == "burst-merge"
    assert img.meta["burst"]["images"] == 131
    assert np.isfinite(img.radiance).all() and (img.radiance > 0).all()
    res = runner.invoke(
        cli, ["deblur", str(cap), "--method", "burst", "--motion-out", "m.exr", "-o", "b2.exr"]
    )
    assert res.exit_code == 2 and "does not apply to --method burst" in res.output


def test_burst_refuses_a_capture_without_measuring_images(tmp_path):
    cap = tmp_path / "cap.exr"
    runner = CliRunner()
    args = ["simulate", "builtin:chart", "--size", "32x24", "--measure-bins", "0", "-o", str(cap)]
    assert runner.invoke(cli, args).exit_code == 0
    res = runner.invoke(cli, ["deblur", str(cap), "--method", "burst", "-o", "x.exr"])
    assert res.exit_code == 1 and "two or more measuring images" in res.output


def test_burst_on_a_realistic_rig_is_as_good_as_on_the_ideal_one():
    """A realistic rig's measurement camera has its own grid (homography, distortion),
    gain and vignetting, and drops frames: its burst merge is brought onto the VET grid
    through that geometry, so that on a pan and on an object it scores within 1.1x of
    the ideal rig's all-pixel RMS and at most hdr-static's (merged on the camera's own
    grid and left there, it scored 1.18-1.19x the ideal rig's)."""
    from stages.burst import burst_hdr
    from stages.hdr_static import hdr_static
    from stages.metrics import measurable_floor, stops_error
    from stages.motion import parse_motion
    from stages.optics import rig_profile
    from stages.scenes import load_scene
    from stages.simulate import simulate

    size = (128, 96)
    scene = load_scene("builtin:interior", size)
    for spec in ("translate:30,0", "object:32,24,64,48:40,10"):
        rms = {}
        for profile in ("ideal", "realistic"):
            rig = rig_profile(profile, size)
            cap = simulate(scene, parse_motion(spec), rig, seed=0)["vet"]
            floor = measurable_floor(rig, cap.radiance_scale)
            for name, img in (("burst", burst_hdr(cap)), ("static", hdr_static(cap))):
                err = stops_error(img.radiance, cap.truth, cap.T, rig.frame_s, floor=floor)
                rms[profile, name] = err["all"]["rms"]
        assert rms["realistic", "burst"] < 1.1 * rms["ideal", "burst"], (spec, rms)
        assert rms["realistic", "burst"] <= rms["realistic", "static"], (spec, rms)
