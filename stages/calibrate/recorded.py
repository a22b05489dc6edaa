"""Calibration from recorded frames: a folder of images or camera raws (docs/calibration.md)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..rig import RigParams
from .calfile import Calibration
from .frames import CalibrationFrames, ProgressFn, calibrate_frames, software_version
from .gray_code import gray_bit_counts

log = logging.getLogger("vet.calibrate")

#: File extensions read by :func:`calibrate_from_folder`: OpenCV images and camera raws.
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".pgm")
RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw")


_NUM = r"(?P<t>\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)"
_TIMED = re.compile(rf"^(?P<kind>dark|open|closed|meas_flat|meas_dark)_{_NUM}s_(?P<n>\d+)$")
_GRAY = re.compile(r"^gray_(?P<k>\d+)(?:_(?P<n>\d+))?$")
_TARGET = re.compile(r"^target_(?P<cam>vet|meas)_(?P<p>\d+)(?:_(?P<n>\d+))?$")
_SWITCH = re.compile(rf"^switch_(?P<c>\d+)_{_NUM}s_(?P<n>\d+)$")
#: Name patterns (file stems) of the folder layout of :func:`calibrate_from_folder`.
LAYOUT = (_TIMED, _GRAY, _TARGET, _SWITCH)


def read_frame(path: str | Path) -> np.ndarray:
    """One recorded frame as ``ndarray of shape (H, W)`` float32 DN, unprocessed.

    PNG/TIFF/PGM through ``cv2.imread(IMREAD_UNCHANGED)`` (colour averaged to one
    channel); camera raws through rawpy's ``raw_image_visible`` (the mosaic as read
    out: no demosaicing, no black-level subtraction, no white balance).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in RAW_SUFFIXES:
        import rawpy

        try:
            with rawpy.imread(str(p)) as raw:
                img = np.array(raw.raw_image_visible, dtype=np.float32)
        except (rawpy.LibRawError, OSError) as exc:
            raise FormatError(f"{p}: not a readable raw file ({exc})") from None
    else:
        import cv2

        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise FormatError(f"{p}: not a readable image")
        img = np.asarray(img, dtype=np.float32)
        if img.ndim == 3:
            img = img[:, :, :3].mean(axis=2) if img.shape[2] >= 3 else img[:, :, 0]
    if img.ndim != 2 or min(img.shape) < 1:
        raise FormatError(f"{p}: frame has no pixels")
    return img


