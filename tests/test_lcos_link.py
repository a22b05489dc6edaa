"""The LCoS link: host driver against scripted bytes, and one behavioural suite that runs
against the emulator in its own process over a real pty and against the same controller
in-process behind a mocked transport.

Every wait in here is bounded: the driver's ACK timeout, retries and flush limit, the
emulator's start/answer timeouts, and pytest-timeout as a last resort.
"""

from __future__ import annotations

import collections
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from stages.devices import SerialLCoS
from stages.devices.lcos_emulator import (
    EmulatorConfig,
    EmulatorRecord,
    InProcessLCoS,
    LCoSEmulator,
    LCoSEmulatorCore,
    SubframeClock,
)
from stages.devices.protocol import (
    Command,
    DeviceInfo,
    NakReason,
    encode_ack,
    encode_closures,
    encode_frame,
    encode_info_reply,
    encode_nak,
    mask_crc,
    pack_mask,
)
from stages.errors import DeviceError
from stages.rig import RigParams

pytestmark = pytest.mark.timeout(60)

W, H = 16, 8
N = W * H
CRC_OPEN = mask_crc(np.zeros(N, dtype=bool))


# --- scripted transport (PyMeasure style) ---------------------------------------------


class ScriptedSerial:
    """A fake port: each exchange is (bytes the host must write, bytes the device answers).

    A write that differs from the script fails the test at once; ``assert_done`` fails
    if any scripted exchange was not used or a reply was left unread.
    """

    def __init__(self, exchanges: list[tuple[bytes, bytes]]):
        self.exchanges = collections.deque(exchanges)
        self.timeout: float | None = 0.002
        self.name = "scripted"
        self._written = bytearray()
        self._rx = bytearray()
        self.closed = False
        self.fail_reads_with: Exception | None = None

    def write(self, data: bytes) -> int:
        self._written += data
        while self.exchanges and len(self._written) >= len(self.exchanges[0][0]):
            expected, reply = self.exchanges.popleft()
            got = bytes(self._written[: len(expected)])
            assert got == expected, f"host wrote\n  {got.hex(' ')}\nexpected\n  {expected.hex(' ')}"
            del self._written[: len(expected)]
            self._rx += reply
        if not self.exchanges and self._written:
            raise AssertionError(f"unscripted write: {bytes(self._written).hex(' ')}")
        return len(data)

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        if self.fail_reads_with is not None:
            raise self.fail_reads_with
        if not self._rx:
            time.sleep(self.timeout or 0)
            return b""
        out = bytes(self._rx[:size])
        del self._rx[:size]
        return out

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        assert not self.exchanges, f"{len(self.exchanges)} scripted exchanges were not used"
        assert not self._written, "host wrote bytes after the last exchange"
        assert not self._rx, "scripted replies were left unread"


def frame(command: Command, seq: int, payload: bytes = b"") -> bytes:
    return encode_frame(command, seq, payload)


def ack(seq: int, applied: int, crc: int, dev_seq: int = 0) -> bytes:
    return frame(Command.ACK, dev_seq, encode_ack(seq, applied, crc))


def nak(expected: int, reason: NakReason, dev_seq: int = 0) -> bytes:
    return frame(Command.NAK, dev_seq, encode_nak(expected, reason))


def info_reply(seq: int = 0, version: int = 1, crc: int = CRC_OPEN) -> bytes:
    info = DeviceInfo((W, H), version, 1, 0.002, 40, crc, "scripted fw", seq=seq)
    return frame(Command.INFO_REPLY, 0, encode_info_reply(info))


INFO_0 = bytes.fromhex("a55a 01 0000 01 00000000 47f6e894")  # docs/lcos-protocol.md
OPEN_1 = bytes.fromhex("a55a 01 0100 02 04000000 00000000 bc73428b")  # OPEN_ALL frame 0, seq 1
CONNECT = [(INFO_0, info_reply())]
OPEN = [(OPEN_1, ack(1, 41, CRC_OPEN))]


def crc_of(cells) -> int:
    m = np.zeros(N, dtype=bool)
    m[list(cells)] = True
    return mask_crc(m)


