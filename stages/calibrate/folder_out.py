"""Writing a folder of calibration frames in the layout that
:func:`.recorded.calibrate_from_folder` reads (docs/calibration.md), whole or not at all.

:func:`build_folder` records into a temporary folder beside the target and moves the
files in when the recording is done; :func:`save_frame` writes one frame as a 16-bit PNG
of the camera's codes; :func:`frame_stem` names the frames an acquisition averages;
:func:`write_rig_toml` writes the ``rig.toml`` the folder's reader takes its settings from.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from ..errors import InputError
from ..rig import RigParams
from .frame_clock import TIMESTAMPS_FILE
from .recorded import LAYOUT

T = TypeVar("T")

#: rig.toml [params] written: what a reader needs that is not measured.
PARAMS = (
    "sensor_size",
    "lcos_cells",
    "frame_s",
    "subframe_s",
    "full_well_e",
    "read_noise_e",
    "adc_bits",
    "black_level_dn",
    "latency_subframes",
)


def build_folder(folder: str | Path, force: bool, record: Callable[[Path], T]) -> T:
    """Run ``record(tmp)`` on a new temporary folder beside ``folder`` and move what it
    wrote into ``folder``; returns what ``record`` returns. Nothing is moved when it
    raises, and the temporary folder is removed either way. An existing ``folder`` that
    holds anything is refused unless ``force``; then the files of the layout (and
    ``rig.toml``, ``meas_timestamps.csv``) already there are replaced, others kept.

    Raises
    ------
    InputError
        ``folder`` is a file, or a non-empty folder without ``force``.
    """
    target = Path(folder)
    if target.exists() and not target.is_dir():
        raise InputError(f"{target}: is a file, not a folder")
    if target.is_dir() and any(target.iterdir()) and not force:
        raise InputError(
            f"{target}: folder is not empty; give --force to replace its calibration frames, "
            "or choose another folder"
        )
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        out = record(tmp)
        _move_into(tmp, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _move_into(tmp: Path, target: Path) -> None:
    """Move the recorded files of ``tmp`` into ``target`` (replacing layout files)."""
    if not target.exists():
        os.replace(tmp, target)
        return
    for p in target.iterdir():
        named = p.name in ("rig.toml", TIMESTAMPS_FILE)
        if p.is_file() and (named or any(r.match(p.stem) for r in LAYOUT)):
            p.unlink()
    for p in tmp.iterdir():
        os.replace(p, target / p.name)


def save_frame(root: Path, name: str, dn: np.ndarray, black_level_dn: float = 0.0) -> None:
    """Write ``root/name.png``: a (H, W) frame in DN with ``black_level_dn`` added back
    (an emulated camera's frames are black-subtracted, a raw camera's pedestal is what
    the dark frames' bias measures), rounded and clipped to 16-bit codes."""
    import cv2

    img = np.clip(np.rint(np.asarray(dn, np.float64) + black_level_dn), 0, 65535)
    if not cv2.imwrite(str(root / f"{name}.png"), img.astype(np.uint16)):
        raise InputError(f"{root / name}.png: cannot write the frame")


def frame_stem(tag: tuple[str, float], index: int) -> str:
    """The file stem of frame ``index`` of an averaged exposure tagged as
    :data:`.acquire.FrameSink` does: ``gray_KK_NN`` for ``("gray", k)``,
    ``KIND_PP_NN`` for a target pose ``("target_vet" | "target_meas", p)``, else
    ``KIND_<t>s_NN`` for ``(kind, exposure_s)``."""
    kind, key = tag
    if kind in ("gray", "target_vet", "target_meas"):
        return f"{kind}_{int(key):02d}_{index:02d}"
    return f"{kind}_{key:.9g}s_{index:02d}"


def write_rig_toml(
    root: Path, rig: RigParams, pattern: tuple[int, int] | None, comment: str
) -> None:
    """``root/rig.toml``: the :data:`PARAMS` of ``rig`` under ``[params]`` and, when
    known, the chessboard's inner corners ``pattern`` (columns, rows) under
    ``[calibration]``; ``comment`` as its first line."""
    d = rig.to_dict()
    lines = [f"# {comment}", "[params]"]
    for key in PARAMS:
        v = d[key]
        lines.append(f"{key} = {list(v) if isinstance(v, (list, tuple)) else repr(v)}")
    if pattern is not None:
        lines += ["", "[calibration]", f"chessboard = [{pattern[0]}, {pattern[1]}]"]
    (root / "rig.toml").write_text("\n".join(lines) + "\n")
