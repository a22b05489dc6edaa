"""File formats: round trips, metadata visibility, streams, atomicity, safe parsing."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from stages.errors import FormatError, InputError
from stages.formats import (
    HDRImage,
    Layered,
    limits,
    read_capture,
    read_hdr,
    read_layered,
    write_capture,
    write_hdr,
    write_layered,
)
from stages.formats import io as vio


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_capture_round_trip_keeps_every_layer_and_metadata(tmp_path, small_capture, ext):
    path = tmp_path / f"cap.{ext}"
    write_capture(path, small_capture)
    back = read_capture(path)
    np.testing.assert_array_equal(back.I, small_capture.I)
    np.testing.assert_array_equal(back.T, small_capture.T)
    np.testing.assert_array_equal(back.measure, small_capture.measure)
    np.testing.assert_allclose(back.measure_times, small_capture.measure_times)
    np.testing.assert_array_equal(back.truth, small_capture.truth)
    np.testing.assert_array_equal(back.truth_motion, small_capture.truth_motion)
    assert back.channels == small_capture.channels == ["R", "G", "B"]
    assert back.rig == small_capture.rig
    assert back.radiance_scale == pytest.approx(small_capture.radiance_scale)
    assert back.meta["provenance"][0]["step"] == "simulate"


def test_exr_and_npz_hold_the_same_content(tmp_path, small_capture):
    write_capture(tmp_path / "a.exr", small_capture)
    write_capture(tmp_path / "a.npz", small_capture)
    a, b = read_layered(tmp_path / "a.exr"), read_layered(tmp_path / "a.npz")
    assert a.channels == b.channels
    for k in a.layers:
        np.testing.assert_array_equal(a.layers[k], b.layers[k])
    assert a.meta == b.meta


def _stream_capture(size: tuple[int, int], motion: str, seed: int):
    """A simulated capture of builtin:interior that keeps its whole stream (int16)."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", size=size)
    return simulate(scene, parse_motion(motion), RigParams(sensor_size=size), seed=seed)["vet"]


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_a_stream_is_read_into_one_array_with_no_copy_beside_it(tmp_path, monkeypatch, ext):
    # The stream is most of a capture: read member by member (npz) or row block by row
    # block (EXR, 4 of this small frame's 64 rows at a time) straight into the
    # (B, H, W, C) array the capture holds, the reader's peak is that array and little
    # more (a dict of 131 layers stacked after reading would be twice it).
    import tracemalloc

    from stages.formats import exr

    monkeypatch.setattr(exr, "READ_ROWS", 4)
    cap = _stream_capture((96, 64), "translate:30,0", 0)
    path = tmp_path / f"cap.{ext}"
    write_capture(path, cap)
    tracemalloc.start()
    try:
        got = read_capture(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert got.measure.shape == cap.measure.shape and got.measure.flags.c_contiguous
    np.testing.assert_allclose(got.measure, cap.measure, rtol=1e-3)
    others = sum(a.nbytes for a in (got.I, got.T, got.truth, got.truth_motion))
    assert peak < 1.25 * got.measure.nbytes + 2 * others, (peak, got.measure.nbytes, others)


def test_exr_read_in_row_blocks_or_tiled_gives_the_same_layers(tmp_path, monkeypatch):
    # A stream's measuring images are a HALF part of their own; a scanline part is
    # decoded a block of rows at a time (a last block shorter); a tiled file (a vet EXR
    # saved again by another tool) is read whole: the same layers, each in its type and
    # channel order.
    import OpenImageIO as oiio

    from stages.formats import exr

    cap = _stream_capture((40, 30), "translate:30,0", seed=1)
    assert cap.measure.dtype == np.int16
    write_capture(tmp_path / "s.exr", cap)
    inp = oiio.ImageInput.open(str(tmp_path / "s.exr"))
    assert inp.seek_subimage(1, 0) and inp.spec().get_string_attribute("oiio:subimagename") == (
        "measure"
    )
    assert str(inp.spec().format) == "half" and inp.spec().channelnames[0] == "M00.R"
    inp.close()
    whole = read_layered(tmp_path / "s.exr")
    assert whole.layers["M00"].dtype == np.float16 and whole.layers["I"].dtype == np.float32
    np.testing.assert_array_equal(whole.layers["M00"], cap.measure[0].astype(np.float16))
    monkeypatch.setattr(exr, "READ_ROWS", 7)  # 30 rows: blocks of 7, 7, 7, 7 and 2
    blocks = read_layered(tmp_path / "s.exr")
    # One part (measuring images in float32 stay with the others), saved tiled.
    cap.measure = cap.measure.astype(np.float32)
    write_capture(tmp_path / "one.exr", cap)
    buf = oiio.ImageBuf(str(tmp_path / "one.exr"))
    buf.set_write_tiles(16, 16)
    assert buf.write(str(tmp_path / "t.exr")), buf.geterror()
    for got, want in (
        (blocks, whole),
        (read_layered(tmp_path / "t.exr"), read_layered(tmp_path / "one.exr")),
    ):
        assert got.channels == want.channels
        for k, v in want.layers.items():
            assert got.layers[k].dtype == v.dtype, k
            np.testing.assert_array_equal(got.layers[k], v)


def test_channel_order_survives_even_though_exr_reorders(tmp_path):
    data = Layered(meta={"kind": "test"})
    arr = np.arange(4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    data.add("", arr, ["B", "G", "R"])  # deliberately not alphabetical/RGB order
    write_layered(tmp_path / "x.exr", data)
    back = read_layered(tmp_path / "x.exr")
    assert back.channels[""] == ["B", "G", "R"]
    np.testing.assert_array_equal(back.layers[""], arr)


def test_single_channel_layer_is_not_corrupted(tmp_path):
    # OIIO silently corrupts 2-D arrays; the container must always pass (H, W, C).
    data = Layered(meta={"kind": "test"})
    arr = np.random.default_rng(1).random((7, 9)).astype(np.float32)
    data.add("T", arr, ["Y"])
    write_layered(tmp_path / "t.exr", data)
    np.testing.assert_array_equal(read_layered(tmp_path / "t.exr").layers["T"][:, :, 0], arr)


def test_large_values_stay_float32_not_half(tmp_path):
    data = Layered(meta={"kind": "test"})
    data.add("I", np.full((3, 3, 1), 1e6, np.float32), ["Y"])
    write_layered(tmp_path / "big.exr", data)
    assert read_layered(tmp_path / "big.exr").layers["I"].max() == 1e6


def test_metadata_readable_by_oiiotool(tmp_path, small_capture):
    oiiotool = shutil.which("oiiotool") or str(Path(sys.executable).parent / "oiiotool")
    if not Path(oiiotool).exists():
        pytest.skip("oiiotool not installed")
    write_capture(tmp_path / "c.exr", small_capture)
    out = subprocess.run(
        [oiiotool, "--info", "-v", str(tmp_path / "c.exr")], capture_output=True, text=True
    )
    assert 'vetKind: "capture"' in out.stdout
    chunks = [ln for ln in out.stdout.splitlines() if ln.strip().startswith("vetMeta")]
    assert chunks[0].strip().startswith("vetMeta: ")  # then vetMeta0001, ... in order
    text = "".join(ln.split(": ", 1)[1].strip()[1:-1] for ln in chunks)  # unquote each
    assert json.loads(text)["rig"]["frame_s"] == 0.99975 and "radiance_scale" in text


def test_hdr_round_trip_and_foreign_exr(tmp_path):
    rad = np.random.default_rng(2).random((6, 8, 3)).astype(np.float32) * 1e4
    mask = np.zeros((6, 8), np.uint8)
    mask[0, 0] = 3
    write_hdr(tmp_path / "h.exr", HDRImage(rad, ["R", "G", "B"], {"units": "scene"}, mask))
    back = read_hdr(tmp_path / "h.exr")
    np.testing.assert_array_equal(back.radiance, rad)
    assert back.mask[0, 0] == 3 and back.meta["units"] == "scene"
    # A plain RGBA EXR from elsewhere reads as radiance, alpha ignored.
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(8, 6, 4, "float")
    out = oiio.ImageOutput.create(str(tmp_path / "plain.exr"))
    out.open(str(tmp_path / "plain.exr"), spec)
    out.write_image(np.dstack([rad, np.ones((6, 8), np.float32)]))
    out.close()
    plain = read_hdr(tmp_path / "plain.exr")
    assert plain.channels == ["R", "G", "B"]
    np.testing.assert_allclose(plain.radiance, rad, rtol=1e-6)


def test_sniff_by_magic_not_extension(tmp_path, small_capture):
    write_capture(tmp_path / "c.npz", small_capture)
    renamed = tmp_path / "looks_like.exr"
    (tmp_path / "c.npz").rename(renamed)
    assert vio.sniff(renamed) == "npz"
    assert read_capture(renamed).I.shape == small_capture.I.shape


def test_stdin_is_spooled_and_sniffed(tmp_path, small_capture, monkeypatch):
    write_capture(tmp_path / "c.exr", small_capture)
    payload = (tmp_path / "c.exr").read_bytes()
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(payload)))
    cap = read_capture("-")
    np.testing.assert_array_equal(cap.I, small_capture.I)


