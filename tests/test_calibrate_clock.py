"""The measurement camera's frame clock (stages.calibrate.frame_clock) and its flat-field
vignetting fit (stages.calibrate.meas_flat) on synthetic data with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from stages.calibrate import frame_clock as fc
from stages.calibrate import meas_flat as mf
from stages.errors import FormatError
from stages.rig import RigParams


def test_clock_fit_is_exact_without_jitter():
    ids = np.delete(np.arange(100, 1100), [5, 6, 500])
    t = 3.25 + ids * 0.00758
    fit = fc.fit_frame_clock(ids, t, 0.00758)
    assert fit["missing"] == 3 and fit["drop_rate"] == pytest.approx(3 / 1000)
    assert fit["period_s"] == pytest.approx(0.00758, rel=1e-9)
    assert fit["trigger_jitter_s"] == pytest.approx(0, abs=1e-9)


def test_clock_jitter_is_robust_to_a_few_late_frames():
    """Gaussian jitter of 50 us on 20000 frames, 20 of them a whole millisecond late
    (a host hiccup): the spread stays within 3% of 50 us and the line ignores them."""
    rng = np.random.default_rng(1)
    ids = np.arange(20000)
    t = ids * 0.00758 + rng.normal(0, 50e-6, ids.size)
    t[rng.choice(ids.size, 20, replace=False)] += 1e-3
    fit = fc.fit_frame_clock(ids, t, 0.00758)
    assert fit["trigger_jitter_s"] == pytest.approx(50e-6, rel=0.03)
    assert fit["outliers"] >= 20 and fit["drop_rate"] == 0


def test_too_few_frames_or_a_wrong_period_are_logged(caplog):
    rig = RigParams()
    assert fc.clock_parts(np.arange(5), np.arange(5) * rig.subframe_s, rig) is None
    assert "needs 20 or more" in caplog.text
    ids = np.arange(100)
    parts, info = fc.clock_parts(ids, ids * rig.subframe_s * 1.01, rig)
    assert info["period_rel_err"] == pytest.approx(0.01) and "subframe is" in caplog.text
    assert parts == {"trigger_jitter_s": pytest.approx(0, abs=1e-9), "drop_rate": 0.0}
    # Ids that run backwards in time, or mostly missing: not a clock, skipped.
    assert fc.clock_parts(ids, -ids * rig.subframe_s, rig) is None
    sparse = np.append(ids, 10**17)
    assert fc.clock_parts(sparse, sparse * rig.subframe_s, rig) is None
    assert "jitter and drop rate not set" in caplog.text


def test_timestamps_file_round_trip_and_limits(tmp_path, monkeypatch):
    p = tmp_path / "meas_timestamps.csv"
    ids, t = np.array([4, 0, 2]), np.array([1.4, 1.0, 1.2])
    fc.write_timestamps(p, ids, t)
    got_ids, got_t = fc.read_timestamps(p)
    assert got_ids.tolist() == [0, 2, 4] and got_t.tolist() == [1.0, 1.2, 1.4]
    p.write_text("# chunk data\nframe_id,timestamp_s,exposure_us\n\n7,0.5,100\n")
    assert fc.read_timestamps(p)[0].tolist() == [7]
    monkeypatch.setattr(fc, "MAX_TIMESTAMPS_BYTES", 10)
    with pytest.raises(FormatError, match="over the limit"):
        fc.read_timestamps(p)
    monkeypatch.undo()
    p.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(FormatError, match="not a text file"):
        fc.read_timestamps(p)


def test_emulated_timestamps_follow_the_rig_clock():
    rig = RigParams(trigger_jitter_s=20e-6, drop_rate=0.01, trigger_offset_s=1e-4)
    ids, t = fc.emulated_timestamps(rig, frames=5000, seed=3)
    assert ids.size < 5000 and np.all(np.diff(ids) > 0)
    fit = fc.fit_frame_clock(ids, t, rig.subframe_s)
    assert fit["trigger_jitter_s"] == pytest.approx(20e-6, rel=0.1)
    assert abs(fit["drop_rate"] - 0.01) <= 3 * np.sqrt(0.01 * 0.99 / 5000)


@pytest.mark.parametrize("a", [0.0, 0.12, 0.5])
def test_vignetting_fit_on_the_measurement_grid(a):
    """``P (1 + a r^2)^-2`` with 1% noise on a 120x160 grid, P = 0.96: within 2% of a
    (or 0.005 for a = 0) and 0.2% of P."""
    rng = np.random.default_rng(2)
    r2 = mf.radius2((120, 160))
    ratio = 0.96 / (1 + a * r2) ** 2 * (1 + rng.normal(0, 0.01, r2.shape))
    ratio[:3] = np.nan
    fit = mf.fit_vignetting(ratio)
    assert fit["centre"] == pytest.approx(0.96, rel=2e-3)
    assert fit["vignetting"] == pytest.approx(a, rel=0.02, abs=5e-3)
    assert fit["pixels"] == 117 * 160


def test_vignetting_lives_on_the_measurement_grid_through_the_mapping():
    """A measurement camera shifted 20 px and rotated against a VET frame whose flat
    field falls off to the right: its falloff is found about its own centre, the VET
    frame's slope taken out through the mapping."""
    from stages.optics import MeasureGeometry, rig_profile

    rig = rig_profile(
        "realistic",
        (160, 120),
        measure_homography=[[0.9998, -0.0175, 20.0], [0.0175, 0.9998, -3.0], [0, 0, 1]],
    )
    h, w = 120, 160
    vet = np.tile(np.linspace(1.0, 0.7, w), (h, 1)).astype(np.float32)
    meas = MeasureGeometry(rig).render(vet[..., None])[..., 0] * rig.measure_gain
    mapping = {k: getattr(rig, k) for k in ("measure_homography", "measure_k1", "measure_k2")}
    parts, info = mf.measure_flat_parts(meas, vet, RigParams(sensor_size=(w, h)), mapping)
    assert parts["measure_vignetting"] == pytest.approx(0.12, rel=0.01)
    assert parts["measure_gain"] == pytest.approx(0.96, rel=0.01)
    assert info["pixels"] < h * w  # the pixels landing off the VET frame are left out
