"""Opening a rig: the emulated one (``sim``) or real hardware described by a TOML file.

A :class:`Rig` has an LCoS controller (:class:`~stages.devices.lcos.LCoSDevice`), a
measurement camera and a VET camera, plus the rig's :class:`~stages.rig.RigParams`.
The capture loop and calibration drive any rig through this one interface.

Rig file (TOML) for real hardware::

    [params]                      # optional RigParams overrides (DESIGN.md §2 defaults)
    lcos_cells = [1024, 600]
    sensor_size = [1280, 1024]

    [lcos]
    url = "/dev/ttyACM0"          # any pyserial URL: /dev/ttyUSB0, socket://host:port, ...
    baudrate = 115200             # optional (UARTs)
    link_bps = 12e6               # optional: the link's real rate, for ACK timeouts
    ack_timeout_s = 0.5           # optional: silence before a frame is resent
    max_retries = 8               # optional: resends before the capture gives up

    [measurement_camera]
    source = "/dev/video0"        # V4L2 device, video file, image pattern or folder (replay)
    exposure = 75                 # driver units (V4L2: 100 us)

    [vet_camera]
    source = "/dev/video1"
    exposure = 9997

A GenICam camera (GigE Vision, USB3 Vision; :mod:`stages.devices.genicam`) instead::

    [measurement_camera]
    backend = "genicam"
    device = "Aravis-Fake-GV01"   # Aravis device id, serial number or IP; omit: the first
    pixel_format = "Mono16"       # Mono8, Mono16 or RGB8
    right_shift = 4               # a 12-bit sensor left-justified in 16 bits
    exposure_us = 7000
    frame_rate_hz = 131.9         # one frame per measuring subframe
    trigger = "free"              # free, software, or a trigger line such as Line0

    [vet_camera]
    backend = "genicam"
    device = "192.168.1.20"
    exposure_us = 999750
    trigger = "software"          # the host starts the exposure with the frame

The emulated rig renders ``scene`` moving by ``motion`` through the same physics as
``vet simulate``; its LCoS controller runs in its own process on a pseudo-terminal and
speaks the real protocol, with a throttled link and optional fault injection.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..formats.limits import parse_toml
from ..formats.schema import check_rig_file
from ..rig import RigParams
from .cameras import Camera, OpenCVCamera
from .emulated_cameras import EmulatedMeasurementCamera, EmulatedVETCamera
from .lcos import LCoSDevice, SerialLCoS


@dataclass
class SimOptions:
    """Settings of the emulated rig (``--rig sim``)."""

    scene: str = "builtin:interior"
    motion: str = "none"
    size: tuple[int, int] | None = None
    seed: int = 0
    link_bps: float | None = None
    link_fault_rate: float = 0.0
    disconnect_at_subframe: int | None = None
    drop_frames: tuple[int, ...] = ()
    true_homography: list[list[float]] | None = None  # what calibration must discover
    realtime: bool = True
    overrides: dict[str, Any] = field(default_factory=dict)
    profile: str = "ideal"  # stages.optics.rig_profile: ideal, realistic or a TOML file


@dataclass
class Rig:
    params: RigParams
    lcos: LCoSDevice
    measurement: Camera
    vet: Camera
    name: str
    emulator: Any = None  # LCoSEmulator for the emulated rig
    scale: float | None = None  # e-/s per scene unit (emulated rig)
    truth: np.ndarray | None = None
    truth_motion: np.ndarray | None = None
    channels: list[str] = field(default_factory=lambda: ["Y"])
    meta: dict[str, Any] = field(default_factory=dict)
    _trigger: Any = None

    @property
    def is_emulated(self) -> bool:
        return self.emulator is not None

    def tick(self, n: int = 1) -> None:
        """The measurement camera's subframe trigger: on hardware the pulse reaches the
        controller by wire; on the emulated rig we advance its clock (a no-op while the
        real-time trigger of :meth:`start_trigger` drives it)."""
        if self.emulator is not None and self._trigger is None:
            self.emulator.tick(n)

    def start_trigger(self, s0: int) -> float | None:
        """Drive the emulated controller's clock in real time from now: subframe ``s0``
        starts now and one subframe passes every ``subframe_s``, whatever the host does
        (as the camera's trigger wire does on a rig). Returns the frame's start time
        (``time.monotonic``) for the camera to pace itself against; None on hardware."""
        if self.emulator is None:
            return None
        import threading
        import time

        t0 = time.monotonic()
        tau = self.params.subframe_s
        stop = threading.Event()
        clock = self.emulator.clock

        def run() -> None:
            while not stop.is_set():
                target = s0 + int((time.monotonic() - t0) / tau)
                with clock.get_lock():
                    if clock.value < target:
                        clock.value = target
                next_edge = t0 + (target - s0 + 1) * tau
                stop.wait(max(0.0, next_edge - time.monotonic()) + 1e-4)

        thread = threading.Thread(target=run, name="vet-trigger", daemon=True)
        self._trigger = (thread, stop)
        thread.start()
        return t0

    def stop_trigger(self) -> None:
        if self._trigger is not None:
            thread, stop = self._trigger
            stop.set()
            thread.join(1.0)
            self._trigger = None

    def close(self) -> Any:
        """Close everything; returns the emulator's own record on the emulated rig."""
        record = None
        self.stop_trigger()
        for dev in (self.measurement, self.vet):
            try:
                dev.close()
            except Exception:  # noqa: BLE001 - closing must not mask the real error
                pass
        try:
            self.lcos.close()
        except Exception:  # noqa: BLE001
            pass
        if self.emulator is not None:
            try:
                record = self.emulator.stop()
            except Exception:  # noqa: BLE001
                record = None
        return record

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_sim_rig(opts: SimOptions) -> Rig:
    """Start the emulated rig: emulator process, driver on its pty, emulated cameras."""
    from ..motion import check_in_frame, parse_motion
    from ..physics import radiance_scale
    from ..scenes import load_scene, luminance
    from .lcos_emulator import LCoSEmulator

    motion = parse_motion(opts.motion)
    scene = load_scene(opts.scene, opts.size)
    h, w = scene.radiance.shape[:2]
    check_in_frame(motion, (h, w))
    from ..optics import rig_profile

    params = rig_profile(opts.profile, (w, h), **opts.overrides)
    scale = radiance_scale(float(np.percentile(luminance(scene.radiance), 99.9)), params)
    emu = LCoSEmulator(
        params.lcos_cells,
        latency_subframes=params.latency_subframes,
        leakage=params.leakage,
        link_bps=opts.link_bps,
        link_fault_rate=opts.link_fault_rate,
        disconnect_at_subframe=opts.disconnect_at_subframe,
        seed=opts.seed,
    )
    try:
        lcos = SerialLCoS(emu.port, link_bps=opts.link_bps, cells=params.lcos_cells)
    except Exception:
        emu.stop()
        raise
    meas = EmulatedMeasurementCamera(
        scene.radiance,
        motion,
        params,
        scale,
        seed=opts.seed,
        drop=opts.drop_frames,
        realtime=opts.realtime,
    )
    vet = EmulatedVETCamera(
        scene.radiance,
        motion,
        params,
        scale,
        seed=opts.seed,
        true_homography=None if opts.true_homography is None else np.asarray(opts.true_homography),
    )
    return Rig(
        params=params,
        lcos=lcos,
        measurement=meas,
        vet=vet,
        name="sim",
        emulator=emu,
        scale=scale,
        truth=scene.radiance,
        truth_motion=motion.velocity((h, w)),
        channels=list(scene.channels),
        meta={
            "scene": scene.source,
            "motion": motion.spec,
            "seed": opts.seed,
            "link_bps": opts.link_bps,
            "link_fault_rate": opts.link_fault_rate,
        },
    )


def load_rig_file(path: str | Path) -> dict[str, Any]:
    """Parse and check a rig TOML file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such rig file (use --rig sim for the emulated rig)")
    data = parse_toml(p.read_bytes(), f"{p}: rig file")
    for section in ("lcos", "measurement_camera", "vet_camera"):
        if not isinstance(data.get(section), dict):
            raise InputError(f"{p}: rig file lacks the [{section}] section")
    if "url" not in data["lcos"]:
        raise InputError(f'{p}: [lcos] needs url = "/dev/ttyACM0" (any pyserial URL)')
    for cam in ("measurement_camera", "vet_camera"):
        backend = data[cam].get("backend", "opencv")
        if backend not in CAMERA_BACKENDS:
            raise InputError(
                f"{p}: [{cam}] backend = {backend!r}; known: {', '.join(CAMERA_BACKENDS)}"
            )
        if backend == "opencv" and "source" not in data[cam]:
            raise InputError(
                f'{p}: [{cam}] needs source = "/dev/videoN" (or a video / frame folder)'
            )
    check_rig_file(data, str(p))
    return data


CAMERA_BACKENDS = ("opencv", "genicam")


def _camera(section: dict[str, Any], where: str, period_s: float) -> Camera:
    """The camera a rig file's ``[*_camera]`` table describes."""
    if section.get("backend", "opencv") == "genicam":
        from .genicam import camera_from_section

        return camera_from_section(section, where)
    return OpenCVCamera(
        section["source"], exposure=section.get("exposure"), frame_period_s=period_s
    )


def open_hardware_rig(path: str | Path, changes: dict[str, Any] | None = None) -> Rig:
    """Open the devices a rig file describes; ``changes`` (RigParams fields: the command's
    rig options, a calibration's parts) take precedence over its ``[params]``."""
    data = load_rig_file(path)
    params = RigParams.from_dict({**dict(data.get("params", {})), **dict(changes or {})})
    lc = data["lcos"]
    link = {k: lc[k] for k in ("ack_timeout_s", "max_retries") if k in lc}
    lcos = SerialLCoS(
        str(lc["url"]),
        baudrate=lc.get("baudrate"),
        link_bps=lc.get("link_bps"),
        cells=params.lcos_cells,
        subframe_s=params.subframe_s,
        **link,
    )
    meas = _camera(data["measurement_camera"], f"{path}: [measurement_camera]", params.subframe_s)
    vet = _camera(data["vet_camera"], f"{path}: [vet_camera]", params.frame_s)
    return Rig(
        params=params,
        lcos=lcos,
        measurement=meas,
        vet=vet,
        name=str(path),
        channels=["Y"],
        meta={"rig_file": str(path)},
    )


def open_rig(spec: str, sim: SimOptions | None = None, known: dict[str, Any] | None = None) -> Rig:
    """``"sim"`` -> the emulated rig (with ``sim`` options); else a rig TOML file (with
    ``sim.overrides``, the command's rig options).

    ``known``: RigParams fields the host knows from a calibration
    (:func:`stages.calibrate.calibration_changes`). The rig's ``params`` (what the capture
    loop thresholds with, and what a capture records for its reconstructions) take them;
    the emulated rig's physics does not: its truth stays what ``sim`` configures, so a
    calibration's errors reach the capture as they would on hardware.
    """
    if spec != "sim":
        over = dict(sim.overrides) if sim is not None else {}
        return open_hardware_rig(spec, {**over, **dict(known or {})})
    rig = open_sim_rig(sim or SimOptions())
    if known:
        try:
            rig.params = rig.params.replace(**known)
        except BaseException:
            rig.close()
            raise
    return rig