def test_atomic_output_failure_leaves_existing_file_untouched(tmp_path):
    target = tmp_path / "keep.exr"
    target.write_bytes(b"precious")
    with pytest.raises(RuntimeError), vio.atomic_output(target) as tmp:
        tmp.write_bytes(b"half-writ")
        raise RuntimeError("killed")
    assert target.read_bytes() == b"precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr"]


def test_pickled_npz_is_refused(tmp_path):
    p = tmp_path / "evil.npz"
    np.savez(p, **{"layer:I": np.array([{"x": 1}], dtype=object)}, __meta__=np.array("{}"))
    with pytest.raises(FormatError, match="pickle"):
        read_layered(p)


def test_declared_size_over_limit_is_refused_before_allocating(
    tmp_path, small_capture, monkeypatch
):
    write_capture(tmp_path / "c.npz", small_capture)
    write_capture(tmp_path / "c.exr", small_capture)
    monkeypatch.setattr(limits, "MAX_INPUT_BYTES", 1000)
    monkeypatch.setattr(limits, "MAX_DENSE_INPUT_BYTES", 1000)
    for name in ("c.npz", "c.exr"):
        with pytest.raises(FormatError, match="over the limit"):
            read_layered(tmp_path / name)


def test_a_dense_input_over_the_plain_limit_reads(tmp_path, small_capture, monkeypatch):
    """Over VET_MAX_INPUT_BYTES, an input whose pixel data are at most DENSE_RATIO times
    its bytes on disk (a large frame's measured light) still reads, up to
    VET_MAX_DENSE_INPUT_BYTES; one that compresses more is refused, naming both."""
    write_capture(tmp_path / "c.npz", small_capture)
    write_capture(tmp_path / "c.exr", small_capture)
    monkeypatch.setattr(limits, "MAX_INPUT_BYTES", 1000)
    for name in ("c.npz", "c.exr"):
        got = read_layered(tmp_path / name)
        np.testing.assert_array_equal(got.layers["I"], small_capture.I)
    monkeypatch.setattr(limits, "DENSE_RATIO", 0.5)  # (any real file is then "sparse")
    for name in ("c.npz", "c.exr"):
        with pytest.raises(FormatError, match=r"for inputs that compress more than 0\.5:1"):
            read_layered(tmp_path / name)
    monkeypatch.setattr(limits, "DENSE_RATIO", 8)
    monkeypatch.setattr(limits, "MAX_DENSE_INPUT_BYTES", 2000)
    for name in ("c.npz", "c.exr"):
        with pytest.raises(FormatError, match="VET_MAX_DENSE_INPUT_BYTES"):
            read_layered(tmp_path / name)


