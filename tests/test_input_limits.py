"""Cost bounded before allocation (issue 22 item 2): bombs and lying headers are refused
from what the files declare, before anything is inflated or allocated."""

from __future__ import annotations

import io
import json
import os
import struct
import zipfile

import numpy as np
import pytest

from stages.errors import FormatError
from stages.formats import limits
from stages.formats.hdr import HDRImage, write_hdr
from stages.formats.layered import read_layered
from tests.hostile import measure_read, write_npz_bomb

GIB = 1024**3


def test_npz_bomb_is_refused_before_inflating(tmp_path):
    bomb = tmp_path / "bomb.npz"
    inflates_to = write_npz_bomb(bomb)  # 2 GiB of zeros
    on_disk = bomb.stat().st_size
    assert inflates_to >= 2 * GIB and on_disk < 3 * 1024**2
    with zipfile.ZipFile(bomb) as zf:  # a genuine zip: the directory says 2 GiB
        assert zf.getinfo("layer:I.npy").file_size == inflates_to
    seconds, added_mib, peak_mib, outcome = measure_read(bomb)
    print(
        f"npz bomb {on_disk} B -> {inflates_to} B: refused in {seconds:.4f} s, "
        f"peak RSS +{added_mib:.1f} MiB ({peak_mib:.0f} MiB in all)"
    )
    assert outcome.startswith("refused:") and "compression ratio" in outcome
    assert added_mib < 100


def test_npz_bomb_that_is_no_vet_file_is_refused_by_its_members(tmp_path):
    bomb = tmp_path / "bomb.npz"
    write_npz_bomb(bomb, 8192, 16384)
    # Rename the tables away: what remains is a lone 512 MiB member.
    raw = bomb.read_bytes().replace(b"__meta__.npy", b"__xxxx__.npy")
    bomb.write_bytes(raw)
    with pytest.raises(FormatError, match="unexpected member '__xxxx__.npy'"):
        read_layered(bomb)


def test_bomb_whose_metadata_agrees_is_still_refused(tmp_path):
    bomb = tmp_path / "bomb.npz"
    write_npz_bomb(bomb, 32768, 16384, meta={"kind": "hdr", "sensor_size": [16384, 32768]})
    with pytest.raises(FormatError, match=r"compression ratio 10\d\d:1, over the limit of 100:1"):
        read_layered(bomb)


def test_layer_that_disagrees_with_the_declared_sensor_is_refused(tmp_path):
    bomb = tmp_path / "bomb.npz"
    write_npz_bomb(bomb, 1024, 1024, meta={"kind": "hdr", "rig": {"sensor_size": [96, 80]}})
    with pytest.raises(
        FormatError,
        match=r"rig.sensor_size: 96x80 but layer 'I' is 1024x1024 pixels; they must match",
    ):
        read_layered(bomb)


def _vet_npz(path, layer_npy: bytes, meta_text: str = '{"kind": "hdr"}') -> None:
    """An npz with the given raw ``layer:I.npy`` bytes (channels: Y) and metadata."""

    def npy(text: str) -> bytes:
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.array(text))
        return buf.getvalue()

    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("__meta__.npy", npy(meta_text))
        zf.writestr("__channels__.npy", npy(json.dumps({"I": ["Y"]})))
        zf.writestr("layer:I.npy", layer_npy)


def test_npy_header_that_promises_more_than_the_zip_holds_is_refused(tmp_path):
    p = tmp_path / "liar.npz"
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (30000, 30000, 1)}
    )
    _vet_npz(p, header.getvalue() + bytes(8 * 8 * 4))
    with pytest.raises(
        FormatError, match="declares 3600000000 bytes of data but the zip holds 256"
    ):
        read_layered(p)


def test_npz_with_bzip2_member_is_refused(tmp_path):
    p = tmp_path / "b.npz"
    with zipfile.ZipFile(p, "w", compression=zipfile.ZIP_BZIP2) as zf:
        zf.writestr("__meta__.npy", b"x")
    with pytest.raises(FormatError, match="zip method 12"):
        read_layered(p)


def _patch_data_window(path, x1: int, y1: int) -> None:
    raw = bytearray(path.read_bytes())
    key = b"dataWindow\0box2i\0"
    at = raw.index(key) + len(key) + 4
    raw[at : at + 16] = struct.pack("<4i", 0, 0, x1, y1)
    path.write_bytes(bytes(raw))


def test_exr_whose_data_window_is_a_bomb_is_refused_before_reading(tmp_path):
    p = tmp_path / "big.exr"
    write_hdr(p, HDRImage(np.zeros((16, 16, 1), np.float32), ["Y"], {}))
    _patch_data_window(p, 8191, 8191)  # 256 MiB declared by a file of under 1 KB
    seconds, added_mib, _, outcome = measure_read(p)
    print(f"EXR data window bomb: refused in {seconds:.4f} s, peak RSS +{added_mib:.1f} MiB")
    assert "compression ratio" in outcome and added_mib < 100


def test_exr_that_disagrees_with_its_declared_sensor_is_refused(tmp_path):
    p = tmp_path / "h.exr"
    write_hdr(p, HDRImage(np.ones((8, 8, 1), np.float32), ["Y"], {"sensor_size": [8, 9]}))
    with pytest.raises(FormatError, match="sensor_size: 8x9 but layer 'image' is 8x8 pixels"):
        read_layered(p)


def test_deeply_nested_metadata_is_refused_in_one_line(tmp_path):
    layer = io.BytesIO()
    np.lib.format.write_array(layer, np.ones((4, 4, 1), np.float32))
    for depth in (40, 100_000):
        p = tmp_path / f"deep{depth}.npz"
        _vet_npz(p, layer.getvalue(), '{"kind": "hdr", "x": ' + "[" * depth + "]" * depth + "}")
        with pytest.raises(FormatError, match="nested more than 32 levels deep"):
            read_layered(p)


def test_metadata_over_the_size_limit_is_refused(monkeypatch):
    monkeypatch.setattr(limits, "MAX_META_BYTES", 100)
    with pytest.raises(FormatError, match="metadata is 113 bytes, over the limit of 100"):
        limits.parse_json(json.dumps({"a": "x" * 104}), "f.exr")


def test_parse_json_reports_depth_and_keeps_shallow_documents():
    assert limits.parse_json('{"a": [[1, 2], {"b": null}]}', "f") == {"a": [[1, 2], {"b": None}]}
    with pytest.raises(FormatError, match="not valid JSON"):
        limits.parse_json("{", "f")


def test_default_input_limit_is_two_gib():
    assert limits.MAX_INPUT_BYTES == 2 * GIB or "VET_MAX_INPUT_BYTES" in os.environ
