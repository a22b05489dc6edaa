"""Trigger jitter and dropped frames from the measurement camera's frame ids and timestamps.

A lab records them while the measurement camera runs on the subframe clock (triggered
by it, or free-running at its period): each frame the host receives, its frame id (the
camera's frame counter, GenICam chunk ``ChunkFrameID`` or the driver's block id) and its
timestamp (``ChunkTimestamp`` or the driver's, converted to seconds), as a CSV file
``meas_timestamps.csv`` in the folder of recorded frames (:data:`TIMESTAMPS_FILE`)::

    frame_id,timestamp_s
    0,12.50
    1,12.51
    3,12.53
    ...

One header line naming the two columns first (further columns are ignored), then one
frame per line: ``frame_id`` a non-negative decimal integer (the counter unwrapped,
each id once), ``timestamp_s`` a finite decimal number of seconds (any epoch). Lines
that are empty or start with ``#`` are skipped.

:func:`fit_frame_clock` fits the clock ``t0 + id * period`` to the timestamps by least
squares, then again on the frames within five robust sigmas of it: the jitter is the
robust spread of the timestamps about that line (``1.4826 * MAD``), the drop rate the
fraction of ids missing between the first and the last id, and the fitted period is
checked against the rig's ``subframe_s``. :func:`emulated_timestamps` draws such a
recording from the emulated rig's physics (:func:`stages.optics.subframe_clock`).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..rig import RigParams

log = logging.getLogger("vet.calibrate")

#: The file of frame ids and timestamps in a folder of recorded frames.
TIMESTAMPS_FILE = "meas_timestamps.csv"
#: Largest timestamps file read, bytes (about 2.5 million frames).
MAX_TIMESTAMPS_BYTES = 64 * 2**20
#: Fewest frames a fit needs.
MIN_FRAMES = 20
#: Frames the emulated rig records: 0.2% drops is 40 +- 6 missing ids.
EMULATED_FRAMES = 20000
#: Largest drop rate taken for one (more ids missing than received: not the clock).
MAX_DROP_RATE = 0.5
#: Relative difference of the fitted period from ``subframe_s`` that draws a warning.
PERIOD_TOLERANCE = 1e-3

_INT = re.compile(r"^\s*\d{1,18}\s*$")
_FLOAT = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")


def read_timestamps(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Frame ids and timestamps of a ``meas_timestamps.csv`` (format in the module
    docstring): ``(ids, t)``, (N,) int64 and (N,) float64 seconds, sorted by id.

    Raises
    ------
    FormatError
        Unreadable, too large, a missing header, a malformed line (its number named), a
        repeated id.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_TIMESTAMPS_BYTES:
            raise FormatError(
                f"{p}: {size} bytes, over the limit of {MAX_TIMESTAMPS_BYTES} for a timestamps file"
            )
        text = p.read_bytes().decode("utf-8-sig")
    except OSError as exc:
        raise FormatError(f"{p}: cannot read the timestamps file ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise FormatError(f"{p}: not a text file (expected CSV frame_id,timestamp_s)") from None
    ids: list[int] = []
    ts: list[float] = []
    header = None
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        cols = s.split(",")
        if header is None:
            header = [c.strip().lower() for c in cols]
            if header[:2] != ["frame_id", "timestamp_s"]:
                raise FormatError(
                    f"{p}:{n}: header {s[:60]!r}; expected 'frame_id,timestamp_s' first"
                )
            continue
        if len(cols) < 2 or not _INT.match(cols[0]) or not _FLOAT.match(cols[1]):
            raise FormatError(
                f"{p}:{n}: {s[:60]!r} is not 'frame_id,timestamp_s' (a non-negative integer "
                "and seconds)"
            )
        t = float(cols[1])
        if not np.isfinite(t):
            raise FormatError(f"{p}:{n}: timestamp {cols[1].strip()[:30]!r} is not finite")
        ids.append(int(cols[0]))
        ts.append(t)
    if header is None:
        raise FormatError(f"{p}: empty; expected a header 'frame_id,timestamp_s' and frames")
    id_arr = np.asarray(ids, np.int64)
    t_arr = np.asarray(ts, np.float64)
    order = np.argsort(id_arr, kind="stable")
    id_arr, t_arr = id_arr[order], t_arr[order]
    rep = np.flatnonzero(np.diff(id_arr) == 0)
    if rep.size:
        raise FormatError(f"{p}: frame id {int(id_arr[rep[0]])} appears more than once")
    return id_arr, t_arr


def write_timestamps(path: str | Path, ids: np.ndarray, t: np.ndarray) -> None:
    """Write ``(ids, t)`` ((N,) integers, (N,) seconds) as :func:`read_timestamps` reads."""
    lines = ["frame_id,timestamp_s"]
    lines += [f"{int(i)},{float(s):.9f}" for i, s in zip(ids, t, strict=True)]
    Path(path).write_text("\n".join(lines) + "\n")


def fit_frame_clock(ids: np.ndarray, t: np.ndarray, subframe_s: float) -> dict | None:
    """The measurement camera's frame clock from frame ``ids`` ((N,) integers, unique)
    and their timestamps ``t`` ((N,) seconds).

    Returns ``trigger_jitter_s`` (``1.4826 * MAD`` of the timestamps about the fitted
    line ``t0 + id * period``, s), ``drop_rate`` (ids missing between the first and the
    last, over that range), ``period_s`` (fitted), ``period_rel_err`` (against
    ``subframe_s``), ``frames`` (N), ``missing``, ``outliers`` (frames beyond five
    robust sigmas, left out of the line's fit); None with fewer than :data:`MIN_FRAMES`
    frames or a span of one id.
    """
    ids = np.asarray(ids, np.int64)
    t = np.asarray(t, np.float64)
    if ids.size < MIN_FRAMES or ids[-1] == ids[0]:
        return None
    x = (ids - ids[0]).astype(np.float64)
    y = t - t[0]
    keep = np.ones(ids.size, bool)
    for _ in range(3):
        period, t0 = np.polyfit(x[keep], y[keep], 1)
        r = y - (t0 + period * x)
        mad = float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        sigma = 1.4826 * mad
        new = np.abs(r - np.median(r[keep])) <= max(5.0 * sigma, 1e-12)
        if np.array_equal(new, keep) or new.sum() < MIN_FRAMES:
            break
        keep = new
    span = int(ids[-1] - ids[0]) + 1
    missing = span - ids.size
    return {
        "trigger_jitter_s": float(sigma),
        "drop_rate": missing / span,
        "period_s": float(period),
        "period_rel_err": float(period / subframe_s - 1),
        "frames": int(ids.size),
        "missing": int(missing),
        "outliers": int(ids.size - keep.sum()),
    }


def clock_parts(ids: np.ndarray, t: np.ndarray, params: RigParams) -> tuple[dict, dict] | None:
    """``(parts, info)`` from a recording (:func:`fit_frame_clock`): the RigParams fields
    ``trigger_jitter_s`` and ``drop_rate``, and the fit's figures for the provenance;
    None (logged) when it cannot be fitted, the period is not positive, more than
    :data:`MAX_DROP_RATE` of the ids are missing or the jitter exceeds a subframe."""
    fit = fit_frame_clock(ids, t, params.subframe_s)
    if fit is None:
        log.warning(
            "calibrate: %s holds %d frames; the frame clock needs %d or more",
            TIMESTAMPS_FILE,
            len(ids),
            MIN_FRAMES,
        )
        return None
    if fit["period_s"] <= 0 or fit["drop_rate"] > MAX_DROP_RATE:
        log.warning(
            "calibrate: %s: the timestamps do not rise with the frame ids, or more than "
            "half the ids are missing; jitter and drop rate not set",
            TIMESTAMPS_FILE,
        )
        return None
    if abs(fit["period_rel_err"]) > PERIOD_TOLERANCE:
        log.warning(
            "calibrate: the measurement camera's frames come every %.6g ms, the rig's subframe "
            "is %.6g ms (is subframe_s right, or was the camera not on the subframe clock?)",
            fit["period_s"] * 1e3,
            params.subframe_s * 1e3,
        )
    if fit["trigger_jitter_s"] > params.subframe_s:
        log.warning(
            "calibrate: timestamp jitter %.3g ms exceeds a subframe; jitter and drop rate not set",
            fit["trigger_jitter_s"] * 1e3,
        )
        return None
    parts = {k: fit[k] for k in ("trigger_jitter_s", "drop_rate")}
    return parts, {k: v for k, v in fit.items() if k not in parts}


def emulated_timestamps(
    rig: RigParams, frames: int = EMULATED_FRAMES, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Frame ids and timestamps the emulated measurement camera gives over ``frames``
    subframes of its clock run without a break (:func:`stages.optics.free_running_clock`:
    the rig's trigger offset, jitter and drops), as its free run
    (:meth:`~stages.devices.cameras.EmulatedMeasurementCamera.free_run`) delivers them:
    ``(ids, t)``, (M,) int64 and (M,) float64 s, the dropped frames left out."""
    from ..optics import free_running_clock

    starts, dropped = free_running_clock(rig, frames, seed)
    ids = np.arange(frames, dtype=np.int64)
    return ids[~dropped], starts[~dropped]
