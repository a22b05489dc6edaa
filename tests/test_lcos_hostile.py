"""A hostile LCoS controller: the host driver never hangs, never allocates from a length
field, never records a T it cannot justify, and `vet capture` ends with exit 1, one line
saying what the device did, and the capture so far kept.

Each misbehaviour of ``stages.devices.lcos_emulator.hostile`` is run through the driver
(in-process transport, and one over a real pty) and two through ``vet capture`` with a
hardware rig file whose LCoS is the hostile device on a pty. Every test has a wall-clock
bound as well as pytest-timeout.
"""

from __future__ import annotations

import json
import struct
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from stages.devices import SerialLCoS
from stages.devices.lcos_emulator import (
    HOSTILE_BEHAVIOURS,
    EmulatorConfig,
    InProcessLCoS,
    LCoSEmulator,
)
from stages.devices.lcos_emulator import main as emulator_main
from stages.devices.protocol import (
    DEVICE_COMMANDS,
    FRAME_OVERHEAD,
    INFO_REPLY_MAX_BYTES,
    SYNC,
    Command,
    DeviceInfo,
    FrameParser,
    encode_ack,
    encode_frame,
    encode_info_reply,
)
from stages.errors import DeviceError, InputError
from tests.conftest import run_vet
from vet_cli.main import cli

pytestmark = pytest.mark.timeout(60)

W, H = 16, 8
LINK = {"ack_timeout_s": 0.05, "max_retries": 2, "flush_timeout_s": 5.0}
BOUND_S = 3.0  # each driver case ends well within (1 + max_retries) * timeouts + slack


def _session(behaviour: str, **device):
    """INFO and OPEN_ALL answered honestly (clock at 100), then ``behaviour``."""
    emu = InProcessLCoS((W, H), hostile=behaviour, hostile_after=2, **device)
    clock = {"subframe_s": device["subframe_s"]} if "subframe_s" in device else {}
    lcos = SerialLCoS(emu.port, **clock, **LINK)
    if emu.config.subframe_s is None:
        emu.tick(100)
    s0 = lcos.open_all(0)
    return emu, lcos, s0


def _fails(lcos: SerialLCoS, match: str) -> float:
    """Close cells 1 and 2, expect DeviceError matching ``match``; returns the seconds."""
    t = time.monotonic()
    with pytest.raises(DeviceError, match=match) as err:
        lcos.close_cells([1, 2], wait=True)
    elapsed = time.monotonic() - t
    assert "\n" not in str(err.value)
    assert elapsed < BOUND_S
    return elapsed


def test_every_behaviour_is_documented_and_tested():
    tested = {
        "garbage",
        "truncated",
        "bad-crc",
        "replay",
        "future-seq",
        "future-subframe",
        "backwards",
        "huge-length",
        "silent",
    }
    assert set(HOSTILE_BEHAVIOURS) == tested
    doc = (Path(__file__).parents[1] / "docs" / "lcos-protocol.md").read_text(encoding="utf-8")
    assert all(f"`{name}`" in doc for name in tested)


def test_an_unknown_behaviour_is_refused_by_name():
    with pytest.raises(InputError, match="hostile behaviour must be one of backwards, bad-crc"):
        EmulatorConfig(hostile="rude")
    with pytest.raises(SystemExit) as exc:
        emulator_main(["--hostile", "rude"])
    assert exc.value.code == 2


# --- through the driver, one per misbehaviour -----------------------------------------


def test_garbage_replies_end_in_a_bounded_error_naming_the_garbage():
    emu, lcos, s0 = _session("garbage")
    _fails(lcos, r"did not acknowledge frame 2 .*after 3 transmissions.*bytes of garbage")
    assert lcos.applied_subframe[[1, 2]].tolist() == [-1, -1]  # no T from garbage
    assert lcos.frame_start_subframe == s0 == 101


def test_truncated_replies_are_abandoned_and_reported():
    emu, lcos, _ = _session("truncated")
    _fails(lcos, r"sent 3 truncated frame\(s\)")
    assert lcos.stats.bad_frames == 3


def test_bad_crc_replies_are_dropped_and_reported():
    emu, lcos, _ = _session("bad-crc")
    _fails(lcos, r"sent 3 frame\(s\) with a bad CRC")
    assert lcos.applied_subframe[[1, 2]].tolist() == [-1, -1]