def delta(seq: int, cells) -> bytes:
    return frame(Command.CLOSE_DELTA, seq, encode_closures(np.array(cells), N))


def scripted(exchanges, **kw) -> tuple[SerialLCoS, ScriptedSerial]:
    port = ScriptedSerial(exchanges)
    kw.setdefault("ack_timeout_s", 0.05)
    return SerialLCoS(port, **kw), port


# --- exact byte exchanges -------------------------------------------------------------


def test_connect_sends_info_and_reads_the_reply():
    lcos, port = scripted(CONNECT)
    assert lcos.cells == (W, H)
    assert lcos.device_info.firmware == "scripted fw"
    assert lcos.device_info.latency_subframes == 1
    assert lcos.device_info.leakage == pytest.approx(0.002)
    assert lcos.applied_subframe.tolist() == [-1] * N
    port.assert_done()


def test_open_all_then_close_cells_exact_bytes():
    cells = [3, 4, 5, 100]
    lcos, port = scripted(CONNECT + OPEN + [(delta(2, cells), ack(2, 44, crc_of(cells)))])
    assert lcos.open_all(0) == 41
    assert lcos.frame_start_subframe == 41
    assert lcos.close_cells(cells, wait=True) == 44
    assert lcos.applied_subframe[cells].tolist() == [44] * 4
    assert (lcos.applied_subframe >= 0).sum() == 4
    t = lcos.exposure_time_s(subframe_s=0.01, frame_s=1.0)
    assert t.shape == (H, W)
    assert t.ravel()[3] == pytest.approx(0.03) and t.ravel()[0] == 1.0
    port.assert_done()


def test_already_closed_cells_are_not_resent():
    lcos, port = scripted(
        CONNECT
        + OPEN
        + [(delta(2, [7]), ack(2, 42, crc_of([7]))), (delta(3, [8]), ack(3, 43, crc_of([7, 8])))]
    )
    lcos.open_all(0)
    lcos.close_cells([7], wait=True)
    assert lcos.close_cells([7], wait=True) is None  # nothing new: no frame
    lcos.close_cells([7, 8], wait=True)
    assert lcos.applied_subframe[[7, 8]].tolist() == [42, 43]
    port.assert_done()


def test_full_mask_exact_bytes():
    pattern = (np.indices((H, W)).sum(axis=0) % 2).astype(bool)  # checkerboard
    lcos, port = scripted(
        CONNECT + [(frame(Command.FULL_MASK, 1, pack_mask(pattern)), ack(1, 50, mask_crc(pattern)))]
    )
    assert lcos.send_full_mask(pattern) == 50
    np.testing.assert_array_equal(lcos.applied_subframe, np.where(pattern.ravel(), 50, -1))
    port.assert_done()


def test_nak_makes_the_host_retransmit():
    f = delta(2, [9])
    lcos, port = scripted(
        CONNECT + OPEN + [(f, nak(2, NakReason.BAD_CRC)), (f, ack(2, 45, crc_of([9])))]
    )
    lcos.open_all(0)
    assert lcos.close_cells([9], wait=True) == 45
    s = lcos.stats
    assert (s.naks, s.retransmits, s.timeouts) == (1, 1, 0)
    port.assert_done()


def test_silence_makes_the_host_retransmit_after_the_timeout():
    f = delta(2, [9])
    lcos, port = scripted(CONNECT + OPEN + [(f, b""), (f, ack(2, 45, crc_of([9])))])
    lcos.open_all(0)
    assert lcos.close_cells([9], wait=True) == 45
    assert (lcos.stats.timeouts, lcos.stats.retransmits) == (1, 1)
    port.assert_done()


def test_corrupted_ack_is_dropped_and_the_frame_resent():
    f = delta(2, [9])
    bad = bytearray(ack(2, 45, crc_of([9])))
    bad[12] ^= 0xFF
    lcos, port = scripted(CONNECT + OPEN + [(f, bytes(bad)), (f, ack(2, 45, crc_of([9])))])
    lcos.open_all(0)
    assert lcos.close_cells([9], wait=True) == 45
    assert lcos.stats.bad_frames == 1 and lcos.stats.retransmits == 1
    port.assert_done()


