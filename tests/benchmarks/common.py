"""Helpers for benchmark scripts: timing subprocesses, the output folder, tables."""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "bench_out"
SHARED_HDR = ROOT.parent / "shared" / "data" / "hdr"
BIN = Path(sys.executable).parent


def out_dir() -> Path:
    OUT.mkdir(exist_ok=True)
    return OUT


def vet_cmd(*args: str) -> list[str]:
    exe = BIN / "vet"
    return [str(exe) if exe.exists() else "vet", *map(str, args)]


def time_cmd(cmd: list[str], repeat: int = 3) -> tuple[float, list[float]]:
    """Median wall time in seconds of running ``cmd`` ``repeat`` times (checked)."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run(
            cmd,
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=dict(os.environ),
        )
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def table(rows: list[dict], cols: list[str]) -> str:
    """A Markdown table of ``rows`` (dicts) with ``cols``."""

    def fmt(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)
