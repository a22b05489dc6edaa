"""The capture control loop: drive a rig through one VET frame and record it.

Per measuring subframe ``k`` the host

1. grabs the subframe from the measurement camera (gaps in the frame counter are
   dropped frames: the missing light is estimated by repeating the next frame, and
   the gap is logged),
2. signals the subframe's end to the controller's clock (a trigger wire on hardware;
   :meth:`~stages.devices.rigs.Rig.tick` on the emulated rig),
3. accumulates it and finds the LCoS cells whose brightest pixel crossed the threshold
   (:class:`~stages.physics.ClosureController`, through the calibration homography),
4. sends only those cells, delta-encoded in the smallest encoding, without waiting for
   the acknowledgement (the driver keeps a window of frames in flight).

After the frame it waits for every acknowledgement: the exposure time image T is built
from the subframes at which the **device** reports having applied each closure, never
from when the host asked. The VET camera's frame gives I.

A capture folder holds ``capture.exr`` (or ``.npz``), the raw measuring stream
``measure_raw.npy`` (K, H, W, C) int16 DN with ``measure_raw.json`` (frame indices,
timestamps), ``capture.log`` (what happened, in words) and ``capture.json`` (link and
timing statistics). On a device fault the loop stops, keeps the raw stream captured so
far and a log that says what happened, and raises :class:`~stages.errors.DeviceError`.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DeviceError, VetError
from .formats.capture import Capture, provenance_entry, write_capture
from .formats.io import atomic_output
from .optics import MeasureGeometry
from .physics import CellMap, ClosureController
from .simulate import add_subframe, measure_store

log = logging.getLogger(__name__)


class CaptureLog:
    """Human-readable log lines plus machine-readable statistics for a capture folder."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()
        self.lines: list[str] = []
        self.stats: dict[str, Any] = {}

    def info(self, msg: str, *args: Any) -> None:
        text = msg % args if args else msg
        self.lines.append(f"{time.monotonic() - self.t0:9.3f}s  {text}")
        log.debug(text)

    def write(self, folder: Path) -> None:
        with atomic_output(folder / "capture.log") as tmp:
            tmp.write_text("\n".join(self.lines) + "\n")
        with atomic_output(folder / "capture.json") as tmp:
            tmp.write_text(
                json.dumps(self.stats, indent=2, sort_keys=True, default=_jsonable) + "\n"
            )


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def capture_frame(
    rig: Any,
    folder: str | Path,
    measure_bins: int | None = None,
    raw_stream: bool = True,
    fmt: str = "exr",
    progress: Callable[[int, int], None] | None = None,
    provenance: list[dict[str, Any]] | None = None,
    cell_leakage: np.ndarray | None = None,
) -> Capture:
    """Capture one VET frame with ``rig`` into the capture folder ``folder``.

    Parameters
    ----------
    rig : stages.devices.rigs.Rig
        An open rig (emulated or hardware).
    folder : path
        Capture folder; created if missing (its parent must exist).
    measure_bins : int, optional
        Time bins of measuring images stored in the capture file; None (the default):
        every subframe (:func:`stages.simulate.measure_store`).
    raw_stream : bool
        Keep every measuring subframe in ``measure_raw.npy``.
    fmt : {"exr", "npz"}
        Format of the capture file.
    cell_leakage : ndarray of shape (H, W), optional
        The calibration's per-cell leakage (``Calibration.cell_leakage``), stored with
        the capture for its reconstructions (NaN, outside the LCoS, as the rig's leakage).

    Returns
    -------
    Capture
        What was written to ``folder/capture.<fmt>``.

    Raises
    ------
    DeviceError
        On a device or link fault; the folder then holds the raw stream so far and a
        log saying what happened.
    """
    folder = Path(folder)
    if not folder.parent.is_dir():
        raise VetError(f"{folder}: parent folder {folder.parent} does not exist")
    folder.mkdir(exist_ok=True)
    params = rig.params
    clog = CaptureLog()
    raw = None
    books = None
    stamps: list[float] = []  # camera timestamp of the frame used for each subframe
    raw_tmp = folder / ".measure_raw.npy.part"
    n_done = 0
    try:
        info = rig.lcos.info()
        clog.info(
            "LCoS: %s, %dx%d cells, protocol %s", info.firmware, *info.cells, info.protocol_version
        )
        if tuple(info.cells) != tuple(params.lcos_cells):
            raise DeviceError(
                f"LCoS reports {info.cells[0]}x{info.cells[1]} cells but the rig says "
                f"{params.lcos_cells[0]}x{params.lcos_cells[1]}"
            )
        w, h = params.sensor_size
        k_sub, tau = params.n_subframes, params.subframe_s
        cellmap = CellMap.for_rig(params, (h, w))
        hm, wm = params.measure_shape
        if params.ideal_geometry:
            ctrl = ClosureController(params, cellmap)
        else:
            # Each cell is thresholded on the measuring pixels that image it (measurement
            # -> VET -> LCoS), on frames flat-fielded for the camera's gain and vignetting.
            geom = MeasureGeometry(params)
            cm_m, starts, cells = geom.host_cells(cellmap)
            ctrl = ClosureController(params, cm_m, extras=(starts, cells), dn_scale=geom.flat)
        decided = np.full(cellmap.n_cells, -1, np.int32)  # subframe whose data closed the cell
        rig.measurement.open()
        s0 = rig.lcos.open_all(0, wait=True)
        if rig.is_emulated:
            rig.tick(max(0, s0 - rig.emulator.subframe))
            # From here the trigger drives the device clock in real time; the camera
            # delivers each subframe at its end on the same clock.
            t0 = rig.start_trigger(s0)
            if hasattr(rig.measurement, "start_at"):
                rig.measurement.start_at(t0)
        else:
            rig.vet.open()
            rig.vet.start_exposure()  # a host-triggered VET camera starts with the frame
        clog.info("frame 0 started at device subframe %d", s0)
        nch = len(rig.channels)
        edges, measure = measure_store(k_sub, measure_bins, (hm, wm, nch))
        bin_of = (
            np.searchsorted(edges, np.arange(k_sub), side="right") - 1
            if edges is not None
            else None
        )
        if raw_stream:
            raw = np.lib.format.open_memmap(
                raw_tmp, mode="w+", dtype=np.int16, shape=(k_sub, hm, wm, nch)
            )
        # Bins and the raw stream are bookkeeping, not control: a worker thread does them
        # (numpy releases the GIL) so the control path keeps up with the subframe clock.
        from concurrent.futures import ThreadPoolExecutor

        books = ThreadPoolExecutor(max_workers=1, thread_name_prefix="vet-capture-books")
        pending = []

        def record_subframe(kk: int, frame_data: np.ndarray) -> None:
            if measure is not None:
                add_subframe(measure, bin_of[kk], frame_data)
            if raw is not None:
                raw[kk] = frame_data  # integer DN in [-black level, 4095]: exact in int16

        dropped: list[int] = []
        step_ms: list[float] = []
        sent_cells = 0
        k = 0
        while k < k_sub:
            frame = rig.measurement.grab()
            data = frame.data
            if data.shape != (hm, wm, nch):
                raise DeviceError(
                    f"measurement camera delivered {data.shape[1]}x{data.shape[0]}x{data.shape[2]} "
                    f"frames; the rig expects {wm}x{hm}x{nch}"
                )
            missing = list(range(k, min(frame.index, k_sub)))
            if missing:
                dropped += missing
                clog.info(
                    "dropped measuring subframe(s) %s: light estimated from subframe %d",
                    missing,
                    frame.index,
                )
            for kk in [*missing, frame.index] if frame.index < k_sub else missing:
                t_start = time.perf_counter()
                rig.tick()
                new = ctrl.step(data, kk)
                if new.size:
                    decided[new] = kk
                    rig.lcos.close_cells(new)
                    sent_cells += int(new.size)
                step_ms.append((time.perf_counter() - t_start) * 1e3)
                pending.append(books.submit(record_subframe, kk, data))
                if len(pending) > 8:  # bounded backlog; also surfaces worker errors
                    pending.pop(0).result()
                stamps.append(frame.timestamp_s)
                n_done = kk + 1
                if progress:
                    progress(n_done, k_sub)
            k = max(k + 1, frame.index + 1)
        # The frame's tail: no more closures. Wait for every acknowledgement, then let
        # the device clock reach the frame end.
        for f in pending:
            f.result()
        books.shutdown()
        rig.lcos.flush()
        if rig.is_emulated:
            rig.stop_trigger()
            rig.tick(max(0, s0 + int(np.ceil(params.frame_s / tau)) - rig.emulator.subframe))
        clog.info("all %d closures acknowledged", sent_cells)
        t_cells = rig.lcos.exposure_time_s(tau, params.frame_s).astype(np.float64).ravel()
        # On the trigger clock: the measuring subframes (and the closures applied on
        # them) start trigger_offset_s after the VET exposure.
        off = params.trigger_offset_s
        t_cells = np.where(
            t_cells < params.frame_s, np.minimum(t_cells + off, params.frame_s), t_cells
        ).astype(np.float32)
        exposure_time = cellmap.to_pixels(np.append(t_cells, np.float32(params.frame_s)))
        applied = rig.lcos.applied_subframe
        # Every commanded closure must have come back with an applied subframe.
        unaccounted = int(((decided >= 0) & (applied < 0)).sum())
        if unaccounted:
            raise DeviceError(
                f"{unaccounted} commanded closures were never acknowledged as applied"
            )
        if rig.is_emulated:
            record = rig.emulator.snapshot()
            close_sub = np.where(
                record.applied_subframe >= 0,
                record.applied_subframe - record.frame_start_subframe,
                -1,
            )
            vet_frame = rig.vet.expose_frame(close_sub)
        else:
            vet_frame = rig.vet.grab()
        img = vet_frame.data
        if img.shape[:2] != (h, w):
            raise DeviceError(
                f"VET camera delivered {img.shape[1]}x{img.shape[0]} frames; the rig expects {w}x{h}"
            )
        late = _lateness(decided, applied, s0, params.latency_subframes)
        stats = rig.lcos.stats.as_dict()
        clog.stats.update(
            {
                "subframes": k_sub,
                "dropped_subframes": dropped,
                "closures": sent_cells,
                "closed_fraction": float((decided >= 0).mean()),
                "host_step_ms": _summary(step_ms),
                "late_closures": late,
                "link": stats,
                "frame_start_subframe": int(s0),
                "measure_timestamps_s": [round(float(t), 9) for t in stamps],
                "cameras": {"measurement": rig.measurement.describe(), "vet": rig.vet.describe()},
            }
        )
        clog.info("host step per subframe: median %.2f ms, p99 %.2f ms", *_pct(step_ms, [50, 99]))
        clog.info(
            "late closures: %d of %d (max %d subframes late)",
            late["count"],
            sent_cells,
            late["max"],
        )
        meta: dict[str, Any] = {
            "method": "vet",
            "integration_s": params.frame_s,
            "leakage_applies": True,
            "rig_name": rig.name,
            "capture_stats": clog.stats,
            **rig.meta,
        }
        if rig.scale:
            meta["radiance_scale"] = float(rig.scale)
        if measure is not None:
            meta["measure_subframes"] = np.diff(edges).tolist()
        if dropped:
            # Their light was estimated from the next frame (capture_stats says so).
            meta["measure_dropped"] = sorted(dropped)
        meta["provenance"] = (provenance or []) + [provenance_entry("capture", [rig.name])]
        cap = Capture(
            I=img.astype(np.float32),
            T=exposure_time,
            channels=list(rig.channels),
            rig=params,
            meta=meta,
            measure=measure,
            measure_times=None
            if edges is None
            else np.stack([edges[:-1] * tau, edges[1:] * tau], axis=1) + off,
            truth=rig.truth,
            truth_motion=rig.truth_motion,
            cell_leakage=None
            if cell_leakage is None
            else np.nan_to_num(cell_leakage, nan=params.leakage).astype(np.float32),
        )
        write_capture(folder / f"capture.{fmt}", cap)
        clog.info("wrote %s", folder / f"capture.{fmt}")
        return cap
    except DeviceError as exc:
        clog.info("FAULT after %d of %d measuring subframes: %s", n_done, params.n_subframes, exc)
        clog.stats.update({"error": str(exc), "subframes_captured": n_done})
        try:
            clog.stats["link"] = rig.lcos.stats.as_dict()
        except Exception:  # noqa: BLE001
            pass
        raise DeviceError(
            f"{exc} (after {n_done} of {params.n_subframes} subframes; "
            f"{folder} keeps what was captured and capture.log)"
        ) from None
    finally:
        if books is not None:
            books.shutdown(wait=True)  # writes in flight land before the stream closes
        if raw is not None:
            raw.flush()
            del raw
            raw_tmp.replace(folder / "measure_raw.npy")
            with atomic_output(folder / "measure_raw.json") as tmp:
                tmp.write_text(
                    json.dumps(
                        {
                            "subframes_valid": n_done,
                            "timestamps_s": [round(float(t), 9) for t in stamps],
                            "subframe_s": params.subframe_s,
                            "dtype": "int16 DN, black-level subtracted",
                        }
                    )
                    + "\n"
                )
        clog.write(folder)


def _lateness(decided: np.ndarray, applied: np.ndarray, s0: int, latency: int) -> dict[str, Any]:
    """How many subframes after the ideal moment (decision + 1 + latency) closures applied."""
    m = decided >= 0
    if not m.any():
        return {"count": 0, "max": 0, "mean": 0.0, "histogram": {}}
    delay = (applied[m] - s0) - (decided[m] + 1 + latency)
    values, counts = np.unique(delay, return_counts=True)
    return {
        "count": int((delay > 0).sum()),
        "max": int(delay.max()),
        "mean": float(delay.mean()),
        "histogram": {str(int(v)): int(c) for v, c in zip(values, counts, strict=True)},
    }


def _pct(values: list[float], q: list[float]) -> list[float]:
    return [float(np.percentile(values, p)) for p in q] if values else [0.0] * len(q)


def _summary(values: list[float]) -> dict[str, float]:
    med, p99 = _pct(values, [50, 99])
    return {"median": med, "p99": p99, "max": float(max(values)) if values else 0.0}