def test_garbage_before_a_reply_is_skipped():
    garbage = b"\x00\x13\xa5\xa5\x5a\x77noise"
    lcos, port = scripted(CONNECT + OPEN + [(delta(2, [1]), garbage + ack(2, 42, crc_of([1])))])
    lcos.open_all(0)
    assert lcos.close_cells([1], wait=True) == 42
    assert lcos.stats.skipped_bytes == len(garbage)
    assert lcos.stats.retransmits == 0
    port.assert_done()


def test_lost_ack_is_detected_from_a_later_ack_and_answered_from_the_cache():
    f2, f3 = delta(2, [1]), delta(3, [2])
    lcos, port = scripted(
        CONNECT
        + OPEN
        + [(f2, b""), (f3, ack(3, 43, crc_of([1, 2]))), (f2, ack(2, 42, crc_of([1])))]
    )
    lcos.open_all(0)
    lcos.close_cells([1])  # pipelined: returns without waiting
    lcos.close_cells([2])
    lcos.flush()
    assert lcos.applied_subframe[[1, 2]].tolist() == [42, 43]
    assert lcos.stats.retransmits == 1 and lcos.stats.timeouts == 0
    port.assert_done()


def test_out_of_order_nak_goes_back_n():
    f2, f3 = delta(2, [1]), delta(3, [2])
    lcos, port = scripted(
        CONNECT
        + OPEN
        + [
            (f2, b""),  # lost on the way to the device
            (f3, nak(2, NakReason.OUT_OF_ORDER)),
            (f2, ack(2, 44, crc_of([1]))),
            (f3, ack(3, 44, crc_of([1, 2]))),
        ]
    )
    lcos.open_all(0)
    lcos.close_cells([1])
    lcos.close_cells([2])
    lcos.flush()
    assert lcos.applied_subframe[[1, 2]].tolist() == [44, 44]
    assert lcos.stats.retransmits == 2
    port.assert_done()


def test_mask_crc_mismatch_triggers_a_full_mask_resync():
    closed = [1, 2]
    wrong = crc_of([1])  # the device lost cell 2
    lcos, port = scripted(
        CONNECT
        + OPEN
        + [
            (delta(2, closed), ack(2, 42, wrong)),
            (
                frame(Command.FULL_MASK, 3, pack_mask(np.isin(np.arange(N), closed))),
                ack(3, 43, crc_of(closed)),
            ),
        ]
    )
    lcos.open_all(0)
    lcos.close_cells(closed)
    lcos.flush()
    assert lcos.stats.resyncs == 1
    np.testing.assert_array_equal(lcos.committed_mask.ravel(), np.isin(np.arange(N), closed))
    port.assert_done()


def test_resync_that_does_not_take_raises():
    lcos, port = scripted(
        CONNECT
        + OPEN
        + [
            (delta(2, [1]), ack(2, 42, 0)),
            (frame(Command.FULL_MASK, 3, pack_mask(np.arange(N) == 1)), ack(3, 43, 0)),
        ]
    )
    lcos.open_all(0)
    with pytest.raises(DeviceError, match="still reports a different mask"):
        lcos.close_cells([1])
        lcos.flush()
    port.assert_done()


def test_bounded_retries_then_a_clear_error():
    f = delta(2, [1])
    lcos, port = scripted(CONNECT + OPEN + [(f, nak(2, NakReason.BAD_CRC))] * 3, max_retries=2)
    lcos.open_all(0)
    with pytest.raises(
        DeviceError,
        match=r"did not acknowledge frame 2 \(CLOSE_DELTA\) after 3 transmissions.*NAK BAD_CRC",
    ):
        lcos.close_cells([1], wait=True)
    port.assert_done()


