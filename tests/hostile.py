"""Crafted hostile files for the tests and ``make bench``: files vet's writers refuse to
make, and decompression bombs.

:func:`write_unchecked` writes a vet file as :func:`stages.formats.layered.write_layered`
does, but without its check that every value is finite (a reader's test needs NaN in T,
in a measuring image, in a motion field). :func:`write_npz_bomb` writes a valid vet-looking ``.npz`` whose ``layer:I`` member
inflates to gigabytes of zeros from about a thousandth of that on disk. The deflate
stream is built from one compressed block repeated (each block ends with a full flush,
so blocks are independent and identical), and the CRC-32 of the zeros is combined
arithmetically, so building a 2 GiB bomb takes milliseconds and no memory.
"""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np

_BLOCK = 1 << 22  # zeros per repeated deflate block


def write_unchecked(path: str | Path, data) -> None:
    """Write the Layered ``data`` at ``path`` (EXR or npz by extension) as
    ``write_layered`` does, non-finite values and all."""
    from stages.formats.exr import write_exr
    from stages.formats.layered import write_npz

    path = Path(path)
    data.meta["channel_order"] = {k: list(v) for k, v in data.channels.items()}
    (write_exr if path.suffix.lower() == ".exr" else write_npz)(path, data)


def _gf2_times(mat: list[int], vec: int) -> int:
    out, i = 0, 0
    while vec:
        if vec & 1:
            out ^= mat[i]
        vec >>= 1
        i += 1
    return out


def _gf2_square(mat: list[int]) -> list[int]:
    return [_gf2_times(mat, mat[n]) for n in range(32)]


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """CRC-32 of ``A + B`` from ``crc32(A)``, ``crc32(B)`` and ``len(B)`` (zlib's method)."""
    if len2 <= 0:
        return crc1
    odd = [0xEDB88320] + [1 << n for n in range(31)]
    even = _gf2_square(odd)
    odd = _gf2_square(even)
    while True:
        even = _gf2_square(odd)
        if len2 & 1:
            crc1 = _gf2_times(even, crc1)
        len2 >>= 1
        if not len2:
            break
        odd = _gf2_square(even)
        if len2 & 1:
            crc1 = _gf2_times(odd, crc1)
        len2 >>= 1
        if not len2:
            break
    return crc1 ^ crc2


def _zeros_member(prefix: bytes, n_zero_blocks: int) -> tuple[bytes, int, int]:
    """``(raw deflate data, crc32, uncompressed size)`` of ``prefix`` + zeros."""
    co = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = co.compress(prefix) + co.flush(zlib.Z_FULL_FLUSH)
    block = co.compress(bytes(_BLOCK)) + co.flush(zlib.Z_FULL_FLUSH)
    again = co.compress(bytes(_BLOCK)) + co.flush(zlib.Z_FULL_FLUSH)
    assert block == again  # a full flush resets the window: blocks are identical
    tail = co.flush(zlib.Z_FINISH)
    data = head + block * n_zero_blocks + tail
    crc = zlib.crc32(prefix)
    block_crc = zlib.crc32(bytes(_BLOCK))
    # CRC of n blocks by doubling.
    run_crc, run_len, n = block_crc, _BLOCK, n_zero_blocks
    while n:
        if n & 1:
            crc = crc32_combine(crc, run_crc, run_len)
        run_crc = crc32_combine(run_crc, run_crc, run_len)
        run_len *= 2
        n >>= 1
    return data, crc, len(prefix) + n_zero_blocks * _BLOCK


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, array, allow_pickle=False)
    return buf.getvalue()


def _write_zip(path: Path, members: list[tuple[str, bytes, int, int, int]]) -> None:
    """Members ``(name, data, crc, uncompressed size, method)``; sizes under 4 GiB."""
    central = b""
    with open(path, "wb") as f:
        for name, data, crc, usize, method in members:
            offset = f.tell()
            raw = name.encode()
            fields = (20, 0, method, 0, 0x21, crc, len(data), usize, len(raw), 0)
            f.write(struct.pack("<IHHHHHIIIHH", 0x04034B50, *fields) + raw + data)
            central += (
                struct.pack("<IH", 0x02014B50, 20)
                + struct.pack("<HHHHHIIIHHHHHII", *fields[:-1], 0, 0, 0, 0, 0, offset)
                + raw
            )
        start = f.tell()
        n = len(members)
        f.write(central)
        f.write(struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, n, n, len(central), start, 0))


def write_npz_bomb(
    path: str | Path, height: int = 32768, width: int = 16384, meta: dict | None = None
) -> int:
    """Write a vet-looking npz whose ``layer:I`` (float32, ``(height, width, 1)``) is all
    zeros, deflated; returns the bytes it inflates to. ``height * width * 4`` must be a
    multiple of 4 MiB and under 4 GiB (the default: 2 GiB from about 2 MB on disk)."""
    path = Path(path)
    nbytes = height * width * 4
    assert nbytes % _BLOCK == 0 and nbytes < 2**32 - 256
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f4", "fortran_order": False, "shape": (height, width, 1)}
    )
    data, crc, usize = _zeros_member(header.getvalue(), nbytes // _BLOCK)
    meta_npy = _npy(np.array(json.dumps(meta if meta is not None else {"kind": "hdr"})))
    chan_npy = _npy(np.array(json.dumps({"I": ["Y"]})))
    _write_zip(
        path,
        [
            ("__meta__.npy", meta_npy, zlib.crc32(meta_npy), len(meta_npy), 0),
            ("__channels__.npy", chan_npy, zlib.crc32(chan_npy), len(chan_npy), 0),
            ("layer:I.npy", data, crc, usize, 8),
        ],
    )
    return usize


_MEASURE = """
import resource, sys, time
from stages.errors import VetError
from stages.formats.layered import read_layered
import OpenImageIO, cv2  # imported up front so their size is not counted
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.perf_counter()
try:
    read_layered(sys.argv[1])
    outcome = "read"
except VetError as exc:
    outcome = "refused: " + str(exc)
dt = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(f"{dt:.6f} {(peak - base) / 1024:.3f} {peak / 1024:.3f}")
print(outcome)
"""


def measure_read(path: str | Path, timeout_s: float = 120.0) -> tuple[float, float, float, str]:
    """Read ``path`` with :func:`read_layered` in a fresh interpreter.

    Returns ``(seconds, MiB of peak RSS added by the read, peak RSS MiB, outcome)``;
    outcome is ``"read"`` or ``"refused: <message>"``.
    """
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", _MEASURE, str(path)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=root,
        check=True,
    ).stdout.splitlines()
    dt, added, peak = (float(v) for v in out[0].split())
    return dt, added, peak, out[1]
