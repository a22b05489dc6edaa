"""Deflated zip members read with ISA-L's inflate (python-isal), faster than the zlib
that :mod:`zipfile` uses: a capture's measuring stream, an npz member a frame, is most of
what reading a capture costs (``tests/benchmarks/bench_capture_io.py`` times it). Where
``isal`` is missing, or a member is stored, encrypted or compressed otherwise,
:mod:`zipfile` reads it as before.

:func:`open_member` is a readable file object over the member's data, checked as
:mod:`zipfile` checks it: its local header, its inflated size (never more than the
central directory declares is produced) and its CRC-32. Damage raises
:class:`zipfile.BadZipFile`, ``EOFError`` or :data:`ERRORS`.
"""

from __future__ import annotations

import io
import struct
import zipfile
from typing import BinaryIO

try:  # (a dependency; its absence only costs speed)
    from isal import isal_zlib as _isal
except ImportError:  # pragma: no cover - isal ships wheels for the platforms vet runs on
    _isal = None

#: A zip local file header: signature, then fixed fields, the name and extra lengths last.
_LOCAL = struct.Struct("<4s22xHH")
_LOCAL_SIGNATURE = b"PK\x03\x04"
#: Compressed bytes read from the file, and inflated bytes made, at a time.
CHUNK_BYTES = 1 << 20
#: What ISA-L raises on corrupt deflate data (besides zlib's, which zipfile raises).
ERRORS: tuple[type[BaseException], ...] = () if _isal is None else (_isal.error,)


def open_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> BinaryIO:
    """A readable binary file over member ``info`` of ``zf`` (opened from its path)."""
    if _isal is None or info.compress_type != zipfile.ZIP_DEFLATED or info.flag_bits & 0x1:
        return zf.open(info)
    return io.BufferedReader(_Inflated(zf.filename, info))  # (large reads go straight through)


class _Inflated(io.RawIOBase):
    """The inflated data of one deflated member, read from its own file handle."""

    def __init__(self, path: str, info: zipfile.ZipInfo):
        self._name = info.filename
        self._fp = open(path, "rb")  # noqa: SIM115 - closed by close()
        try:
            self._fp.seek(info.header_offset)
            head = self._fp.read(_LOCAL.size)
            if len(head) != _LOCAL.size or head[:4] != _LOCAL_SIGNATURE:
                raise zipfile.BadZipFile(f"bad local file header for {self._name!r}")
            _sig, n_name, n_extra = _LOCAL.unpack(head)
            self._fp.seek(n_name + n_extra, io.SEEK_CUR)
        except BaseException:
            self._fp.close()
            raise
        self._left_in = info.compress_size
        self._left_out = info.file_size
        self._crc_declared = info.CRC
        self._crc = 0
        self._inflater = _isal.decompressobj(-15)

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        view = memoryview(buffer).cast("B")
        want = min(len(view), self._left_out)
        got = 0
        while got < want:
            data = self._inflater.unconsumed_tail
            if not data and self._left_in > 0:
                data = self._fp.read(min(CHUNK_BYTES, self._left_in))
                if not data:
                    raise EOFError(f"the zip ends inside {self._name!r}")
                self._left_in -= len(data)
            # (with no input left, what the inflater holds back comes out)
            out = self._inflater.decompress(data, min(want - got, CHUNK_BYTES))
            if not out:
                if not data or self._inflater.eof:
                    raise EOFError(f"the deflated data of {self._name!r} ends early")
                continue
            view[got : got + len(out)] = out
            got += len(out)
            self._crc = _isal.crc32(out, self._crc)
        self._left_out -= got
        if want and not self._left_out and self._crc != self._crc_declared:
            raise zipfile.BadZipFile(f"Bad CRC-32 for file {self._name!r}")
        return got

    def close(self) -> None:
        if not self.closed:
            self._fp.close()
        super().close()