def test_read_failure_is_a_device_error_naming_the_port():
    lcos, port = scripted(CONNECT + [(OPEN_1, b"")])
    port.fail_reads_with = serial.SerialException("read failed: [Errno 5] Input/output error")
    with pytest.raises(DeviceError, match="lost the LCoS link scripted: read failed"):
        lcos.open_all(0)


def test_protocol_version_mismatch_is_refused():
    port = ScriptedSerial([(INFO_0, info_reply(version=2))])
    with pytest.raises(DeviceError, match="protocol version 2"):
        SerialLCoS(port)
    assert port.closed


def test_unopenable_url_is_a_device_error():
    with pytest.raises(DeviceError, match="cannot open the LCoS link"):
        SerialLCoS("/nonexistent/ttyLCoS")


def test_bad_arguments_are_value_errors():
    lcos, port = scripted(CONNECT)
    with pytest.raises(ValueError, match=r"\[0, 128\)"):
        lcos.close_cells([N])
    with pytest.raises(ValueError, match="shape"):
        lcos.send_full_mask(np.zeros((W, H), dtype=bool))
    with pytest.raises(ValueError, match="frame_index"):
        lcos.open_all(-1)
    port.assert_done()


def test_loop_url_reaches_the_driver():
    # pyserial's loop:// echoes our own frames back: the host parser only accepts device
    # commands, so the INFO request is discarded as garbage and the handshake times out.
    with pytest.raises(DeviceError, match="did not acknowledge frame 0 \\(INFO\\)"):
        SerialLCoS("loop://", ack_timeout_s=0.02, max_retries=1)


# --- the emulated device's side of the protocol, byte for byte ---------------------------


def device_core(**settings) -> tuple[LCoSEmulatorCore, SubframeClock]:
    clock = SubframeClock(100)
    core = LCoSEmulatorCore(EmulatorConfig(cells=(W, H), **settings), clock=lambda: clock.value)
    return core, clock


def exchange(core: LCoSEmulatorCore, data: bytes) -> bytes:
    core.receive(data)
    core.poll()
    return core.pop_output()


def test_device_answers_info_open_and_delta_exactly():
    core, clock = device_core(firmware="fw")
    info = DeviceInfo((W, H), 1, 1, 0.002, 100, CRC_OPEN, "fw", seq=0)
    assert exchange(core, INFO_0) == frame(Command.INFO_REPLY, 0, encode_info_reply(info))
    assert exchange(core, OPEN_1) == ack(1, 101, CRC_OPEN, dev_seq=1)
    clock.tick()
    assert exchange(core, delta(2, [3, 4])) == ack(2, 102, crc_of([3, 4]), dev_seq=2)
    assert core.applied[[3, 4]].tolist() == [102, 102]


def test_device_naks_a_damaged_frame_once_then_recovers():
    core, _ = device_core()
    exchange(core, INFO_0)
    exchange(core, OPEN_1)
    damaged = bytearray(delta(2, [3]))
    damaged[11] ^= 0x01  # payload byte: CRC mismatch
    # the damaged frame and the one after it (now out of order) earn a single NAK
    assert exchange(core, bytes(damaged) + delta(3, [4])) == nak(2, NakReason.BAD_CRC, dev_seq=2)
    assert exchange(core, delta(2, [3]) + delta(3, [4])) == (
        ack(2, 101, crc_of([3]), dev_seq=3) + ack(3, 101, crc_of([3, 4]), dev_seq=4)
    )


def test_device_skips_garbage_and_answers_retransmissions_from_its_cache():
    core, clock = device_core()
    exchange(core, INFO_0)
    first = exchange(core, b"\x00garbage\xa5" + OPEN_1)
    assert first == ack(1, 101, CRC_OPEN, dev_seq=1)
    clock.tick(5)
    assert exchange(core, OPEN_1) == first  # same reply, nothing re-applied
    assert core.counters["duplicates"] == 1 and core.frame_start == 101


