"""Work shared over the process's threads (``stages.cluster.in_order``): results in order,
a bounded number in flight, inline on one thread, and the same values to the bit as one
thread gives (reading a capture, binning its stream, the motion estimate's rates)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from stages import cluster
from stages.formats import layered
from stages.formats.capture import read_capture, write_capture
from stages.motion import parse_motion
from stages.rig import RigParams
from stages.scenes import builtin_interior
from stages.simulate import simulate


def _threads(monkeypatch, n: int) -> None:
    monkeypatch.setattr(cluster, "solve_threads", lambda: n)
    monkeypatch.setattr(layered, "solve_threads", lambda: n)


def test_in_order_hands_out_results_in_order_with_few_in_flight(monkeypatch):
    _threads(monkeypatch, 3)
    rng = np.random.default_rng(4)
    delays = rng.uniform(0.0, 0.004, 40)
    started: list[int] = []
    lock = threading.Lock()

    def fn(k: int) -> int:
        with lock:
            started.append(k)
        time.sleep(delays[k])
        return k * k

    got = []
    ahead = []
    for k, v in enumerate(cluster.in_order(fn, 40, ahead=2)):
        got.append(v)
        with lock:
            ahead.append(len(started) - (k + 1))
    assert got == [k * k for k in range(40)]
    # 3 threads x 2 each: at most 6 calls started beyond the ones handed out
    assert max(ahead) <= 6


def test_in_order_runs_inline_on_one_thread(monkeypatch):
    _threads(monkeypatch, 1)
    names = []

    def fn(k: int) -> int:
        names.append(threading.current_thread().name)
        return k

    assert list(cluster.in_order(fn, 5)) == [0, 1, 2, 3, 4]
    assert set(names) == {threading.main_thread().name}


def test_in_order_passes_a_workers_error_on(monkeypatch):
    _threads(monkeypatch, 2)

    def fn(k: int) -> int:
        if k == 3:
            raise ValueError("bin 3")
        return k

    out = []
    with pytest.raises(ValueError, match="bin 3"):
        for v in cluster.in_order(fn, 8):
            out.append(v)
    assert out == [0, 1, 2]


@pytest.fixture(scope="module")
def stream_capture():
    return simulate(
        builtin_interior(48, 32),
        parse_motion("translate:30,0"),
        RigParams(sensor_size=(48, 32)),
        seed=5,
        methods=["vet"],
    )["vet"]


def test_a_stream_reads_and_bins_the_same_on_one_thread_and_on_several(
    tmp_path, monkeypatch, stream_capture
):
    from stages.deblur.layers.bins import binned_work_frames, rate_frames
    from stages.deblur.layers.paths import Groups

    path = tmp_path / "cap.npz"
    write_capture(path, stream_capture)
    got = {}
    for n in (1, 3):
        _threads(monkeypatch, n)
        cap = read_capture(path)
        got[n] = (
            cap.measure,
            cap.time_bins(7).measure,
            *rate_frames(cap),
            *binned_work_frames(cap, 5, 24)[:3],
            np.stack(list(Groups(cap.measure, cap.measure_times, cap.rig, 11).each())),
        )
    assert stream_capture.keeps_stream and got[1][0].shape[0] > 100
    for a, b in zip(got[1], got[3], strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_corrupt_member_read_on_threads_is_one_format_error(tmp_path, monkeypatch):
    import zipfile

    from stages.errors import FormatError

    layers = {f"m{k}": np.full((4, 5, 1), k, np.float32) for k in range(6)}
    data = layered.Layered(layers=layers, channels={k: ["Y"] for k in layers}, meta={"kind": "hdr"})
    good = tmp_path / "good.npz"
    layered.write_layered(good, data)
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(good) as zin, zipfile.ZipFile(bad, "w", zipfile.ZIP_STORED) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, zin.read(info))
    with zipfile.ZipFile(bad) as z:
        info = z.getinfo("layer:m4.npy")
        start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    raw = bytearray(bad.read_bytes())
    raw[start + info.file_size - 4] ^= 0xFF  # one byte of its data: the CRC no longer holds
    bad.write_bytes(bytes(raw))
    _threads(monkeypatch, 3)
    with pytest.raises(FormatError, match="bad.npz.*m4"):
        layered.read_npz(bad)
