"""`make bench`: run every benchmark module (tests/benchmarks/bench_*.py) and print figures.

Usage: python -m tests.benchmarks.run [NAME ...]   (NAME: a bench_NAME.py module here:
batch, capture, deblur, foundation, fusion, hostile, layers, ...)

Each module has a ``main()`` that prints its own figures to stdout. Benchmarks report
numbers; they never fail on a time (tests assert behaviour, not wall-clock times).
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> int:
    here = Path(__file__).parent
    names = sorted(
        m.name[len("bench_") :]
        for m in pkgutil.iter_modules([str(here)])
        if m.name.startswith("bench_")
    )
    wanted = argv or names
    unknown = [n for n in wanted if n not in names]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; available: {names}", file=sys.stderr)
        return 2
    failed = []
    for name in wanted:
        print(f"\n=== bench {name} ===", flush=True)
        t0 = time.perf_counter()
        try:
            importlib.import_module(f"tests.benchmarks.bench_{name}").main()
        except Exception as exc:  # report and go on with the others
            failed.append(name)
            print(f"bench {name} FAILED: {type(exc).__name__}: {exc}", flush=True)
        print(f"=== bench {name}: {time.perf_counter() - t0:.1f} s ===", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