def calibrate_from_folder(
    folder: str | Path, params: RigParams | None = None, progress: ProgressFn | None = None
) -> Calibration:
    """Calibrate from recorded frames (layout in docs/calibration.md).

    File names (any of .png .tif .tiff .pgm, or camera raws .dng .nef .cr2 ...)::

        dark_<t>s_<NN>        VET camera, lens capped, exposure t seconds (two t or more)
        open_<t>s_<NN>        VET camera, flat field, LCoS all open
        closed_<t>s_<NN>      VET camera, flat field, LCoS all closed
        gray_<KK>[_<NN>]      VET camera, flat field, LCoS showing Gray pattern KK of
                              gray_code_patterns() (even KK pattern, odd KK its inverse)
        meas_flat_<t>s_<NN>   measurement camera, same flat field
        meas_dark_<t>s_<NN>   measurement camera, lens capped, same t (optional)
        target_vet_<PP>[_<NN>]   VET camera, all cells open, a chessboard in pose PP
        target_meas_<PP>[_<NN>]  measurement camera, the same chessboard pose PP
        switch_<C>_<W>s_<NN>  VET camera, flat field, every cell applied closed at
                              subframe C (as the LCoS acknowledges it), exposure window
                              W seconds from the trigger; W stepped across the closure
        meas_timestamps.csv   measurement camera on the subframe clock: frame_id,
                              timestamp_s per frame received (:mod:`.frame_clock`)

    e.g. ``dark_0.5s_00.tif``, ``gray_07.png``, ``target_vet_00_03.png``,
    ``switch_20_0.1511s_00.png``. An optional ``rig.toml`` in the folder with a
    ``[params]`` table (as in a rig file) gives the LCoS grid, the sensor's gain and the
    subframe length; ``params`` overrides it. Its optional ``[calibration]`` table's
    ``chessboard = [columns, rows]`` gives the target's inner corners (found by a small
    search without it).

    Found from them: the flat-field calibration (:func:`.frames.calibrate_frames`:
    homography, bias and dark current, the per-pixel leakage map from the open and
    closed frames, the gain ratio) and the parts of a real rig into ``Calibration.parts``
    (:mod:`.recorded_parts`): ``measure_homography``, ``measure_k1``, ``measure_k2``
    from the chessboard poses, ``trigger_offset_s`` and ``switch_s`` from the switching
    series, ``relay_blur_px`` from the Gray code, ``measure_vignetting`` and
    ``measure_gain`` (with the configured ``measure_fraction``) from the measurement
    flat field (:mod:`.meas_flat`), ``trigger_jitter_s`` and ``drop_rate`` from
    ``meas_timestamps.csv`` (:mod:`.frame_clock`). Missing parts are skipped with a
    warning (``provenance["skipped"]``); a pose whose chessboard is not found in both
    cameras is left out with a warning.

    Raises
    ------
    InputError
        Not a folder, no usable frame, frames of different sizes, or an incomplete set
        of Gray-code patterns with nothing else usable; a malformed
        ``meas_timestamps.csv`` (:class:`~stages.errors.FormatError`).
    """
    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{root}: no such folder of calibration frames")
    table = _folder_toml(root)
    if params is None:
        params = _folder_params(root, table)
    pattern = _chessboard(table, root)
    from .frame_clock import TIMESTAMPS_FILE, read_timestamps

    stamps = root / TIMESTAMPS_FILE
    clock = read_timestamps(stamps) if stamps.is_file() else None  # a bad file fails first
    timed: dict[str, dict[float, list[Path]]] = {}
    gray: dict[int, list[Path]] = {}
    targets: dict[str, dict[str, list[Path]]] = {}
    switch: dict[int, dict[float, list[Path]]] = {}
    for p in sorted(root.iterdir()):
        if not p.is_file() or p.suffix.lower() not in IMAGE_SUFFIXES + RAW_SUFFIXES:
            continue
        m = _TIMED.match(p.stem)
        if m:
            timed.setdefault(m["kind"], {}).setdefault(float(m["t"]), []).append(p)
            continue
        m = _GRAY.match(p.stem)
        if m:
            gray.setdefault(int(m["k"]), []).append(p)
            continue
        m = _TARGET.match(p.stem)
        if m:
            targets.setdefault(f"pose {m['p']}", {}).setdefault(m["cam"], []).append(p)
            continue
        m = _SWITCH.match(p.stem)
        if m:
            switch.setdefault(int(m["c"]), {}).setdefault(float(m["t"]), []).append(p)
            continue
        log.debug("calibrate: ignoring %s (name does not follow the layout)", p.name)
    if not timed and not gray:
        raise InputError(
            f"{root}: no calibration frames (expected names like dark_0.5s_00.tif, open_0.01s_00.png, "
            "gray_00.png; see docs/calibration.md)"
        )

    n_files = (
        sum(len(v) for g in timed.values() for v in g.values())
        + sum(len(v) for v in gray.values())
        + sum(len(v) for g in targets.values() for v in g.values())
        + sum(len(v) for g in switch.values() for v in g.values())
    )
    done = 0
    shape: list[tuple[int, int]] = []
    meas_shape: list[tuple[int, int]] = []

    def mean_of(
        paths: list[Path], shapes: list[tuple[int, int]] = shape, halves: list | None = None
    ) -> np.ndarray:
        """The mean of ``paths``' frames; with ``halves`` (a list), the means of the even-
        and odd-numbered ones appended to it (two or more frames; of an odd number, the
        last left out of the halves, which must be equal)."""
        nonlocal done
        acc = None
        part: list = [None, None]
        for i, p in enumerate(paths):
            img = read_frame(p)
            if not shapes:
                shapes.append(img.shape)
                from ..formats.io import check_size

                check_size(img.size * 4 * 32, str(p))  # the maps we will hold at this size
            elif img.shape != shapes[0]:
                raise InputError(
                    f"{p}: frame is {img.shape[1]}x{img.shape[0]}, the others are "
                    f"{shapes[0][1]}x{shapes[0][0]}"
                )
            acc = img.astype(np.float64) if acc is None else acc + img
            if halves is not None and i < len(paths) // 2 * 2:
                k = i % 2
                part[k] = img.astype(np.float64) if part[k] is None else part[k] + img
            done += 1
            if progress is not None:
                progress(done, n_files)
        if halves is not None and len(paths) >= 2:
            half = len(paths) // 2
            halves.append((part[0] / half, part[1] / half))
        return (acc / len(paths)).astype(np.float32)

    frames = CalibrationFrames()
    for kind in ("dark", "open", "closed", "meas_flat", "meas_dark"):
        for t, paths in sorted(timed.get(kind, {}).items()):
            if t <= 0:
                log.warning("calibrate: ignoring %s frames with exposure %g s", kind, t)
                continue
            cam = meas_shape if kind.startswith("meas") else shape
            longest = kind in ("open", "closed") and t == max(timed[kind])
            split: list | None = [] if longest else None
            getattr(frames, kind)[t] = mean_of(paths, cam, split)
            frames.counts[f"{kind}_{t:g}s"] = len(paths)
            if split:
                frames.halves[kind] = split[0]
    if gray:
        nx, ny = gray_bit_counts(params.lcos_cells)
        needed = 2 * (nx + ny)
        missing = [k for k in range(needed) if k not in gray]
        if missing:
            log.warning(
                "calibrate: Gray-code set for %dx%d cells needs gray_00 .. gray_%02d; missing %s",
                params.lcos_cells[0],
                params.lcos_cells[1],
                needed - 1,
                ", ".join(f"{k:02d}" for k in missing[:8]) + (" ..." if len(missing) > 8 else ""),
            )
        else:
            frames.gray_diffs = [
                mean_of(gray[k]) - mean_of(gray[k + 1]) for k in range(0, needed, 2)
            ]
            frames.counts["gray"] = min(len(v) for v in gray.values())
    if frames.shape() is None or not shape:
        raise InputError(f"{root}: no usable calibration frames (see the warnings above)")
    if params.sensor_size != (shape[0][1], shape[0][0]):
        log.info(
            "calibrate: frames are %dx%d; using that as the sensor size", shape[0][1], shape[0][0]
        )
        params = params.replace(sensor_size=(shape[0][1], shape[0][0]), homography=[])
    prov = {
        "source": f"folder:{root}",
        "frames_averaged": frames.counts,
        "software": software_version(),
    }
    cal = calibrate_frames(frames, params, prov)
    poses = {}
    for name, cams in sorted(targets.items()):
        if "vet" not in cams or "meas" not in cams:
            log.warning(
                "calibrate: target %s has frames of the %s camera only; pose left out",
                name,
                "VET" if "vet" in cams else "measurement",
            )
            continue
        poses[name] = (mean_of(cams["vet"]), mean_of(cams["meas"], meas_shape))
        cal.provenance["frames_averaged"][f"target_{name}"] = len(cams["vet"])
    switch_means = {
        c: {w: mean_of(paths) for w, paths in by_w.items()} for c, by_w in switch.items()
    }
    from .recorded_parts import fit_folder_parts

    if clock is not None:
        cal.provenance["frames_averaged"]["meas_timestamps"] = len(clock[0])
    fit_folder_parts(cal, params, poses, switch_means, pattern, frames.gray_diffs, frames, clock)
    return cal


