"""Shared fixtures. Randomness is seeded everywhere so failures reproduce."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_HDR = ROOT.parent / "shared" / "data" / "hdr"
SHARED_SCENES = ["Desk", "CandleGlass", "GoldenGate", "Bonita", "Cannon"]
VET = [sys.executable, "-m", "vet_cli"]


@pytest.fixture
def shared_hdr() -> Path:
    """../shared/data/hdr, or skip (a fresh clone has no ../shared)."""
    if not SHARED_HDR.is_dir():
        pytest.skip("../shared/data/hdr is absent")
    return SHARED_HDR


def run_vet(*args: str, input: bytes | None = None, cwd: Path | None = None, timeout: float = 300):
    """Run the vet CLI in a subprocess; returns CompletedProcess with bytes output."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [*VET, *map(str, args)], input=input, capture_output=True, cwd=cwd, env=env, timeout=timeout
    )


@pytest.fixture
def small_scene():
    from stages.scenes import load_scene

    return load_scene("builtin:interior", (96, 80))


@pytest.fixture
def small_capture(small_scene):
    """A VET capture of the builtin interior at 96x80, still, seed 3."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.simulate import simulate

    rig = RigParams(sensor_size=(96, 80))
    return simulate(small_scene, parse_motion("none"), rig, seed=3, measure_bins=4)["vet"]


@pytest.fixture
def rng():
    # Fixed seed: tests must be deterministic.
    return np.random.default_rng(12345)
