"""GenICam machine-vision cameras (GigE Vision, USB3 Vision) through Aravis.

Most lab cameras speak GenICam, not V4L2. :class:`GenICamCamera` drives one through
Aravis 0.8 (https://github.com/AravisProject/aravis) via PyGObject: it opens the camera
by Aravis device id, serial number or IP address, sets the region of interest, pixel
format, exposure time, gain, frame rate and trigger, reads every setting back (the camera
may round them) and streams frames as :class:`~stages.devices.cameras.Frame`.

Frames are ``(H, W, C)`` float32 DN: ``Mono8``/``Mono16`` give ``C = 1`` and ``RGB8``
gives ``C = 3``. ``right_shift`` undoes a camera's left-justified packing (a 12-bit sensor
in a 16-bit container: ``right_shift = 4``). ``Frame.index`` counts frames since the
first one this camera delivered (block ids wrap at 2^16 in GigE Vision 1.x and are
unwrapped), so a gap is a dropped frame; ``Frame.timestamp_s`` is the camera's own clock
in seconds since that first frame. Buffers that arrive incomplete are dropped (the next
frame's index shows the gap), never passed on.

Triggers: ``"free"`` streams continuously at ``frame_rate_hz``; ``"software"`` exposes one
frame per :meth:`GenICamCamera.start_exposure` (the VET camera: its exposure starts with
the VET frame); any other value names a hardware trigger line (``"Line0"``), wired to the
rig's trigger.

Aravis and PyGObject are optional: Debian's ``gir1.2-aravis-0.8`` and ``pip install
'PyGObject<3.51'`` (``make test-hardware`` installs both). Without them, opening a GenICam
camera raises :class:`~stages.errors.DeviceError` saying so.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..errors import DeviceError, InputError
from .cameras import Camera, Frame

#: Pixel formats vet reads: name -> (numpy dtype, channels).
PIXEL_FORMATS = {"Mono8": (np.uint8, 1), "Mono16": (np.uint16, 1), "RGB8": (np.uint8, 3)}
TRIGGERS_BUILTIN = ("free", "software")
#: Keys a ``[*_camera]`` section with ``backend = "genicam"`` may hold.
SECTION_KEYS = {
    "backend",
    "device",
    "exposure_us",
    "gain",
    "frame_rate_hz",
    "pixel_format",
    "region",
    "right_shift",
    "trigger",
    "timeout_s",
}


def aravis() -> Any:
    """The ``Aravis`` 0.8 module from PyGObject; :class:`DeviceError` when unavailable."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceError(
            f"GenICam cameras need Aravis 0.8 and PyGObject ({exc}); install Debian's "
            "gir1.2-aravis-0.8 and pip install 'PyGObject<3.51' (make test-hardware does both)"
        ) from None
    return Aravis


def list_devices() -> list[dict[str, str]]:
    """GenICam cameras Aravis finds: ``[{"id", "serial", "address", "protocol"}, ...]``."""
    arv = aravis()
    arv.update_device_list()
    return [
        {
            "id": arv.get_device_id(i),
            "serial": arv.get_device_serial_nbr(i),
            "address": arv.get_device_address(i),
            "protocol": arv.get_device_protocol(i),
        }
        for i in range(arv.get_n_devices())
    ]


