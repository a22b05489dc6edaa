"""Frame acquisition from a rig (emulated or real) for a calibration.

The closed frame gets a longer exposure than the open one so both are well exposed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .calfile import Calibration
from .frames import CalibrationFrames, ProgressFn, calibrate_frames, software_version
from .gray_code import gray_code_patterns

log = logging.getLogger("vet.calibrate")

#: ``sink(tag, index, frame)``: each frame an acquisition averages, as the camera gave it
#: ((H, W) float32 DN); ``tag`` is ``(kind, exposure_s)`` for ``dark``, ``open``,
#: ``closed`` and ``meas_flat`` frames, ``("gray", k)`` for Gray pattern ``k``.
FrameSink = Callable[[tuple[str, float], int, np.ndarray], None]


@dataclass
class AcquisitionSettings:
    """How :func:`calibrate_rig` exposes (emulated rig; a real camera keeps its own exposure).

    Attributes
    ----------
    frames_per_exposure : int
        Frames averaged for each dark, open, closed and measurement exposure.
    gray_frames : int
        Frames averaged per Gray-code pattern.
    dark_exposures_s : tuple of float
        Dark-frame exposure times, seconds (two or more).
    target_fill : float
        Flat-field exposures aim the 99th-percentile pixel at this fraction of full scale.
    max_exposure_s : float
        Longest exposure (the all-closed frame asks for long ones), seconds.
    """

    frames_per_exposure: int = 4
    gray_frames: int = 1
    dark_exposures_s: tuple[float, ...] = (0.01, 2.0)
    target_fill: float = 0.5
    max_exposure_s: float = 10.0


class RigExposer:
    """One exposure of either camera on any rig, averaged, as (H, W) float32 DN."""

    def __init__(self, rig: Any, sink: FrameSink | None = None):
        self.rig = rig
        self.sink = sink
        self.emulated_vet = hasattr(rig.vet, "expose_pattern")
        self.emulated_meas = hasattr(rig.measurement, "render")
        self.n_cells = rig.params.lcos_cells[0] * rig.params.lcos_cells[1]
        self._meas_k = 0
        self._stale = False

    @staticmethod
    def mono(img: np.ndarray) -> np.ndarray:
        """(H, W) float32: colour frames averaged over their channels."""
        a = np.asarray(img, np.float32)
        return a.mean(axis=2) if a.ndim == 3 else a

    @staticmethod
    def _fixed_exposure_s(cam: Any, default_s: float) -> float:
        """A real camera's own exposure, seconds.

        A GenICam camera's ``exposure_us`` as it reads it back (``describe()``; cameras
        round), else as asked; a V4L2 camera's ``exposure`` in driver units of 100 us;
        else ``default_s``.
        """
        cam.open()
        us = cam.describe().get("exposure_us") or getattr(cam, "exposure_us", None)
        if us:
            return float(us) * 1e-6
        exp = getattr(cam, "exposure", None)
        return float(exp) * 1e-4 if exp else default_s

    def vet_fixed_exposure_s(self) -> float:
        """A real VET camera's exposure, seconds (else the frame length)."""
        return self._fixed_exposure_s(self.rig.vet, self.rig.params.frame_s)

    def meas_fixed_exposure_s(self) -> float:
        """A real measurement camera's exposure, seconds (else the subframe length)."""
        return self._fixed_exposure_s(self.rig.measurement, self.rig.params.subframe_s)

    @staticmethod
    def _grab(cam: Any) -> np.ndarray:
        """One frame of a real camera; a host-triggered one is started first."""
        cam.start_exposure()
        return cam.grab().data

    def mark_stale(self) -> None:
        """The scene changed (a mask, a board placed): a real camera's next frame may
        have started before, and is dropped."""
        self._stale = True

    def show(self, closed: np.ndarray | None) -> None:
        """Put a mask on the LCoS (None: all open) and wait for the device to apply it."""
        mask = np.zeros(self.n_cells, bool) if closed is None else np.asarray(closed, bool).ravel()
        self.rig.lcos.send_full_mask(mask, wait=True)
        self.mark_stale()

    def vet(
        self,
        closed: np.ndarray | None,
        exposure_s: float,
        n: int,
        light: bool = True,
        tag: tuple[str, float] | None = None,
    ) -> np.ndarray:
        """Mean of ``n`` VET frames, (H, W) float32 DN, through ``closed`` (None: all open).

        The emulated camera exposes ``exposure_s`` seconds (``light=False``: a dark frame);
        a real one keeps its own exposure, and its first frame after a new mask is dropped.
        Each frame goes to the sink under ``tag`` when both are given.
        """
        acc = None
        for i in range(n):
            if self.emulated_vet:
                open_cells = None if closed is None else ~np.asarray(closed, bool).ravel()
                img = self.rig.vet.expose_pattern(open_cells, exposure_s, light=light)
            else:
                if self._stale:
                    self._grab(self.rig.vet)
                    self._stale = False
                img = self._grab(self.rig.vet)
            img = self.mono(img)
            if self.sink is not None and tag is not None:
                self.sink(tag, i, img)
            acc = img.astype(np.float64) if acc is None else acc + img
        return (acc / n).astype(np.float32)

    def meas(self, n: int, tag: tuple[str, float] | None = None) -> np.ndarray:
        """Mean of ``n`` measurement-camera frames, (H, W) float32 DN (each to the sink
        under ``tag``)."""
        acc = None
        for i in range(n):
            if self.emulated_meas:
                img = self.rig.measurement.render(
                    self._meas_k % max(self.rig.params.n_subframes, 1)
                )
                self._meas_k += 1
            else:
                img = self._grab(self.rig.measurement)
            img = self.mono(img)
            if self.sink is not None and tag is not None:
                self.sink(tag, i, img)
            acc = img.astype(np.float64) if acc is None else acc + img
        return (acc / n).astype(np.float32)


