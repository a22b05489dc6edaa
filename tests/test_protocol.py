"""The LCoS link protocol: frame bytes, payloads, closure encodings, the streaming parser.

Byte strings written out in hex are the specification (docs/lcos-protocol.md); a change
that alters them breaks every deployed controller, so they are pinned literally.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stages.devices.protocol import (
    FRAME_OVERHEAD,
    INFO_REPLY_MAX_BYTES,
    SYNC,
    Ack,
    Command,
    DeviceInfo,
    Encoding,
    Frame,
    FrameParser,
    Nak,
    NakReason,
    ProtocolError,
    closure_sizes,
    decode_ack,
    decode_closures,
    decode_info_reply,
    decode_nak,
    decode_open_all,
    encode_ack,
    encode_closures,
    encode_frame,
    encode_info_reply,
    encode_nak,
    encode_open_all,
    mask_crc,
    max_payload_bytes,
    pack_mask,
    unpack_mask,
    varint_sizes,
)

GRID = 1024 * 600
EXAMPLE_CELLS = [1000, 1001, 1002, 1003, 5000]
# docs/lcos-protocol.md §5
EXAMPLE_DELTA = bytes.fromhex("a55a 01 0700 04 07000000 02 e807 03 9b1f 00 84fed9d0")
EXAMPLE_ACK = bytes.fromhex("a55a 01 2300 06 0a000000 0700 d2040000 bf68ddb7 99095035")


# --- frames -------------------------------------------------------------------------


def test_info_request_bytes():
    assert encode_frame(Command.INFO, 0) == bytes.fromhex("a55a 01 0000 01 00000000 47f6e894")


def test_open_all_bytes():
    frame = encode_frame(Command.OPEN_ALL, 1, encode_open_all(0))
    assert frame == bytes.fromhex("a55a 01 0100 02 04000000 00000000 bc73428b")


def test_worked_example_close_delta_and_ack():
    payload = encode_closures(EXAMPLE_CELLS, GRID)
    assert payload == bytes.fromhex("02 e807 03 9b1f 00")
    assert encode_frame(Command.CLOSE_DELTA, 7, payload) == EXAMPLE_DELTA
    mask = np.zeros(GRID, dtype=bool)
    mask[EXAMPLE_CELLS] = True
    assert mask_crc(mask) == 0xB7DD68BF
    assert encode_frame(Command.ACK, 0x23, encode_ack(7, 1234, mask_crc(mask))) == EXAMPLE_ACK


def test_frame_layout_and_crc_coverage():
    payload = b"\x10\x20\x30"
    frame = encode_frame(Command.CLOSE_DELTA, 0x1234, payload)
    assert frame[:2] == SYNC
    assert frame[2] == 1  # version
    assert frame[3:5] == b"\x34\x12"  # seq, little-endian
    assert frame[5] == Command.CLOSE_DELTA
    assert frame[6:10] == (3).to_bytes(4, "little")
    assert frame[10:13] == payload
    # CRC-32 over version .. payload (SYNC excluded), little-endian
    assert frame[13:] == zlib.crc32(frame[2:13]).to_bytes(4, "little")
    assert len(frame) == FRAME_OVERHEAD + len(payload)


def test_small_payloads_round_trip():
    assert decode_open_all(encode_open_all(2**32 - 1)) == 2**32 - 1
    assert decode_ack(encode_ack(65535, 4_000_000_000, 0xFFFFFFFF)) == Ack(
        65535, 4_000_000_000, 0xFFFFFFFF
    )
    assert decode_nak(encode_nak(7, NakReason.OUT_OF_ORDER)) == Nak(7, NakReason.OUT_OF_ORDER)
    info = DeviceInfo((1024, 600), 1, 1, 0.002, 123456, 0x35B9EF0C, "fw 1.2 µ", seq=9)
    assert decode_info_reply(encode_info_reply(info)) == info


def test_small_payloads_reject_malformed():
    with pytest.raises(ProtocolError):
        decode_ack(b"\x00" * 9)
    with pytest.raises(ProtocolError, match="unknown reason"):
        decode_nak(b"\x07\x00\x63")
    with pytest.raises(ProtocolError):
        decode_open_all(b"\x00\x00")
    bad_grid = DeviceInfo((0, 600), 1, 1, 0.0, 0, 0, "")
    with pytest.raises(ProtocolError, match="implausible grid"):
        decode_info_reply(encode_info_reply(bad_grid))
    good = encode_info_reply(DeviceInfo((4, 4), 1, 1, 0.0, 0, 0, "abc"))
    with pytest.raises(ProtocolError, match="firmware"):
        decode_info_reply(good[:-1])


# --- masks --------------------------------------------------------------------------


def test_mask_bit_order_is_lsb_first_row_major():
    mask = np.zeros((2, 8), dtype=bool)  # H=2, W=8
    mask[0, 0] = True  # cell 0 -> byte 0 bit 0
    mask[1, 1] = True  # cell 9 -> byte 1 bit 1
    assert pack_mask(mask) == b"\x01\x02"
    np.testing.assert_array_equal(unpack_mask(b"\x01\x02", 16), mask.ravel())


def test_mask_crc_is_crc32_of_the_packed_bitmap():
    rng = np.random.default_rng(5)  # seeded: a fixed arbitrary mask
    mask = rng.random((600, 1024)) < 0.3
    expected = zlib.crc32(np.packbits(mask.ravel(), bitorder="little").tobytes())
    assert mask_crc(mask) == expected == mask_crc(mask.ravel())
    assert mask_crc(np.zeros(GRID, dtype=bool)) == 0x35B9EF0C


def test_unpack_mask_rejects_padding_and_wrong_length():
    with pytest.raises(ProtocolError, match="padding"):
        unpack_mask(b"\x00\x80", 12)
    with pytest.raises(ProtocolError, match="must be 2 bytes"):
        unpack_mask(b"\x00", 12)


# --- closure encodings ----------------------------------------------------------------


def test_varint_sizes_and_bytes():
    assert varint_sizes(np.array([0, 127, 128, 16383, 16384, 2**21 - 1, 2**21, 2**32 - 1])).tolist() == [
        1, 1, 2, 2, 3, 3, 4, 5,
    ]  # fmt: skip
    # INDICES of [0, 128, 128+1+300]: varints 0, 127, 300 = 00 | 7f | ac 02
    assert encode_closures([0, 128, 429], 1000) == bytes.fromhex("01 00 7f ac02")


def _check_all_encodings(idx: np.ndarray, n: int) -> None:
    expected = np.unique(idx)
    sizes = closure_sizes(idx, n)
    for enc in Encoding:
        payload = encode_closures(idx, n, encoding=enc)
        assert payload[0] == enc
        assert len(payload) == sizes[enc], enc
        np.testing.assert_array_equal(decode_closures(payload, n), expected)
    chosen = encode_closures(idx, n)
    assert len(chosen) == min(sizes.values())
    assert chosen[0] == min(sizes, key=lambda e: (sizes[e], int(e)))  # ties: the lower tag
    np.testing.assert_array_equal(decode_closures(chosen, n), expected)


@pytest.mark.parametrize(
    "name",
    ["empty", "first", "last", "all", "block", "rows", "sparse", "dense", "half", "unsorted-dups"],
)
def test_encodings_round_trip_and_chooser_picks_smallest(name):
    n = 1024 * 600
    rng = np.random.default_rng(11)  # seeded so each case is the same set every run
    yy, xx = np.divmod(np.arange(n), 1024)
    idx = {
        "empty": np.zeros(0, dtype=np.int64),
        "first": np.array([0]),
        "last": np.array([n - 1]),
        "all": np.arange(n),
        "block": np.flatnonzero((abs(xx - 500) < 40) & (abs(yy - 300) < 30)),
        "rows": np.arange(10 * 1024, 14 * 1024),
        "sparse": np.flatnonzero(rng.random(n) < 0.002),
        "dense": np.flatnonzero(rng.random(n) < 0.5),
        "half": np.flatnonzero(xx < 512),
        "unsorted-dups": rng.integers(0, n, 50_000),
    }[name]
    _check_all_encodings(idx, n)


def test_chooser_prefers_each_encoding_where_it_is_smallest():
    n = 1024 * 600
    rng = np.random.default_rng(3)  # seeded: a fixed scattered set
    assert encode_closures(rng.choice(n, 100, replace=False), n)[0] == Encoding.INDICES
    assert encode_closures(np.arange(1000, 9000), n)[0] == Encoding.RUNS
    assert encode_closures(np.arange(0, n, 2), n)[0] == Encoding.BITMAP  # checkerboard-like
    assert encode_closures([], n) == b"\x01"


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(min_value=1, max_value=3000),
    data=st.data(),
)
def test_encodings_round_trip_property(n, data):
    idx = data.draw(st.lists(st.integers(min_value=0, max_value=n - 1), max_size=400))
    _check_all_encodings(np.array(idx, dtype=np.int64), n)


def test_bool_mask_input_is_accepted():
    mask = np.zeros(100, dtype=bool)
    mask[[3, 4, 5, 50]] = True
    np.testing.assert_array_equal(decode_closures(encode_closures(mask, 100), 100), [3, 4, 5, 50])


def test_encode_rejects_bad_indices():
    with pytest.raises(ValueError, match=r"\[0, 100\)"):
        encode_closures([5, 100], 100)
    with pytest.raises(ValueError, match=r"\[0, 100\)"):
        encode_closures([-1, 5], 100)
    with pytest.raises(ValueError, match="integers"):
        encode_closures([1.5], 100)


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (b"", "no encoding tag"),
        (b"\x09\x00", "unknown CLOSE_DELTA encoding"),
        (b"\x01\x80", "truncated"),
        (b"\x01\xff\xff\xff\xff\xff\x01", "longer than 5"),
        (b"\x01\x63\x00", "outside"),  # indices 99, 100 in a 100-cell grid
        (b"\x02\x05", "odd number"),
        (b"\x02\x5a\x0a", "past the end"),  # run 90 .. 100
        (b"\x03" + b"\x00" * 12, "must be 13 bytes"),
    ],
)
def test_decode_rejects_malformed_payloads(payload, message):
    with pytest.raises(ProtocolError, match=message):
        decode_closures(payload, 100)


# --- parser ---------------------------------------------------------------------------


def _frames(n: int, start_seq: int = 0) -> list[bytes]:
    return [
        encode_frame(Command.ACK, start_seq + k, encode_ack(start_seq + k, 100 + k, k))
        for k in range(n)
    ]


def test_parser_yields_frames_fed_byte_by_byte():
    stream = b"".join(_frames(3))
    parser = FrameParser()
    got = [f for b in stream for f in parser.feed(bytes([b]))]
    assert [f.seq for f in got] == [0, 1, 2]
    assert got[1] == Frame(1, Command.ACK, encode_ack(1, 101, 1))
    assert parser.bad_frames == parser.skipped_bytes == parser.pending == 0


def test_parser_resynchronises_after_garbage():
    garbage = b"\x00\xff\xa5\x13\xa5\x5a\x09garbage\xa5"  # includes a fake SYNC + bad version
    parser = FrameParser()
    got = list(parser.feed(garbage + _frames(1)[0]))
    assert [f.seq for f in got] == [0]
    assert parser.skipped_bytes == len(garbage)
    assert parser.bad_frames == 0


def test_parser_keeps_a_trailing_half_sync():
    parser = FrameParser()
    frame = _frames(1)[0]
    assert list(parser.feed(b"junk" + frame[:1])) == []
    assert parser.pending == 1
    assert [f.seq for f in parser.feed(frame[1:])] == [0]


def test_parser_counts_bad_crc_and_finds_the_next_frame():
    a, b = _frames(2)
    damaged = bytearray(a)
    damaged[12] ^= 0x40  # inside the payload
    parser = FrameParser()
    got = list(parser.feed(bytes(damaged) + b))
    assert [f.seq for f in got] == [1]
    assert parser.bad_frames == 1
    assert parser.skipped_bytes == len(a)


def test_parser_rejects_lengths_above_its_bound_at_once():
    parser = FrameParser(max_payload=max_payload_bytes(64))
    bogus = encode_frame(Command.CLOSE_DELTA, 0, b"\x01")[:6] + (10**9).to_bytes(4, "little")
    good = encode_frame(Command.CLOSE_DELTA, 1, b"\x01")
    got = list(parser.feed(bogus + good))
    assert [f.seq for f in got] == [1]
    assert parser.pending == 0


def test_parser_host_bound_rejects_device_sized_payloads():
    parser = FrameParser()  # host default: INFO_REPLY at most
    big = encode_frame(Command.INFO_REPLY, 0, b"\x00" * (INFO_REPLY_MAX_BYTES + 1))
    assert list(parser.feed(big)) == []
    assert parser.skipped_bytes >= len(big) - 1  # a trailing A5 may be held back


def test_parser_expire_recovers_frames_swallowed_by_a_corrupted_length():
    first = bytearray(encode_frame(Command.CLOSE_DELTA, 0, b"\x01"))
    first[6] = 200  # length 1 -> 200: within the bound, so the parser waits for it
    rest = b"".join(encode_frame(Command.CLOSE_DELTA, s, b"\x01") for s in (1, 2))
    parser = FrameParser(max_payload=max_payload_bytes(10_000))
    assert list(parser.feed(bytes(first) + rest)) == []
    assert parser.pending == len(first) + len(rest)
    parser.expire()  # the link went idle
    assert [f.seq for f in parser.feed(b"")] == [1, 2]
    assert parser.bad_frames == 1 and parser.pending == 0


def test_feed_events_pass_every_byte_through_once():
    rng = np.random.default_rng(2)  # seeded garbage
    frames = _frames(5)
    pieces = []
    for f in frames:
        pieces.append(rng.integers(0, 256, int(rng.integers(0, 20)), dtype=np.uint8).tobytes())
        pieces.append(f)
    stream = b"".join(pieces)
    parser = FrameParser()
    out = []
    for k in range(0, len(stream), 7):
        for kind, item in parser.feed_events(stream[k : k + 7]):
            out.append(item.encode() if kind == "frame" else item)
    while parser.pending:
        out.append(parser.expire())
        out.extend(
            item.encode() if kind == "frame" else item for kind, item in parser.feed_events(b"")
        )
    assert b"".join(out) == stream
    assert parser.frames >= 5


def test_parser_recovers_every_intact_frame_from_a_corrupted_stream():
    rng = np.random.default_rng(8)  # seeded: which frames are damaged, and how
    frames = [
        encode_frame(Command.CLOSE_DELTA, k, encode_closures(rng.integers(0, 5000, 20), 5000))
        for k in range(300)
    ]
    intact = []
    stream = bytearray()
    for k, f in enumerate(frames):
        if rng.random() < 0.2:
            f = bytearray(f)
            f[int(rng.integers(len(f)))] ^= int(rng.integers(1, 256))
            f = bytes(f)
        else:
            intact.append(k)
        stream += f
    parser = FrameParser(max_payload=max_payload_bytes(5000))
    got = []
    for k in range(0, len(stream), 64):
        got.extend(parser.feed(bytes(stream[k : k + 64])))
    while parser.pending:
        parser.expire()
        got.extend(parser.feed(b""))
    assert [f.seq for f in got] == intact
    assert parser.bad_frames >= 1