class GenICamCamera(Camera):
    """A GenICam camera through Aravis.

    Parameters
    ----------
    device : str, optional
        Aravis device id (``"Aravis-Fake-GV01"``), serial number or IP address; None opens
        the first camera found.
    exposure_us, gain, frame_rate_hz : float, optional
        Set when given (checked against the camera's bounds); read back either way.
    pixel_format : str
        One of :data:`PIXEL_FORMATS`.
    region : (width, height) or (width, height, x, y), optional
        Region of interest; the whole sensor when None.
    right_shift : int
        Bits to shift each pixel right (0-8).
    trigger : str
        ``"free"``, ``"software"`` or a trigger line name.
    timeout_s : float
        How long :meth:`grab` waits beyond one frame period or exposure.
    n_buffers : int
        Stream buffers queued with the camera.
    """

    def __init__(
        self,
        device: str | None = None,
        exposure_us: float | None = None,
        gain: float | None = None,
        frame_rate_hz: float | None = None,
        pixel_format: str = "Mono16",
        region: tuple[int, ...] | None = None,
        right_shift: int = 0,
        trigger: str = "free",
        timeout_s: float = 2.0,
        n_buffers: int = 16,
    ) -> None:
        super().__init__()
        if pixel_format not in PIXEL_FORMATS:
            raise InputError(
                f"pixel_format {pixel_format!r} is not one of {', '.join(PIXEL_FORMATS)}"
            )
        if region is not None and len(region) not in (2, 4):
            raise InputError(
                f"region must be [width, height] or [width, height, x, y], got {region}"
            )
        if not 0 <= int(right_shift) <= 8:
            raise InputError(f"right_shift must be 0-8 bits, got {right_shift}")
        if not timeout_s > 0:
            raise InputError(f"timeout_s must be > 0, got {timeout_s}")
        self.device = device
        self.exposure_us = exposure_us
        self.gain = gain
        self.frame_rate_hz = frame_rate_hz
        self.pixel_format = pixel_format
        self.region = tuple(int(v) for v in region) if region is not None else None
        self.right_shift = int(right_shift)
        self.trigger = trigger
        self.timeout_s = float(timeout_s)
        self.n_buffers = int(n_buffers)
        self.settings: dict[str, Any] = {}
        self._cam: Any = None
        self._stream: Any = None
        self._shape: tuple[int, int] = (0, 0)
        self._first: tuple[int, int] | None = None  # (block id, timestamp ns) of frame 0
        self._last_id = 0
        self._count = 0

    # -- opening -----------------------------------------------------------------------

    def _do_open(self) -> None:
        arv = aravis()
        from gi.repository import GLib

        name = self.device or "the first GenICam camera"
        try:
            cam = arv.Camera.new(self.device)
        except GLib.Error as exc:
            raise DeviceError(f"cannot open GenICam camera {name!r}: {exc.message}") from None
        self._cam = cam
        try:
            self._configure(cam)
            stream = cam.create_stream(None, None)
            payload = cam.get_payload()
            for _ in range(self.n_buffers):
                stream.push_buffer(arv.Buffer.new_allocate(payload))
            self._stream = stream
            cam.start_acquisition()
        except GLib.Error as exc:
            self._release()
            raise DeviceError(f"GenICam camera {name!r}: {exc.message}") from None
        except DeviceError:
            self._release()
            raise

    def _configure(self, cam: Any) -> None:
        available = list(cam.dup_available_pixel_formats_as_strings())
        if self.pixel_format not in available:
            raise DeviceError(
                f"camera offers pixel formats {', '.join(available)}; not {self.pixel_format}"
            )
        cam.set_pixel_format_from_string(self.pixel_format)
        sensor_w, sensor_h = cam.get_sensor_size()
        if self.region is not None:
            w, h, x, y = (*self.region, 0, 0)[:4]
            if x + w > sensor_w or y + h > sensor_h or w <= 0 or h <= 0:
                raise DeviceError(
                    f"region {w}x{h}+{x}+{y} does not fit the {sensor_w}x{sensor_h} sensor"
                )
            cam.set_region(x, y, w, h)
        if self.trigger == "free":
            cam.clear_triggers()
            cam.set_acquisition_mode(aravis().AcquisitionMode.CONTINUOUS)
        else:
            source = "Software" if self.trigger == "software" else self.trigger
            sources = list(cam.dup_available_trigger_sources())
            if source not in sources:
                raise DeviceError(f"camera trigger sources are {', '.join(sources)}; not {source}")
            cam.set_trigger(source)
        for what, value, bounds, setter in (
            ("exposure_us", self.exposure_us, cam.get_exposure_time_bounds, cam.set_exposure_time),
            ("gain", self.gain, cam.get_gain_bounds, cam.set_gain),
            ("frame_rate_hz", self.frame_rate_hz, cam.get_frame_rate_bounds, cam.set_frame_rate),
        ):
            if value is None:
                continue
            lo, hi = bounds()
            if not lo <= float(value) <= hi:
                raise DeviceError(f"{what} {value} is outside the camera's range [{lo:g}, {hi:g}]")
            setter(float(value))
        x, y, w, h = cam.get_region()
        self._shape = (h, w)
        dev = cam.get_device()
        self.settings = {
            "backend": "genicam",
            "vendor": cam.get_vendor_name(),
            "model": cam.get_model_name(),
            "serial": cam.get_device_serial_number(),
            "pixel_format": cam.get_pixel_format_as_string(),
            "region": [x, y, w, h],
            "exposure_us": float(cam.get_exposure_time()),
            "gain": float(cam.get_gain()) if cam.is_gain_available() else None,
            "frame_rate_hz": float(cam.get_frame_rate()),
            "trigger": self.trigger,
            "trigger_mode": dev.get_string_feature_value("TriggerMode"),
            "right_shift": self.right_shift,
        }

    # -- frames ------------------------------------------------------------------------

    def start_exposure(self) -> None:
        """Start one exposure now (``trigger = "software"``); a no-op otherwise."""
        if self.trigger == "software":
            if not self._is_open:
                self.open()
            self._cam.software_trigger()

    def set_exposure_s(self, seconds: float) -> float | None:
        """Set ``ExposureTime`` to ``seconds`` and return what the camera reads back (s;
        it rounds); None where the camera has no settable exposure time or ``seconds``
        is outside its bounds."""
        if not self._is_open:
            self.open()
        cam = self._cam
        if not cam.is_exposure_time_available():
            return None
        us = float(seconds) * 1e6
        lo, hi = cam.get_exposure_time_bounds()
        if not lo <= us <= hi:
            return None
        cam.set_exposure_time(us)
        got = float(cam.get_exposure_time())
        self.settings["exposure_us"] = got
        return got * 1e-6

    def _wait_s(self) -> float:
        s = self.settings
        period = 1.0 / s["frame_rate_hz"] if s.get("frame_rate_hz") else 0.0
        return max(period, s.get("exposure_us", 0.0) * 1e-6) + self.timeout_s

    def _do_grab(self) -> Frame:
        arv = aravis()
        deadline = time.monotonic() + self._wait_s()
        while True:
            left = deadline - time.monotonic()
            buf = self._stream.timeout_pop_buffer(max(1, int(left * 1e6))) if left > 0 else None
            if buf is None:
                raise DeviceError(
                    f"GenICam camera {self.settings.get('serial', self.device)!r} delivered no "
                    f"frame within {self._wait_s():.1f} s"
                )
            try:
                if buf.get_status() != arv.BufferStatus.SUCCESS:
                    continue  # incomplete: dropped; the next frame's index shows the gap
                return self._frame(buf)
            finally:
                self._stream.push_buffer(buf)

    def _frame(self, buf: Any) -> Frame:
        dtype, nch = PIXEL_FORMATS[self.pixel_format]
        h, w = buf.get_image_height(), buf.get_image_width()
        raw = np.frombuffer(buf.get_data(), dtype=dtype)
        if raw.size != h * w * nch:
            raise DeviceError(
                f"camera sent {raw.size} samples for a {w}x{h} {self.pixel_format} frame"
            )
        data = raw.reshape(h, w, nch)
        if self.right_shift:
            data = data >> self.right_shift
        block, stamp = int(buf.get_frame_id()), int(buf.get_timestamp())
        if self._first is None:
            self._first, self._last_id, self._count = (block, stamp), block, 0
        else:
            step = block - self._last_id
            if step <= 0 and self._last_id < 1 << 16:  # GigE Vision 1.x 16-bit block ids wrap
                step %= (1 << 16) - 1  # block id 0 is never used
            self._count += max(1, step)
            self._last_id = block
        return Frame(data.astype(np.float32), self._count, (stamp - self._first[1]) * 1e-9)

    # -- closing -----------------------------------------------------------------------

    def _release(self) -> None:
        if self._cam is not None:
            try:
                self._cam.stop_acquisition()
            except Exception:  # noqa: BLE001 - closing must not mask the real error
                pass
        self._stream = None
        self._cam = None

    def _do_close(self) -> None:
        self._release()
        self._first = None

    def describe(self) -> dict[str, Any]:
        return dict(self.settings) or {"backend": "genicam", "device": self.device}


