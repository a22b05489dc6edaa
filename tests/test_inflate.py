"""Deflated zip members read with ISA-L (stages.formats.inflate): the bytes zipfile reads,
and damage refused as zipfile refuses it."""

from __future__ import annotations

import zipfile
import zlib

import numpy as np
import pytest

from stages.formats import inflate

pytest.importorskip("isal")

_DAMAGE = (zipfile.BadZipFile, EOFError, zlib.error, *inflate.ERRORS)


@pytest.fixture
def archive(tmp_path):
    rng = np.random.default_rng(5)
    # Compressible but not trivial (a stream's small DN), and larger than a few chunks.
    data = rng.integers(-40, 40, 300_000, dtype=np.int16).tobytes()
    path = tmp_path / "a.zip"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("deflated.bin", data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=1)
        zf.writestr("stored.bin", data[:1000], compress_type=zipfile.ZIP_STORED)
    return path, data


def _read_in_pieces(fp, piece: int) -> bytes:
    out = bytearray()
    while chunk := fp.read(piece):
        out += chunk
    return bytes(out)


@pytest.mark.parametrize("chunk", [inflate.CHUNK_BYTES, 777])
def test_a_member_reads_as_zipfile_reads_it(archive, monkeypatch, chunk):
    path, data = archive
    monkeypatch.setattr(inflate, "CHUNK_BYTES", chunk)  # (many chunks in and out)
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("deflated.bin")
        with inflate.open_member(zf, info) as fp:
            assert not isinstance(fp, zipfile.ZipExtFile)
            assert _read_in_pieces(fp, 12_345) == data
        with inflate.open_member(zf, info) as fp:
            whole = bytearray(len(data))
            assert fp.readinto(whole) == len(data) and bytes(whole) == data
            assert fp.read() == b""
        stored = zf.getinfo("stored.bin")
        with inflate.open_member(zf, stored) as fp:  # (not deflated: zipfile's own)
            assert isinstance(fp, zipfile.ZipExtFile) and fp.read() == data[:1000]


def test_a_wrong_crc_is_refused(archive):
    path, _data = archive
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("deflated.bin")
        bad = _copy(info)
        bad.CRC ^= 1
        with inflate.open_member(zf, bad) as fp, pytest.raises(zipfile.BadZipFile, match="CRC"):
            fp.read()


def test_a_member_cut_short_is_refused(archive):
    path, _data = archive
    with zipfile.ZipFile(path) as zf:
        bad = _copy(zf.getinfo("deflated.bin"))
        bad.compress_size //= 2
        with inflate.open_member(zf, bad) as fp, pytest.raises(EOFError, match="ends early"):
            fp.read()


def test_damaged_deflate_data_is_refused(archive):
    path, _data = archive
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("deflated.bin")
    raw = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    raw[start + 200 : start + 260] = b"\xff" * 60
    path.write_bytes(bytes(raw))
    with zipfile.ZipFile(path) as zf, inflate.open_member(zf, zf.getinfo("deflated.bin")) as fp:
        with pytest.raises(_DAMAGE):
            fp.read()


def test_a_bad_local_header_is_refused(archive):
    path, _data = archive
    with zipfile.ZipFile(path) as zf:
        bad = _copy(zf.getinfo("deflated.bin"))
        bad.header_offset += 1
        with pytest.raises(zipfile.BadZipFile, match="local file header"):
            inflate.open_member(zf, bad)


def _copy(info: zipfile.ZipInfo) -> zipfile.ZipInfo:
    new = zipfile.ZipInfo(info.filename, info.date_time)
    for slot in zipfile.ZipInfo.__slots__:
        try:
            setattr(new, slot, getattr(info, slot))
        except AttributeError:
            pass
    return new