def test_replayed_acknowledgements_do_not_keep_the_link_alive():
    emu, lcos, _ = _session("replay")  # and repeats it unasked every 10 ms
    _fails(lcos, r"replayed acknowledgement")
    assert lcos.stats.duplicate_acks >= 5
    assert lcos.applied_subframe[[1, 2]].tolist() == [-1, -1]


def test_an_ack_for_a_frame_never_sent_is_refused_at_once():
    emu, lcos, _ = _session("future-seq")
    elapsed = _fails(
        lcos, r"acknowledged frame 102, which was never sent \(the last frame sent was 2\)"
    )
    assert elapsed < 0.5  # no waiting for retries: the device lied
    assert lcos.applied_subframe[[1, 2]].tolist() == [-1, -1]


def test_an_applied_subframe_in_the_future_is_refused():
    emu, lcos, s0 = _session("future-subframe", subframe_s=0.002)
    _fails(lcos, r"at subframe \d{7}, a subframe that has not happened yet")
    assert lcos.applied_subframe[[1, 2]].tolist() == [-1, -1]  # the lie never entered T


def test_applied_subframes_going_backwards_are_refused():
    emu, lcos, s0 = _session("backwards")
    emu.tick(3)
    _fails(lcos, rf"at subframe {s0 - 5}, before the previous frame's {s0}: .*went backwards")
    assert lcos.applied_subframe[[1, 2]].tolist() == [-1, -1]
    # the device did apply them: the host refuses to guess when
    assert emu.snapshot().closed[[1, 2]].all()


def test_huge_length_fields_are_skipped_without_waiting_or_allocating():
    emu, lcos, _ = _session("huge-length")
    _fails(
        lcos,
        r"impossible frame header\(s\) \(last: ACK header announcing 2147483648 payload bytes\)",
    )


def test_a_silent_device_is_reported_as_silent():
    emu, lcos, _ = _session("silent")
    _fails(lcos, r"after 3 transmissions .*the device sent nothing at all")


def test_a_silent_device_at_connect_is_a_bounded_device_error():
    emu = InProcessLCoS((W, H), hostile="silent")
    t = time.monotonic()
    with pytest.raises(DeviceError, match=r"frame 0 \(INFO\).*sent nothing at all"):
        SerialLCoS(emu.port, **LINK)
    assert time.monotonic() - t < BOUND_S


class _OneReply:
    """A port that answers the first write with ``reply`` and then stays silent."""

    def __init__(self, reply: bytes) -> None:
        self.timeout = 0.01
        self._rx = b""
        self._reply = reply

    def write(self, data: bytes) -> int:
        self._rx, self._reply = self._rx + self._reply, b""
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        out, self._rx = self._rx[:size], self._rx[size:]
        return out

    def close(self) -> None:
        pass


def test_a_device_claiming_a_huge_grid_is_refused_before_allocating():
    info = DeviceInfo((8192, 8192), 1, 1, 0.002, 0, 0, "liar", seq=0)
    port = _OneReply(encode_frame(Command.INFO_REPLY, 0, encode_info_reply(info)))
    tracemalloc.start()
    with pytest.raises(DeviceError, match="reports 8192x8192 cells but the rig says 16x8"):
        SerialLCoS(port, cells=(W, H), **LINK)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 1 << 20  # a 64 Mi-cell record would take hundreds of MB


def test_an_absurd_length_costs_no_memory_and_the_next_frame_is_found():
    """A header announcing 2**31 bytes is refused before the payload: the parser buffers
    at most one maximal frame, and the honest frame behind it still parses."""
    honest = encode_frame(Command.ACK, 7, encode_ack(3, 120, 0))
    lie = struct.pack("<2sBHBI", SYNC, 1, 6, int(Command.ACK), 1 << 31) + bytes(64)
    parser = FrameParser(INFO_REPLY_MAX_BYTES, DEVICE_COMMANDS)
    tracemalloc.start()
    frames = list(parser.feed(lie + honest))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert [f.seq for f in frames] == [7]
    assert parser.bad_headers == 1 and "2147483648" in parser.last_bad_header
    assert parser.pending <= INFO_REPLY_MAX_BYTES + FRAME_OVERHEAD
    assert peak < 1 << 20