def test_a_file_or_standard_input_over_the_dense_limit_is_refused(
    tmp_path, small_capture, monkeypatch
):
    """VET_MAX_DENSE_INPUT_BYTES bounds a file's size before it is opened, and standard
    input as it is spooled: exit 1 with one line naming the variable."""
    from tests.conftest import run_vet

    write_capture(tmp_path / "c.npz", small_capture)
    size = (tmp_path / "c.npz").stat().st_size
    monkeypatch.setattr(limits, "MAX_DENSE_INPUT_BYTES", size - 1)
    with pytest.raises(FormatError, match=f"file is {size} bytes, over the limit of {size - 1}"):
        read_layered(tmp_path / "c.npz")
    monkeypatch.setenv("VET_MAX_DENSE_INPUT_BYTES", str(size - 1))
    res = run_vet("info", "-", input=(tmp_path / "c.npz").read_bytes())
    err = res.stderr.decode().strip().splitlines()
    assert res.returncode == 1 and len(err) == 1
    assert f"standard input is over the limit of {size - 1} bytes (set VET_MAX_DENSE" in err[0]
    monkeypatch.setenv("VET_MAX_DENSE_INPUT_BYTES", str(size))
    assert run_vet("info", "-", input=(tmp_path / "c.npz").read_bytes()).returncode == 0


def test_npz_with_foreign_members_is_refused(tmp_path):
    p = tmp_path / "x.npz"
    with zipfile.ZipFile(p, "w") as zf:
        zf.writestr("readme.txt", "hello")
    with pytest.raises(FormatError, match="unexpected member"):
        read_layered(p)


def test_wrong_kind_is_refused(tmp_path):
    write_hdr(tmp_path / "h.exr", HDRImage(np.ones((4, 4, 1), np.float32), ["Y"], {}))
    with pytest.raises(FormatError, match="not a capture"):
        read_capture(tmp_path / "h.exr")


