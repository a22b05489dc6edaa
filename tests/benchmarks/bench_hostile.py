"""Hostile inputs: what refusing a decompression bomb costs (time and peak memory).

Each line builds a crafted file and reads it with ``read_layered`` in a fresh
interpreter, measuring wall time and peak RSS (``resource.getrusage``) added by the read.
"""

from __future__ import annotations

import struct
import tempfile
from pathlib import Path

import numpy as np

from tests.hostile import measure_read, write_npz_bomb


def main() -> None:
    from stages.formats.hdr import HDRImage, write_hdr

    with tempfile.TemporaryDirectory() as tmp:
        bomb = Path(tmp) / "bomb.npz"
        inflates = write_npz_bomb(bomb)
        size = bomb.stat().st_size
        dt, added, peak, outcome = measure_read(bomb)
        print(
            f"npz bomb: {size / 1e6:.1f} MB inflating to {inflates / 2**30:.1f} GiB: "
            f"{outcome.split(':')[0]} in {dt * 1e3:.1f} ms, peak RSS +{added:.1f} MiB "
            f"({peak:.0f} MiB with the interpreter and imports)"
        )
        exr = Path(tmp) / "window.exr"
        write_hdr(exr, HDRImage(np.zeros((16, 16, 1), np.float32), ["Y"], {}))
        raw = bytearray(exr.read_bytes())
        at = raw.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
        raw[at : at + 16] = struct.pack("<4i", 0, 0, 8191, 8191)
        exr.write_bytes(bytes(raw))
        dt, added, peak, outcome = measure_read(exr)
        print(
            f"EXR declaring an 8192x8192 data window in {len(raw)} bytes: "
            f"{outcome.split(':')[0]} in {dt * 1e3:.1f} ms, peak RSS +{added:.1f} MiB"
        )


if __name__ == "__main__":
    main()
