"""The calibration acceptance point on the emulated rig (``python -m stages.calibrate``)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

from .emulated import calibrate_sim
from .geometry import example_homography


def selftest(
    size: tuple[int, int] = (320, 256),
    lcos_cells: tuple[int, int] = (256, 150),
    leakage: float = 0.003,
    dark_current_e_s: float = 15.0,
    seed: int = 1,
) -> dict[str, Any]:
    """The acceptance point: calibrate the emulated rig with a known misalignment.

    Returns
    -------
    dict
        The figures of :func:`compare_to_truth` plus the measured values and timing.
    """
    true_h = example_homography(lcos_cells, size)
    t0 = time.monotonic()
    cal = calibrate_sim(
        size,
        {"lcos_cells": lcos_cells, "leakage": leakage, "dark_current_e_s": dark_current_e_s},
        true_h,
        seed,
    )
    elapsed = time.monotonic() - t0
    figures: dict[str, Any] = {
        "size": f"{size[0]}x{size[1]}",
        "lcos": f"{lcos_cells[0]}x{lcos_cells[1]}",
        **cal.provenance["errors_vs_truth"],
        "leakage_median": cal.summary.get("leakage_median"),
        "dark_current_median_e_s": cal.summary.get("dark_current_median_e_s"),
        "gain_ratio_median": cal.summary.get("gain_ratio_median"),
        **cal.homography_fit,
        "elapsed_s": round(elapsed, 2),
    }
    return figures


def _main(argv: Sequence[str] | None = None) -> int:
    import argparse
    import json

    ap = argparse.ArgumentParser(
        prog="python -m stages.calibrate", description="Calibration acceptance on the emulated rig."
    )
    ap.add_argument(
        "--selftest", action="store_true", help="run the acceptance point and print its figures"
    )
    ap.add_argument(
        "--full", action="store_true", help="at the default 1280x1024 sensor / 1024x600 LCoS"
    )
    args = ap.parse_args(argv)
    if not args.selftest:
        ap.print_help()
        return 2
    logging.basicConfig(level=logging.WARNING, format="vet: %(message)s")
    kw = {"size": (1280, 1024), "lcos_cells": (1024, 600)} if args.full else {}
    print(json.dumps(selftest(**kw), indent=2))
    return 0