def test_a_hostile_device_over_a_real_pty_is_a_bounded_device_error():
    with LCoSEmulator((W, H), hostile="garbage", hostile_after=2) as emu:
        lcos = SerialLCoS(emu.port, **LINK)
        try:
            emu.tick(100)
            lcos.open_all(0)
            _fails(lcos, r"bytes of garbage")
        finally:
            lcos.close()
        assert emu.stop().counters["hostile_replies"] >= 3


# --- through vet capture: a hardware rig file whose LCoS is the hostile device --------

SUB_S = 0.01
K = 40
SENSOR = (32, 24)
CELLS = (16, 12)


def _rig_folder(tmp_path, port: str):
    """Replayed cameras (16-bit PNGs) whose columns cross the threshold one after
    another, so closures go out over the first ten subframes, and a rig file."""
    import cv2

    meas, vet = tmp_path / "meas", tmp_path / "vet"
    meas.mkdir()
    vet.mkdir()
    ramp = np.linspace(4000, 300, SENSOR[0]).astype(np.uint16)
    frame = np.tile(ramp, (SENSOR[1], 1))
    for k in range(K):
        cv2.imwrite(str(meas / f"m{k:03d}.png"), frame)
    cv2.imwrite(str(vet / "v000.png"), frame)
    rig = tmp_path / "rig.toml"
    rig.write_text(
        f"[params]\nframe_s = {K * SUB_S}\nsubframe_s = {SUB_S}\n"
        f"sensor_size = [{SENSOR[0]}, {SENSOR[1]}]\nlcos_cells = [{CELLS[0]}, {CELLS[1]}]\n"
        f'[lcos]\nurl = "{port}"\nack_timeout_s = 0.05\nmax_retries = 2\n'
        f'[measurement_camera]\nsource = "{meas}"\n[vet_camera]\nsource = "{vet}"\n'
    )
    return rig


def _check_kept_capture(folder):
    assert not (folder / "capture.exr").exists()
    meta = json.loads((folder / "measure_raw.json").read_text())
    assert 0 < meta["subframes_valid"] <= K
    raw = np.load(folder / "measure_raw.npy", mmap_mode="r")
    assert raw.shape == (K, SENSOR[1], SENSOR[0], 1)
    assert int(raw[0, 0, 0, 0]) == 4000  # the first subframe, as the camera delivered it
    assert "FAULT" in (folder / "capture.log").read_text()
    assert "error" in json.loads((folder / "capture.json").read_text())
    assert not list(folder.glob(".*part*"))


def _hostile_rig(tmp_path, behaviour):
    # INFO (open), INFO (capture), OPEN_ALL and the first closures honest, then hostile
    return LCoSEmulator(CELLS, subframe_s=SUB_S, hostile=behaviour, hostile_after=4)


def test_vet_capture_with_a_silent_device_exits_1_and_keeps_the_capture(tmp_path):
    with _hostile_rig(tmp_path, "silent") as emu:
        rig = _rig_folder(tmp_path, emu.port)
        t = time.monotonic()
        res = run_vet("capture", "--rig", rig, "-o", tmp_path / "cap", timeout=60)
        elapsed = time.monotonic() - t
    err = res.stderr.decode()
    lines = err.strip().splitlines()
    assert res.returncode == 1, err
    assert "Traceback" not in err and len(lines) == 1
    assert lines[0].startswith("vet capture: error: the LCoS on ")
    assert "did not acknowledge frame" in lines[0] and "the device sent nothing at all" in lines[0]
    assert "keeps what was captured" in lines[0]
    assert elapsed < 30
    _check_kept_capture(tmp_path / "cap")


def test_vet_capture_with_a_device_whose_time_goes_backwards_exits_1(tmp_path):
    with _hostile_rig(tmp_path, "backwards") as emu:
        rig = _rig_folder(tmp_path, emu.port)
        t = time.monotonic()
        res = CliRunner().invoke(cli, ["capture", "--rig", str(rig), "-o", str(tmp_path / "cap")])
        elapsed = time.monotonic() - t
    out = res.stderr if hasattr(res, "stderr") else res.output
    lines = out.strip().splitlines()
    assert res.exit_code == 1, out
    assert "Traceback" not in out and len(lines) == 1
    assert "went backwards" in lines[0] and "keeps what was captured" in lines[0]
    assert elapsed < 30
    _check_kept_capture(tmp_path / "cap")
