"""Recording a rig's calibration live, through its own device interfaces, into the folder
layout that :func:`.recorded.calibrate_from_folder` reads (docs/calibration.md).

:func:`record_rig_folder` drives an open rig (a rig file's hardware, or the emulated
rig) through:

1. the flat-field acquisition of :func:`.acquire.acquire_frames` (dark frames on the
   emulated rig only, open, closed, Gray code, measurement flat field), every frame
   averaged saved;
2. the chessboard poses (``target_vet_PP_NN``, ``target_meas_PP_NN``): every cell open,
   both cameras, :attr:`LiveSettings.board_frames` frames each. On a real rig a person
   places the board, prompted on standard error, and presses Enter; the emulated
   cameras are shown the board (:func:`.parts.chessboard_target`) and image it through
   their own geometry, vignetting, gain and noise;
3. the switching series (``switch_C_Ws_NN``): per window ``W`` and frame, a new frame
   opened on the LCoS, every cell closed on the subframe clock so that the device
   applies it at subframe ``C`` (the host sends the closure ``latency`` subframes
   ahead, as :func:`stages.capture.capture_frame` does) and the VET camera exposed for
   ``W`` from the frame's start; ``C`` in the name is the subframe the device
   acknowledges. A real VET camera's exposure is set per window
   (:meth:`~stages.devices.cameras.Camera.set_exposure_s`; where it cannot be, the
   series is skipped with a warning); the emulated one exposes
   :meth:`~stages.devices.emulated_cameras.EmulatedVETCamera.expose_window`, its flat
   field dimmed so the longest window is not saturated (a lab's neutral-density filter);
4. the frame clock (``meas_timestamps.csv``): the measurement camera on its subframe
   clock for :attr:`LiveSettings.clock_frames` subframes, every frame received's own
   ``Frame.index`` and ``Frame.timestamp_s``;
5. ``rig.toml``: the rig's settings (:data:`.folder_out.PARAMS`) and, when known, the
   chessboard's inner corners.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError, UsageError
from .acquire import AcquisitionSettings, RigExposer, acquire_frames
from .emulated_folder import (
    SWITCH_AFTER_S,
    SWITCH_BEFORE_S,
    SWITCH_FRAMES,
    SWITCH_STEP_S,
    SWITCH_SUBFRAME,
    TARGET_POSES,
    switch_windows,
)
from .folder_out import build_folder, frame_stem, save_frame, write_rig_toml
from .frame_clock import EMULATED_FRAMES, TIMESTAMPS_FILE, write_timestamps
from .frames import ProgressFn
from .parts import chessboard_target, find_corners

log = logging.getLogger("vet.calibrate")

#: ``ask(k, n)``: wait until the board is in pose ``k`` (1-based) of ``n``.
AskFn = Callable[[int, int], None]
#: Fraction of saturated pixels in a switching frame that draws a warning.
SATURATED_WARN = 0.01


@dataclass
class LiveSettings:
    """What :func:`record_rig_folder` records beyond the flat-field acquisition.

    Attributes
    ----------
    clock_frames : int
        Subframes the measurement camera runs on its clock for ``meas_timestamps.csv``
        (0: skipped, no jitter and drop rate).
    board_poses : int
        Chessboard poses (0: skipped, no measurement -> VET mapping).
    board_frames : int
        Frames averaged per pose and camera.
    switch_subframe : int
        Subframe ``C`` at which the switching series closes every cell (capped to the
        frame's last; negative: skipped).
    switch_frames : int
        Frames per window of the switching series.
    switch_before_s, switch_after_s, switch_step_s : float
        Its windows: ``switch_step_s`` apart from ``switch_before_s`` before ``C tau``
        to ``switch_after_s`` after (s).
    """

    clock_frames: int = EMULATED_FRAMES
    board_poses: int = 2
    board_frames: int = 4
    switch_subframe: int = SWITCH_SUBFRAME
    switch_frames: int = SWITCH_FRAMES
    switch_before_s: float = SWITCH_BEFORE_S
    switch_after_s: float = SWITCH_AFTER_S
    switch_step_s: float = SWITCH_STEP_S


def emulated_cameras(rig: Any) -> bool:
    """Whether both of ``rig``'s cameras are emulated ones that can be shown a scene."""
    return hasattr(rig.vet, "expose_window") and hasattr(rig.measurement, "show_scene")


def terminal_prompt(k: int, n: int) -> None:
    """Ask on standard error for pose ``k`` of ``n`` and wait for Enter on standard input
    (:class:`InputError` when it is closed instead)."""
    print(f"place the board for pose {k} of {n}, press Enter", file=sys.stderr, flush=True)
    if not sys.stdin.readline():
        raise InputError(f"standard input closed while waiting for board pose {k} of {n}")


def check_live(rig: Any, live: LiveSettings, ask: AskFn | None = None) -> None:
    """Refuse, before anything is recorded, chessboard poses on a real rig (``rig`` None:
    one not opened yet) that nobody can be asked for: no ``ask`` and standard input not
    a terminal.

    Raises
    ------
    UsageError
        (exit 2) naming ``--board-poses``, ``--frames`` and the terminal.
    """
    real = rig is None or not emulated_cameras(rig)
    if live.board_poses > 0 and ask is None and real:
        if not (sys.stdin is not None and sys.stdin.isatty()):
            raise UsageError(
                "the chessboard poses need someone at the rig pressing Enter, and standard "
                "input is not a terminal: run from a terminal, give --board-poses 0, or "
                "record the frames and calibrate with --frames FOLDER",
                option="--board-poses",
            )


def record_rig_folder(
    rig: Any,
    folder: str | Path,
    settings: AcquisitionSettings | None = None,
    live: LiveSettings | None = None,
    force: bool = False,
    progress: ProgressFn | None = None,
    ask: AskFn | None = None,
) -> dict[str, Any]:
    """Record an open ``rig``'s calibration frames into ``folder`` (steps in the module
    docstring; the folder written whole or not at all, :func:`.folder_out.build_folder`,
    a non-empty one only with ``force``).

    ``ask`` waits for each chessboard pose on a real rig (default
    :func:`terminal_prompt`, which needs standard input to be a terminal). Returns what
    was recorded: ``poses``, ``pattern`` (the board's inner corners when known),
    ``closures`` (the subframes of the switching series), ``clock_frames`` (frames in
    ``meas_timestamps.csv``).

    Raises
    ------
    UsageError
        Chessboard poses on a real rig without a terminal (:func:`check_live`).
    InputError
        ``folder`` is a file, or a non-empty folder without ``force``.
    DeviceError
        A camera or the LCoS failed.
    """
    live = live or LiveSettings()
    check_live(rig, live, ask)
    return build_folder(
        folder, force, lambda root: _record(rig, root, settings, live, progress, ask)
    )


def _record(
    rig: Any,
    root: Path,
    settings: AcquisitionSettings | None,
    live: LiveSettings,
    progress: ProgressFn | None,
    ask: AskFn | None,
) -> dict[str, Any]:
    black = rig.params.black_level_dn if getattr(rig, "is_emulated", False) else 0.0

    def save(name: str, img: np.ndarray) -> None:
        save_frame(root, name, img, black)

    def sink(tag: tuple[str, float], i: int, img: np.ndarray) -> None:
        save(frame_stem(tag, i), img)

    s = settings or AcquisitionSettings()
    frames = acquire_frames(rig, s, progress, sink)
    t_open = max(frames.open)
    ex = RigExposer(rig, sink)
    out: dict[str, Any] = {"poses": 0, "pattern": None, "closures": [], "clock_frames": 0}
    if live.board_poses > 0:
        out["poses"], out["pattern"] = record_board_poses(ex, live, t_open, ask)
    else:
        log.warning(
            "calibrate: --board-poses 0: no chessboard, so the measurement -> VET mapping is "
            "not found"
        )
    if live.switch_subframe >= 0:
        rate = float(np.percentile(frames.open[t_open], 99)) / t_open
        out["closures"] = record_switching(rig, save, live, rate, s.target_fill)
    if live.clock_frames > 0:
        out["clock_frames"] = record_clock(rig, root / TIMESTAMPS_FILE, live.clock_frames)
    comment = f"the settings of rig {rig.name} (its parts are what calibration finds)"
    write_rig_toml(root, rig.params, out["pattern"], comment)
    return out


# --- the chessboard -------------------------------------------------------------------


def _emulated_pose(k: int) -> tuple[int, tuple[float, float]]:
    """Board square (px) and shift (x, y) of the emulated rig's pose ``k``: those of
    :data:`.emulated_folder.TARGET_POSES`, then further shifts."""
    square, (x, y) = TARGET_POSES[k % len(TARGET_POSES)]
    turn = k // len(TARGET_POSES)
    return square, (x - 2.9 * turn, y + 1.7 * turn)


def record_board_poses(
    ex: RigExposer, live: LiveSettings, exposure_s: float, ask: AskFn | None
) -> tuple[int, tuple[int, int] | None]:
    """``live.board_poses`` chessboard poses, every cell open, ``live.board_frames``
    frames of each camera to ``ex``'s sink (``target_vet``, ``target_meas``); the VET
    camera (emulated) exposed ``exposure_s``. Returns the poses recorded and the board's
    inner corners (columns, rows) when known (the emulated board's)."""
    rig = ex.rig
    emulated = emulated_cameras(rig)
    ask = ask or terminal_prompt
    ex.show(None)
    pattern = None
    try:
        for p in range(live.board_poses):
            if emulated:
                level = 1.0 if rig.truth is None else float(np.median(rig.truth))
                square, shift = _emulated_pose(p)
                board, pattern = chessboard_target(rig.params.sensor_size, square, offset_px=shift)
                rig.vet.show_scene(board * np.float32(level))
                rig.measurement.show_scene(board * np.float32(level))
            else:
                ask(p + 1, live.board_poses)
                ex.mark_stale()  # a frame may have started before the board was placed
            vet = ex.vet(None, exposure_s, live.board_frames, tag=("target_vet", p))
            ex.meas(live.board_frames, tag=("target_meas", p))
            if pattern is not None and find_corners(vet, pattern) is None:
                log.warning("calibrate: emulated board pose %d not detectable at this size", p)
    finally:
        if emulated:
            rig.vet.show_scene(None)
            rig.measurement.show_scene(None)
    return live.board_poses, pattern


# --- the switching series -------------------------------------------------------------


def _close_all_at(rig: Any, c: int, frame_index: int) -> tuple[int, np.ndarray]:
    """Open a new frame on the LCoS and close every cell (a full mask) so that the device
    applies it at subframe ``c`` of the frame: the mask is sent ``latency`` subframes
    ahead on the subframe clock (the emulated controller's clock ticked; on hardware, the measurement
    camera's frames counted), and acknowledged. A host-triggered VET camera is started
    with the frame. Returns the subframe the device acknowledges (of the frame) and, per
    cell, the subframe of the frame at which the device reports having applied it (-1:
    open)."""
    lcos = rig.lcos
    lat = int(rig.params.latency_subframes)
    s0 = lcos.open_all(frame_index, wait=True)
    ahead = max(0, c - lat)
    if rig.is_emulated:
        rig.tick(max(0, s0 - rig.emulator.subframe))
        rig.tick(ahead)
    else:
        rig.vet.start_exposure()
        for _ in range(max(0, ahead - 1)):  # frame k arrives at the end of subframe k
            rig.measurement.grab()
    lcos.send_full_mask(np.ones(lcos.n_cells, bool), wait=True)
    raw = np.asarray(lcos.applied_subframe, np.int64)
    applied = np.where(raw >= 0, raw - int(lcos.frame_start_subframe), -1)
    return int(np.median(applied)), applied


def record_switching(
    rig: Any,
    save: Callable[[str, np.ndarray], None],
    live: LiveSettings,
    open_rate_dn_s: float,
    fill: float = 0.5,
) -> list[int]:
    """The switching series (module docstring, step 3), each frame to ``save(name, dn)``
    as ``switch_C_Ws_NN``. ``open_rate_dn_s``: the flat field's 99th-percentile rate all
    open (DN/s), from which the emulated flat field is dimmed so that the longest window
    reaches ``fill`` of full scale. Returns the subframes ``C`` acknowledged ([] when
    skipped: a VET camera whose exposure cannot be set from the host)."""
    p = rig.params
    c = min(live.switch_subframe, p.n_subframes - 1)
    wins = switch_windows(p, c, live.switch_before_s, live.switch_after_s, live.switch_step_s)
    if wins.size == 0:
        return []
    emulated = emulated_cameras(rig)
    if not emulated:
        first = rig.vet.set_exposure_s(float(wins[0]))
        if first is None:
            log.warning(
                "calibrate: the VET camera (%s) cannot have its exposure set from the host; the "
                "switching series (trigger offset, switching time) is skipped: record "
                "switch_C_Ws frames and calibrate with --frames",
                rig.vet.describe().get("backend", type(rig.vet).__name__),
            )
            return []
        restore = float(rig.vet.describe().get("exposure_us") or 0) * 1e-6
    else:
        dim = fill * p.max_dn / max(open_rate_dn_s * float(wins.max()), 1e-12)
        scene = np.asarray(rig.truth, np.float32) * np.float32(min(dim, 1.0))
        rig.vet.show_scene(scene)
        rig.measurement.show_scene(scene)
    closures: set[int] = set()
    saturated = 0.0
    index = 1
    try:
        for w in wins:
            window = float(w)
            if not emulated:
                got_s = rig.vet.set_exposure_s(window)
                if got_s is None:
                    log.warning("calibrate: the VET camera refused a %.6g s exposure", window)
                    continue
                window = got_s
            for n in range(live.switch_frames):
                got, applied = _close_all_at(rig, c, index)
                index += 1
                if emulated:
                    img = rig.vet.expose_window(applied, window)
                else:
                    img = rig.vet.grab().data
                img = RigExposer.mono(img)
                saturated = max(saturated, float(np.mean(img >= p.saturation_dn)))
                closures.add(got)
                save(f"switch_{got}_{window:.9g}s_{n:02d}", img)
        rig.lcos.open_all(index, wait=True)
    finally:
        if emulated:
            rig.vet.show_scene(None)
            rig.measurement.show_scene(None)
        elif restore > 0:
            rig.vet.set_exposure_s(restore)
    if closures != {c}:
        log.warning(
            "calibrate: the switching series' closures were applied at subframe(s) %s, not %d "
            "as sent (the windows were placed about %d)",
            sorted(closures),
            c,
            c,
        )
    if saturated > SATURATED_WARN:
        log.warning(
            "calibrate: %.0f%% of a switching frame is saturated; dim the flat field so that a "
            "%.4g s exposure is not",
            100 * saturated,
            float(wins.max()),
        )
    return sorted(closures)


# --- the frame clock ------------------------------------------------------------------


def record_clock(rig: Any, path: Path, subframes: int) -> int:
    """Run the measurement camera on its subframe clock for ``subframes`` subframes (an
    emulated one's :meth:`free_run`) and write every frame it delivers within them (ids
    from the first received to ``subframes - 1`` after it, at most ``subframes`` grabs) as
    ``frame_id,timestamp_s``
    (the camera's own ``Frame.index`` and ``Frame.timestamp_s``) to ``path``
    (:func:`.frame_clock.write_timestamps`). Returns the frames written."""
    cam = rig.measurement
    if hasattr(cam, "free_run"):
        cam.free_run(subframes)
    ids: list[int] = []
    stamps: list[float] = []
    first = None
    for _ in range(subframes):  # (a camera whose ids do not advance still ends)
        cam.start_exposure()
        f = cam.grab()
        first = f.index if first is None else first
        if f.index - first >= subframes:
            break
        ids.append(int(f.index))
        stamps.append(float(f.timestamp_s))
    write_timestamps(path, np.asarray(ids, np.int64), np.asarray(stamps, np.float64))
    log.info("calibrate: %d frames of %d subframes on the clock recorded", len(ids), subframes)
    return len(ids)