def acquire_frames(
    rig: Any,
    settings: AcquisitionSettings | None = None,
    progress: ProgressFn | None = None,
    sink: FrameSink | None = None,
) -> CalibrationFrames:
    """Drive a rig through the calibration sequence and collect averaged frames.

    Order: dark frames (emulated VET camera only: a real one needs its lens capped, so
    record them and use :func:`calibrate_from_folder`), all-open flat field (exposure
    found from a probe), all-closed flat field (longer exposure, capped), the Gray-code
    patterns and inverses, the measurement camera on the flat field. The LCoS is left
    all open.

    Parameters
    ----------
    rig : stages.devices.rigs.Rig
        An open rig viewing a flat, bright, still field.
    settings : AcquisitionSettings, optional
    progress : callable(done, total), optional
    sink : callable(tag, index, frame), optional
        Receives every frame averaged (:data:`FrameSink`; probes are not), e.g. to
        record the calibration as a folder for :func:`calibrate_from_folder`.

    Returns
    -------
    CalibrationFrames
    """
    s = settings or AcquisitionSettings()
    ex = RigExposer(rig, sink)
    params = rig.params
    patterns = gray_code_patterns(params.lcos_cells)
    n_gray = len(patterns)
    total = (len(s.dark_exposures_s) if ex.emulated_vet else 0) + 4 + n_gray // 2
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    frames = CalibrationFrames()
    n = s.frames_per_exposure
    full = params.max_dn
    if ex.emulated_vet:
        for t in s.dark_exposures_s:
            frames.dark[float(t)] = ex.vet(None, float(t), n, light=False, tag=("dark", float(t)))
            tick()
    else:
        log.warning(
            "calibrate: a real camera cannot take dark frames unattended; record them with the lens "
            "capped and calibrate from a folder (--frames) for dark current and bias"
        )

    ex.show(None)
    if ex.emulated_vet:
        t_probe = params.subframe_s
        probe = ex.vet(None, t_probe, 1)
        rate = max(float(np.percentile(probe, 99)), 1.0) / t_probe
        t_open = min(s.max_exposure_s, s.target_fill * full / rate)
    else:
        t_open = ex.vet_fixed_exposure_s()
    frames.open[t_open] = ex.vet(None, t_open, n, tag=("open", t_open))
    tick()

    ex.show(np.ones(ex.n_cells, bool))
    if ex.emulated_vet:
        probe = ex.vet(np.ones(ex.n_cells, bool), t_open, 1)
        # pixels outside the LCoS footprint stay bright: size the exposure on the dim majority
        rate_c = max(float(np.percentile(probe, 50)), 0.05) / t_open
        t_closed = float(min(s.max_exposure_s, max(t_open, s.target_fill * full / rate_c)))
    else:
        t_closed = ex.vet_fixed_exposure_s()
    frames.closed[t_closed] = ex.vet(
        np.ones(ex.n_cells, bool), t_closed, n, tag=("closed", t_closed)
    )
    tick()

    diffs = []
    for k in range(0, n_gray, 2):
        imgs = []
        for j, pat in enumerate((patterns[k], patterns[k + 1])):
            closed = ~pat
            ex.show(closed)
            imgs.append(ex.vet(closed, t_open, s.gray_frames, tag=("gray", k + j)))
        diffs.append(imgs[0] - imgs[1])
        tick()
    frames.gray_diffs = diffs
    ex.show(None)
    tick()

    t_meas = params.subframe_s if ex.emulated_meas else ex.meas_fixed_exposure_s()
    frames.meas_flat[t_meas] = ex.meas(n, tag=("meas_flat", t_meas))
    tick()
    sat = float(np.mean(frames.meas_flat[t_meas] >= params.saturation_dn))
    if sat > 0.01:
        log.warning(
            "calibrate: %.0f%% of the measurement camera's flat field is saturated; the gain ratio "
            "is biased low",
            100 * sat,
        )
    frames.counts = {"dark": n, "open": n, "closed": n, "gray": s.gray_frames, "meas_flat": n}
    return frames


def calibrate_rig(
    rig: Any, progress: ProgressFn | None = None, settings: AcquisitionSettings | None = None
) -> Calibration:
    """Calibrate a rig (emulated or real) that views a flat, bright, still field.

    Parameters
    ----------
    rig : stages.devices.rigs.Rig
    progress : callable(done, total), optional
    settings : AcquisitionSettings, optional

    Returns
    -------
    Calibration
    """
    return calibrate_rig_frames(rig, progress, settings)[0]


def calibrate_rig_frames(
    rig: Any, progress: ProgressFn | None = None, settings: AcquisitionSettings | None = None
) -> tuple[Calibration, CalibrationFrames]:
    """:func:`calibrate_rig` and the averaged frames it was computed from."""
    t0 = time.monotonic()
    s = settings or AcquisitionSettings()
    frames = acquire_frames(rig, s, progress)
    prov = {
        "source": f"rig:{rig.name}",
        "rig_meta": dict(rig.meta),
        "exposures_s": {
            "dark": sorted(frames.dark),
            "open": sorted(frames.open),
            "closed": sorted(frames.closed),
            "meas_flat": sorted(frames.meas_flat),
        },
        "frames_averaged": frames.counts,
        "software": software_version(),
    }
    cal = calibrate_frames(frames, rig.params, prov)
    cal.provenance["elapsed_s"] = round(time.monotonic() - t0, 3)
    return cal, frames