def test_device_naks_gaps_bad_payloads_and_unknown_commands():
    core, _ = device_core()
    exchange(core, INFO_0)
    assert exchange(core, delta(3, [1]) + delta(4, [2])) == nak(
        1, NakReason.OUT_OF_ORDER, dev_seq=1
    )
    # indices 127 and 255 in a 128-cell grid
    assert exchange(core, frame(Command.CLOSE_DELTA, 1, b"\x01\x7f\x7f")) == nak(
        1, NakReason.BAD_PAYLOAD, dev_seq=2
    )
    assert exchange(core, ack(1, 0, 0)) == nak(1, NakReason.UNKNOWN_COMMAND, dev_seq=3)
    assert not core.closed.any()


def test_device_abandons_a_partial_frame_after_an_idle_gap():
    now = [0.0]
    clock = SubframeClock(100)
    core = LCoSEmulatorCore(
        EmulatorConfig(cells=(W, H)), clock=lambda: clock.value, now=lambda: now[0]
    )
    exchange(core, INFO_0)
    long = bytearray(delta(1, [3]))
    long[6] = 12  # corrupted length, within the bound: the device waits for 10 more bytes
    assert exchange(core, bytes(long)) == b""
    now[0] = 0.04
    core.poll()
    assert core.pop_output() == b""
    now[0] = 0.06  # idle longer than idle_expire_s (0.05 s)
    core.poll()
    assert core.pop_output() == nak(1, NakReason.BAD_CRC, dev_seq=1)
    # the host resends; the device takes it
    assert exchange(core, delta(1, [3])) == ack(1, 101, crc_of([3]), dev_seq=2)


def test_device_applies_at_the_subframe_the_last_byte_arrives():
    # 1e5 bit/s, 10 bits per byte: a 1 000-byte frame takes 0.1 s = 10 subframes of 10 ms
    now = [0.0]
    core = LCoSEmulatorCore(
        EmulatorConfig(cells=(100, 80), link_bps=1e5, latency_subframes=1),
        clock=lambda: int(now[0] / 0.01 + 1e-9),
        now=lambda: now[0],
    )
    payload = encode_closures(np.arange(0, 8000, 2), 8000)  # bitmap, 1 001 bytes
    big = encode_frame(Command.CLOSE_DELTA, 1, payload)
    core.receive(INFO_0 + big)
    now[0] = 0.09
    core.poll()
    now[0] = 0.098  # the 55-byte INFO_REPLY has crossed the wire back (5.5 ms)
    assert core.pop_output().startswith(frame(Command.INFO_REPLY, 0)[:6])
    assert not core.closed.any()  # the delta is still on the wire
    now[0] = (len(INFO_0) + len(big)) * 10 / 1e5 + 1e-6  # its last byte has arrived
    core.poll()
    assert core.closed.sum() == 4000
    assert core.applied[0] == 10 + 1  # clock 10 (0.103 s) + latency
    assert core.pop_output() == b""  # the 24-byte ACK needs 2.4 ms on the way back
    now[0] += 0.0025
    assert core.pop_output() == ack(1, 11, mask_crc(core.closed), dev_seq=1)


# --- behavioural suite: emulator process over a pty, and in-process over a mock ---------


@pytest.fixture(params=["pty-process", "in-process"])
def backend(request):
    """Factory for emulated controllers of the selected kind; stops them at teardown."""
    made = []

    def make(cells=(W, H), **settings):
        cls = LCoSEmulator if request.param == "pty-process" else InProcessLCoS
        emu = cls(cells, **settings)
        made.append(emu)
        emu.start()
        return emu

    make.kind = request.param
    yield make
    for emu in made:
        try:
            emu.stop()
        except DeviceError:
            pass


def connect(emu, **kw) -> SerialLCoS:
    kw.setdefault("ack_timeout_s", 0.1)
    kw.setdefault("flush_timeout_s", 20.0)
    return SerialLCoS(emu.port, **kw)


def assert_host_matches_device(lcos: SerialLCoS, record: EmulatorRecord) -> None:
    np.testing.assert_array_equal(lcos.applied_subframe, record.applied_subframe)
    np.testing.assert_array_equal(lcos.mask.ravel(), record.closed)
    np.testing.assert_array_equal(lcos.committed_mask.ravel(), record.closed)
    assert lcos.frame_start_subframe == record.frame_start_subframe