def test_capture_folder_is_accepted(tmp_path, small_capture):
    folder = tmp_path / "cap1"
    folder.mkdir()
    write_capture(folder / "capture.exr", small_capture)
    assert read_capture(folder).shape == small_capture.shape
    with pytest.raises(InputError, match="no capture file"):
        read_capture(tmp_path)


def test_unknown_output_extension(tmp_path, small_capture):
    with pytest.raises(InputError, match="unsupported output extension"):
        write_capture(tmp_path / "c.png", small_capture)
    assert not list(tmp_path.iterdir())


def test_metadata_is_json_serialisable_and_complete(tmp_path, small_capture):
    write_capture(tmp_path / "c.npz", small_capture)
    meta = read_layered(tmp_path / "c.npz").meta
    json.dumps(meta)
    for key in (
        "rig",
        "units",
        "radiance_scale",
        "method",
        "motion",
        "seed",
        "provenance",
        "measure_times",
    ):
        assert key in meta


def test_a_capture_with_its_stream_in_the_main_part_still_reads(tmp_path, monkeypatch):
    # Earlier vet wrote a stream of the sensor's size into part 0, beside float layers.
    from stages.formats import exr

    cap = _stream_capture((24, 16), "none", seed=2)
    write_capture(tmp_path / "new.exr", cap)
    monkeypatch.setattr(exr, "_exr_parts", lambda data: data.parts())
    write_capture(tmp_path / "old.exr", cap)
    old, new = read_capture(tmp_path / "old.exr"), read_capture(tmp_path / "new.exr")
    assert old.measure.dtype == new.measure.dtype == np.float16
    np.testing.assert_array_equal(old.measure, new.measure)
    np.testing.assert_array_equal(old.I, new.I)
    assert old.meta == new.meta


def test_npz_headers_are_parsed_one_at_a_time_while_layers_load_on_threads(
    tmp_path, small_capture, monkeypatch
):
    """A capture's .npz layers load on threads; numpy parses each .npy header with ast,
    which CPython 3.11 cannot run on two threads at once (a SystemError, now and then):
    no two header parses overlap, and the layers read back whole."""
    import threading
    import time

    from stages.formats import read_capture, write_capture

    write_capture(tmp_path / "c.npz", small_capture)
    inside, overlaps = [0], [0]
    guard = threading.Lock()
    import ast

    real = ast.literal_eval

    def slow_header(*args, **kwargs):
        with guard:
            inside[0] += 1
            overlaps[0] += inside[0] > 1
        time.sleep(0.002)
        try:
            return real(*args, **kwargs)
        finally:
            with guard:
                inside[0] -= 1

    monkeypatch.setattr(ast, "literal_eval", slow_header)
    monkeypatch.setattr("stages.formats.layered.solve_threads", lambda: 2)
    back = read_capture(tmp_path / "c.npz")
    assert overlaps[0] == 0
    np.testing.assert_array_equal(back.measure, small_capture.measure)
    np.testing.assert_array_equal(back.I, small_capture.I)


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_a_capture_read_without_its_truth_holds_everything_else(tmp_path, small_capture, ext):
    """read_capture(truth=False), as vet deblur reads a capture: the simulator's truth
    layers are left unread, every other layer is the same."""
    from stages.formats import read_capture, write_capture

    write_capture(tmp_path / f"c.{ext}", small_capture)
    full = read_capture(tmp_path / f"c.{ext}")
    bare = read_capture(tmp_path / f"c.{ext}", truth=False)
    assert full.truth is not None and full.truth_motion is not None
    assert bare.truth is None and bare.truth_motion is None and bare.truth_layers is None
    np.testing.assert_array_equal(bare.I, full.I)
    np.testing.assert_array_equal(bare.T, full.T)
    np.testing.assert_array_equal(bare.measure, full.measure)
    assert bare.rig == full.rig and bare.meta == full.meta


def _npy_declaring(nbytes: int, data: bytes = b"x" * 16) -> bytes:
    """A .npy stream whose header declares ``nbytes`` uint8 elements but holds ``data``."""
    import io

    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {"descr": "|u1", "fortran_order": False, "shape": (nbytes,)}
    )
    return head.getvalue() + data


def test_an_npy_header_declaring_more_data_than_its_member_holds_is_refused_unallocated():
    """A member's header is untrusted: 1 TiB declared in a 16-byte member is refused
    before any allocation (it would be a MemoryError, not this ValueError, after)."""
    import io

    from stages.formats.layered import read_npy

    stream = _npy_declaring(1 << 40)
    with pytest.raises(ValueError, match="declares 1099511627776 bytes of data, more than"):
        read_npy(io.BytesIO(stream), len(stream))
    small = _npy_declaring(16)
    assert read_npy(io.BytesIO(small), len(small)).tobytes() == b"x" * 16