def _folder_params(root: Path, data: dict | None = None) -> RigParams:
    """RigParams from the folder's ``rig.toml`` ``[params]`` (defaults without it; ``data``:
    the file already parsed); InputError if bad."""
    if data is None:
        data = _folder_toml(root)
    if not data:
        return RigParams()
    from ..formats.schema import check_rig_params

    return RigParams.from_dict(check_rig_params(data, str(root / "rig.toml")))


def _chessboard(data: dict, root: Path) -> tuple[int, int] | None:
    """``[calibration] chessboard = [columns, rows]`` of the folder's ``rig.toml``."""
    table = data.get("calibration", {})
    if not isinstance(table, dict):
        raise InputError(f"{root / 'rig.toml'}: [calibration] must be a table")
    board = table.get("chessboard")
    if board is None:
        return None
    ok = (
        isinstance(board, list)
        and len(board) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and 3 <= v <= 1000 for v in board)
    )
    if not ok:
        raise InputError(
            f"{root / 'rig.toml'}: [calibration] chessboard: {board!r}; expected [columns, rows] "
            "of inner corners, integers from 3 to 1000"
        )
    return int(board[0]), int(board[1])


def _folder_toml(root: Path) -> dict:
    """The folder's parsed ``rig.toml`` ({} without it); InputError if it is not TOML."""
    toml = root / "rig.toml"
    if not toml.is_file():
        return {}
    from ..formats.limits import parse_toml

    return parse_toml(toml.read_bytes(), str(toml))