def test_info_reports_the_configured_device(backend):
    emu = backend((32, 24), latency_subframes=2, leakage=0.01, firmware="unit fw")
    with connect(emu) as lcos:
        info = lcos.info()
        assert info.cells == (32, 24)
        assert (info.latency_subframes, info.leakage, info.firmware) == (2, 0.01, "unit fw")
        assert info.subframe == emu.subframe


def test_closures_are_applied_latency_subframes_after_arrival(backend):
    emu = backend(latency_subframes=1)
    rig = RigParams(lcos_cells=(W, H))
    with connect(emu) as lcos:
        emu.tick(10)
        s0 = lcos.open_all(3)
        assert s0 == 11  # clock 10 + latency 1
        expected = np.full(N, -1)
        for k, cells in enumerate([[0, 1], [5], [], [2, 3, 100]]):
            emu.tick()  # subframe 10 + k + 1 has started: the cameras read subframe 10 + k
            got = lcos.close_cells(cells, wait=True)
            if cells:
                assert got == 10 + k + 1 + 1
                expected[cells] = got
        np.testing.assert_array_equal(lcos.applied_subframe, expected)
        t = lcos.exposure_time_s(rig.subframe_s, rig.frame_s)
        assert t.ravel()[5] == pytest.approx(2 * rig.subframe_s)
        assert t.ravel()[6] == rig.frame_s
        record = emu.snapshot()
        assert record.frame_index == 3
        assert_host_matches_device(lcos, record)


def test_a_cell_keeps_its_first_closure_time(backend):
    emu = backend()
    with connect(emu) as lcos:
        lcos.open_all(0)
        first = lcos.close_cells([4], wait=True)
        emu.tick(5)
        lcos.close_cells([4, 5], wait=True)
        assert lcos.applied_subframe[4] == first
        assert_host_matches_device(lcos, emu.snapshot())


def test_full_mask_and_reopening(backend):
    emu = backend()
    pattern = np.zeros((H, W), dtype=bool)
    pattern[2:5, 3:9] = True
    with connect(emu) as lcos:
        emu.tick(3)
        at = lcos.send_full_mask(pattern)
        record = emu.snapshot()
        np.testing.assert_array_equal(record.closed, pattern.ravel())
        np.testing.assert_array_equal(record.applied_subframe, np.where(pattern.ravel(), at, -1))
        assert_host_matches_device(lcos, record)
        lcos.open_all(1)
        assert not emu.snapshot().closed.any()
        assert (lcos.applied_subframe == -1).all()


def test_one_percent_link_faults_every_closure_accounted_for(backend):
    # seeded: fault positions are reproducible; 1% per frame per direction over
    # ~900 frame transmissions makes a clean run vanishingly unlikely
    emu = backend((64, 48), link_fault_rate=0.01, seed=4, fault_delay_s=0.02)
    rng = np.random.default_rng(4)
    n = 64 * 48
    with connect(emu, ack_timeout_s=0.08) as lcos:
        for frame_index in range(3):
            lcos.open_all(frame_index)
            requested = np.zeros(n, dtype=bool)
            for _ in range(150):
                emu.tick()
                cells = rng.integers(0, n, int(rng.integers(0, 40)))
                requested[cells] = True
                lcos.close_cells(cells)
            lcos.flush()
            record = emu.snapshot()
            assert_host_matches_device(lcos, record)
            np.testing.assert_array_equal(record.closed, requested)
            assert (record.applied_subframe[requested] >= record.frame_start_subframe).all()
        stats = lcos.stats
    faults = sum(v for k, v in record.counters.items() if k.startswith(("rx_", "tx_")))
    assert faults > 0
    assert stats.retransmits > 0
    assert stats.frames_sent == stats.acks


def test_disconnect_is_a_device_error(backend):
    emu = backend(disconnect_at_subframe=5)
    lcos = connect(emu)
    lcos.open_all(0)
    with pytest.raises(DeviceError, match="lost the LCoS link"):
        for k in range(20):
            emu.tick()
            lcos.close_cells([k], wait=True)
    lcos.close()
    assert emu.stop().exit_reason == "disconnect injected"


