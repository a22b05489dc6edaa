"""``python -m stages.devices.lcos_emulator``: serve one host session on a new pty."""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys

from ...errors import InputError
from .config import EmulatorConfig
from .hostile import HOSTILE_BEHAVIOURS
from .process import serve

__all__ = ["main"]


def _parse_cells(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"cells must look like 1024x600, got {text!r}") from None
    return w, h


def main(argv: list[str] | None = None) -> int:
    """``python -m stages.devices.lcos_emulator``: serve one host session on a new pty.

    Prints the pty path on standard output, then runs with a free-running clock until
    the host closes the port; the final record goes to ``--record`` if given.
    """
    ap = argparse.ArgumentParser(
        prog="python -m stages.devices.lcos_emulator", description=main.__doc__
    )
    ap.add_argument(
        "--cells", type=_parse_cells, default=(1024, 600), help="grid WxH (default 1024x600)"
    )
    ap.add_argument(
        "--subframe-s", type=float, default=0.00758, help="free-running subframe length, s"
    )
    ap.add_argument("--latency", type=int, default=1, help="latency, subframes")
    ap.add_argument("--leakage", type=float, default=0.002)
    ap.add_argument(
        "--link-bps", type=float, default=None, help="link rate, bit/s (default unthrottled)"
    )
    ap.add_argument("--link-fault-rate", type=float, default=0.0)
    ap.add_argument("--disconnect-at-subframe", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--hostile",
        choices=sorted(HOSTILE_BEHAVIOURS),
        default=None,
        help="misbehave on purpose (docs/lcos-protocol.md §9)",
    )
    ap.add_argument(
        "--hostile-after", type=int, default=0, help="host frames answered honestly first"
    )
    ap.add_argument("--record", default=None, help="write the final record to this .npz")
    ap.add_argument("--connect-timeout-s", type=float, default=60.0)
    args = ap.parse_args(argv)
    try:
        config = EmulatorConfig(
            cells=args.cells,
            subframe_s=args.subframe_s,
            latency_subframes=args.latency,
            leakage=args.leakage,
            link_bps=args.link_bps,
            link_fault_rate=args.link_fault_rate,
            disconnect_at_subframe=args.disconnect_at_subframe,
            seed=args.seed,
            connect_timeout_s=args.connect_timeout_s,
            hostile=args.hostile,
            hostile_after=args.hostile_after,
        )
    except InputError as exc:
        print(f"lcos_emulator: error: {exc}", file=sys.stderr)
        return 2

    def announce(path: str) -> None:
        print(path, flush=True)

    record = serve(config, multiprocessing.Value("q", 0, lock=False), None, args.record, announce)
    print(
        f"lcos_emulator: {record.exit_reason}; counters {json.dumps(record.counters)}",
        file=sys.stderr,
    )
    return 0