def camera_from_section(section: dict[str, Any], where: str) -> GenICamCamera:
    """A :class:`GenICamCamera` from a rig file's ``[*_camera]`` table (``where`` names it
    in messages)."""
    unknown = sorted(set(section) - SECTION_KEYS)
    if unknown:
        raise InputError(
            f"{where}: unknown key(s) {', '.join(unknown)} for a genicam camera "
            f"(known: {', '.join(sorted(SECTION_KEYS))})"
        )
    region = section.get("region")
    try:
        return GenICamCamera(
            device=None if section.get("device") is None else str(section["device"]),
            exposure_us=_number(section, "exposure_us", where),
            gain=_number(section, "gain", where),
            frame_rate_hz=_number(section, "frame_rate_hz", where),
            pixel_format=str(section.get("pixel_format", "Mono16")),
            region=None if region is None else tuple(int(v) for v in region),
            right_shift=int(section.get("right_shift", 0)),
            trigger=str(section.get("trigger", "free")),
            timeout_s=float(section.get("timeout_s", 2.0)),
        )
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None
    except InputError as exc:
        raise InputError(f"{where}: {exc}") from None


def _number(section: dict[str, Any], key: str, where: str) -> float | None:
    value = section.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"{where}: {key} must be a number, got {value!r}")
    return float(value)