def test_throttled_link_applies_large_deltas_late(backend):
    # 3 Mbit/s, 10 bits per byte: a 76.8 kB bitmap delta needs 0.256 s on the wire,
    # i.e. 128 subframes of a 2 ms free-running clock
    emu = backend((1024, 600), link_bps=3e6, subframe_s=0.002, latency_subframes=1)
    rng = np.random.default_rng(9)  # seeded: a dense scattered set that encodes as a bitmap
    with connect(emu, link_bps=3e6) as lcos:
        lcos.open_all(0)
        requested = emu.subframe
        big = np.flatnonzero(rng.random(1024 * 600) < 0.4)
        lcos.close_cells(big)
        lcos.close_cells([0])  # tiny, but queued behind the big one
        lcos.flush()
        applied = lcos.applied_subframe
        wire_subframes = (1024 * 600 // 8 + 15) * 10 / 3e6 / 0.002
        assert applied[big[1]] - (requested + 1) > 0.5 * wire_subframes
        assert applied[0] >= applied[big[1]]
        assert_host_matches_device(lcos, emu.snapshot())


def test_diverged_device_mask_is_resynchronised(backend):
    emu = backend()
    with connect(emu) as lcos:
        lcos.open_all(0)
        lcos.close_cells([1, 2, 3], wait=True)
        emu.inject_mask_fault([2])  # the device silently reopens cell 2
        emu.tick()
        lcos.close_cells([10], wait=True)
        lcos.flush()
        assert lcos.stats.resyncs == 1
        record = emu.snapshot()
        np.testing.assert_array_equal(record.closed, lcos.mask.ravel())
        assert record.closed[[1, 2, 3, 10]].all()


# --- emulator process lifecycle ---------------------------------------------------------


def test_emulator_process_exits_when_the_host_closes(tmp_path):
    path = tmp_path / "record.npz"
    emu = LCoSEmulator((W, H), record_path=str(path))
    try:
        lcos = SerialLCoS(emu.start(), ack_timeout_s=0.1)
        lcos.open_all(0)
        emu.tick()
        lcos.close_cells([1, 2], wait=True)
        host_table = lcos.applied_subframe
        lcos.close()
        deadline = time.monotonic() + 10
        while emu.running and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not emu.running
        record = emu.stop()
    finally:
        if emu.running:
            emu.stop()
    assert record.exit_reason == "host closed the port"
    np.testing.assert_array_equal(record.applied_subframe, host_table)
    saved = EmulatorRecord.load_npz(path)
    np.testing.assert_array_equal(saved.applied_subframe, host_table)
    assert saved.counters == record.counters


def test_emulator_from_rig_uses_the_rig_grid_latency_and_leakage():
    rig = RigParams(lcos_cells=(40, 30), latency_subframes=3, leakage=0.01)
    emu = LCoSEmulator.from_rig(rig, link_bps=1e6)  # configured, not started
    assert (emu.config.cells, emu.config.latency_subframes, emu.config.leakage) == (
        (40, 30),
        3,
        0.01,
    )
    assert emu.config.link_bps == 1e6
    assert not emu.running


def test_command_line_emulator_serves_one_session(tmp_path):
    path = tmp_path / "cli.npz"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "stages.devices.lcos_emulator", "--cells", "16x8", "--subframe-s", "0.001",
         "--record", str(path), "--connect-timeout-s", "20"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )  # fmt: skip
    try:
        pty_path = proc.stdout.readline().strip()
        assert pty_path.startswith("/dev/")
        with SerialLCoS(pty_path, ack_timeout_s=0.1) as lcos:
            s0 = lcos.open_all(0)
            applied = lcos.close_cells([5, 6, 7], wait=True)
            assert applied >= s0
            host_table = lcos.applied_subframe
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert "host closed the port" in proc.stderr.read()
    np.testing.assert_array_equal(EmulatorRecord.load_npz(path).applied_subframe, host_table)
