"""Cameras: the measurement sensor and the VET sensor of a rig.

A :class:`Camera` yields frames in DN as ``ndarray of shape (H, W, C)`` float32 with a
frame index and a timestamp. Its public methods wrap ``_do_*`` hooks, so drivers only
implement the hooks (python-microscope style).

- :class:`OpenCVCamera`: a V4L2 device (manual exposure in the driver's units, raw
  16-bit frames with ``CAP_PROP_CONVERT_RGB`` off), or a video file / image sequence /
  folder of PNG or TIFF frames for replaying a recorded measuring stream.
- :class:`EmulatedMeasurementCamera` and :class:`EmulatedVETCamera`: render a scene with
  motion through the same sensor physics as ``vet simulate`` (:mod:`stages.physics`);
  the VET camera integrates through the LCoS state that the emulated controller
  *applied*, so what it records depends on the link, as on a real rig.
"""

from __future__ import annotations

import abc
import glob
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DeviceError, InputError
from ..motion import Motion
from ..optics import (
    MeasureGeometry,
    close_times,
    leakage_map,
    pixel_leakage,
    relay_blur,
    slot_transmittance,
    subframe_clock,
    timing_rng,
)
from ..physics import CellMap, SensorNoise, expose, noise_streams
from ..rig import RigParams


@dataclass
class Frame:
    data: np.ndarray  # (H, W, C) DN: float32, or the sensor's integers
    index: int  # frame counter as reported by the source (gaps = dropped frames)
    timestamp_s: float


class Camera(abc.ABC):
    """Abstract camera. Use as a context manager or call :meth:`close`."""

    def __init__(self) -> None:
        self._is_open = False

    def open(self) -> None:
        if not self._is_open:
            self._do_open()
            self._is_open = True

    def grab(self) -> Frame:
        """The next frame; raises :class:`DeviceError` when the source fails or ends."""
        if not self._is_open:
            self.open()
        return self._do_grab()

    def start_exposure(self) -> None:  # noqa: B027 - optional hook
        """Start the frame's exposure now, where the camera is triggered by the host (a
        GenICam software trigger); free-running and wired cameras ignore it."""

    def describe(self) -> dict:
        """The camera's settings as recorded in a capture's metadata."""
        return {"backend": type(self).__name__}

    def close(self) -> None:
        if self._is_open:
            self._do_close()
            self._is_open = False

    def __enter__(self) -> Camera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @abc.abstractmethod
    def _do_open(self) -> None: ...

    @abc.abstractmethod
    def _do_grab(self) -> Frame: ...

    def _do_close(self) -> None:  # noqa: B027 - optional hook
        pass


# --- OpenCV -----------------------------------------------------------------------------

IMAGE_EXTENSIONS = (".png", ".tif", ".tiff", ".pgm", ".ppm")


class OpenCVCamera(Camera):
    """A camera through OpenCV.

    Parameters
    ----------
    source : str or int
        ``/dev/videoN`` or an index (V4L2 device); a video file; a printf pattern such as
        ``frames/%04d.png``; or a folder of PNG/TIFF frames (sorted by name) to replay.
    exposure : float, optional
        Manual exposure in the driver's units (V4L2: 100 microseconds).
    frame_period_s : float
        Timestamp spacing for replayed sources (they carry no clock).
    """

    def __init__(
        self, source: str | int, exposure: float | None = None, frame_period_s: float = 0.00758
    ):
        super().__init__()
        self.source = source
        self.exposure = exposure
        self.frame_period_s = frame_period_s
        self._cap = None
        self._files: list[str] | None = None
        self._next = 0

    def _do_open(self) -> None:
        import cv2

        src = self.source
        if isinstance(src, str) and Path(src).is_dir():
            files = sorted(
                f for f in glob.glob(os.path.join(src, "*")) if f.lower().endswith(IMAGE_EXTENSIONS)
            )
            if not files:
                raise InputError(f"{src}: folder holds no PNG or TIFF frames")
            self._files = files
            return
        if isinstance(src, str) and "%" in src:
            # An image sequence: OpenCV's CAP_IMAGES backend would convert it to 8 bits,
            # so expand the pattern and read each frame unchanged (16-bit preserved).
            first = 0 if os.path.exists(src % 0) else 1
            files = []
            while os.path.exists(src % (first + len(files))):
                files.append(src % (first + len(files)))
            if not files:
                raise InputError(f"{src}: no frames match this pattern")
            self._files = files
            return
        is_device = isinstance(src, int) or (isinstance(src, str) and src.startswith("/dev/video"))
        if isinstance(src, str) and not is_device and not Path(src).exists():
            raise InputError(f"{src}: no such video file or device")
        self._cap = cv2.VideoCapture(src, cv2.CAP_V4L2) if is_device else cv2.VideoCapture(src)
        if not self._cap.isOpened():
            raise DeviceError(f"cannot open camera {src!r}")
        if is_device:
            self._cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)  # raw frames, 16-bit where the sensor has it
            if self.exposure is not None:
                self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
                self._cap.set(cv2.CAP_PROP_EXPOSURE, float(self.exposure))

    def describe(self) -> dict:
        return {"backend": "opencv", "source": str(self.source), "exposure": self.exposure}

    def _do_grab(self) -> Frame:
        import cv2

        idx = self._next
        if self._files is not None:
            if idx >= len(self._files):
                raise DeviceError(f"replay source {self.source} ended after {idx} frames")
            img = cv2.imread(self._files[idx], cv2.IMREAD_UNCHANGED)
            if img is None:
                raise DeviceError(f"{self._files[idx]}: unreadable frame")
            ts = idx * self.frame_period_s
        else:
            ok, img = self._cap.read()
            if not ok or img is None:
                raise DeviceError(
                    f"camera {self.source!r} delivered no frame (ended or disconnected)"
                )
            pos = self._cap.get(cv2.CAP_PROP_POS_FRAMES)
            idx = int(pos) - 1 if pos and pos > 0 else idx
            msec = self._cap.get(cv2.CAP_PROP_POS_MSEC)
            ts = msec / 1000.0 if msec and msec > 0 else idx * self.frame_period_s
        self._next = idx + 1
        data = np.asarray(img, dtype=np.float32)
        if data.ndim == 2:
            data = data[:, :, None]
        elif data.shape[2] >= 3:
            data = data[:, :, [2, 1, 0]]  # OpenCV delivers BGR
        return Frame(data, idx, ts)

    def _do_close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


# --- emulated ---------------------------------------------------------------------------


class _SceneSource:
    """Scene radiance in electrons/s at the sensor, rendered at any time."""

    def __init__(self, radiance: np.ndarray, motion: Motion, scale: float):
        self.radiance = radiance
        self.motion = motion
        self.scale = np.float32(scale)
        self._still = radiance * self.scale if motion.is_still else None

    def rate(self, t: float) -> np.ndarray:
        if self._still is not None:
            return self._still
        return self.motion.render(self.radiance, t) * self.scale


class EmulatedMeasurementCamera(Camera):
    """Emulated measurement sensor: subframe ``k`` renders the scene at mid-subframe
    time through the sensor chain with its own seeded stream (same physics and seeding
    rule as ``simulate``, so a perfect link reproduces ``simulate``'s capture).

    With ``realtime`` the whole frame's subframes are rendered when the camera opens
    and then delivered on the real subframe clock (subframe ``k`` at ``(k + 1) tau``
    after the first grab), so the host loop and the throttled LCoS link see real
    timing. ``drop`` lists frame indices to skip, to exercise the capture loop's
    handling of dropped frames.
    """

    def __init__(
        self,
        radiance: np.ndarray,
        motion: Motion,
        rig: RigParams,
        scale: float,
        seed: int = 0,
        drop: tuple[int, ...] = (),
        realtime: bool = False,
    ):
        super().__init__()
        self.rig = rig
        self.source = _SceneSource(radiance, motion, scale)
        self.streams = noise_streams(seed)[1].spawn(rig.n_subframes + 1)
        # A real rig's measurement camera (stages.optics): its own grid, gain and
        # vignetting; its trigger offset and the frames it drops (drop_rate).
        self.geom = None if rig.ideal_geometry else MeasureGeometry(rig)
        _, rig_drops = subframe_clock(rig, timing_rng(seed))
        self.drop = set(drop) | set(np.flatnonzero(rig_drops).tolist())
        self.realtime = realtime
        self._frames: np.ndarray | None = None
        self._t0: float | None = None
        self._k = 0

    def _do_open(self) -> None:
        self._k = 0
        self._t0 = None
        if self.realtime:
            from concurrent.futures import ThreadPoolExecutor

            k_sub = self.rig.n_subframes
            shape = (*self.rig.measure_shape, self.source.radiance.shape[2])
            self._frames = np.empty((k_sub, *shape), np.int16)  # DN fit: [-black, 4095]
            with ThreadPoolExecutor(max_workers=2) as ex:
                for k, frame in enumerate(ex.map(self.render, range(k_sub))):
                    self._frames[k] = frame

    def start_at(self, t0: float | None) -> None:
        """Pace against a frame start ``t0`` (``time.monotonic``): subframe ``k`` is
        delivered at ``t0 + (k + 1) tau``, its end, as a triggered camera does."""
        self._t0 = t0

    def render(self, k: int) -> np.ndarray:
        rig = self.rig
        tau = rig.subframe_s
        lam = self.source.rate((k + 0.5) * tau) * np.float32(tau * rig.measure_fraction)
        rng = np.random.default_rng(self.streams[min(k, len(self.streams) - 1)])
        if self.geom is not None:
            return self.geom.expose(lam, np.float32(rig.dark_current_e_s * tau), rng)
        lam += np.float32(rig.dark_current_e_s * tau)
        return expose(lam, rig, rng)

    def _do_grab(self) -> Frame:
        import time

        while self._k in self.drop:
            self._k += 1
        k = self._k
        if k >= self.rig.n_subframes:
            raise DeviceError("measurement camera: frame is over (no more subframes)")
        self._k += 1
        stamp = k * self.rig.subframe_s + self.rig.trigger_offset_s
        if self._frames is None:
            return Frame(self.render(k), k, stamp)
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now - k * self.rig.subframe_s
        due = self._t0 + (k + 1) * self.rig.subframe_s
        if due > now:
            time.sleep(due - now)
        return Frame(self._frames[k], k, stamp)  # int16 DN, as a sensor delivers

    def _do_close(self) -> None:
        self._frames = None


class EmulatedVETCamera(Camera):
    """Emulated VET sensor behind the LCoS.

    :meth:`expose_frame` integrates one frame given, per LCoS cell, the subframe index
    from which the cell was closed as the controller applied it; :meth:`expose_pattern`
    images a static LCoS mask (calibration). ``true_homography`` may differ from the
    rig's nominal one, which is what calibration must discover.
    """

    def __init__(
        self,
        radiance: np.ndarray,
        motion: Motion,
        rig: RigParams,
        scale: float,
        seed: int = 0,
        true_homography: np.ndarray | None = None,
    ):
        super().__init__()
        self.rig = rig
        self.source = _SceneSource(radiance, motion, scale)
        h, w = radiance.shape[:2]
        hom = np.asarray(
            rig.homography if true_homography is None else true_homography, dtype=float
        )
        self.cellmap = CellMap(hom, rig.lcos_cells, (h, w))
        self.rng = np.random.default_rng(noise_streams(seed)[0])
        self._frames = 0
        # A real rig's LCoS (stages.optics): per-cell leakage, relay blur, switching on
        # the measurement camera's trigger clock (the same seeded clock as its camera's).
        self.real = not rig.ideal_shutter
        if self.real:
            self.eps = pixel_leakage(rig, self.cellmap).astype(np.float64)
            self.starts, _ = subframe_clock(rig, timing_rng(seed))

    def _do_open(self) -> None:
        self._frames = 0

    def _do_grab(self) -> Frame:
        raise DeviceError("the VET camera delivers frames through expose_frame()")

    def transmission(self, open_cells: np.ndarray) -> np.ndarray:
        """(H, W, 1) transmittance for a per-cell open mask (length ``n_cells``)."""
        if self.real:
            leak = leakage_map(self.rig).ravel()
            per_cell = np.append(np.where(open_cells, np.float32(1.0), leak), np.float32(1.0))
            trans = self.cellmap.to_pixels(per_cell.astype(np.float32))
            return relay_blur(trans, self.rig.relay_blur_px)[..., None]
        per_cell = np.append(np.where(open_cells, 1.0, self.rig.leakage), 1.0).astype(np.float32)
        return self.cellmap.to_pixels(per_cell)[..., None]

    def expose_frame(self, close_subframe: np.ndarray) -> Frame:
        """Integrate a frame; ``close_subframe[c]`` (length ``n_cells``; < 0 or beyond
        the frame = never closed) is when cell ``c`` closed, in subframes."""
        rig = self.rig
        k_sub, tau = rig.n_subframes, rig.subframe_s
        cs = np.where(close_subframe < 0, np.iinfo(np.int32).max, close_subframe)
        per_pixel = self.cellmap.to_pixels(np.append(cs, np.iinfo(np.int32).max))[..., None]
        eps = np.float32(rig.leakage)
        acc = np.zeros(self.source.radiance.shape, np.float32)
        t_close = None
        if self.real:
            t_close = self.cellmap.to_pixels(
                np.append(close_times(close_subframe, self.starts), np.inf)
            )

        def trans_of(j: int, a: float, b: float) -> np.ndarray:
            if t_close is None:
                return np.where(per_pixel > j, np.float32(1.0), eps)
            t = slot_transmittance(t_close, a, b, self.eps, rig)
            return relay_blur(t, rig.relay_blur_px)[..., None]

        for j in range(k_sub):
            trans = trans_of(j, j * tau, (j + 1) * tau)
            acc += self.source.rate((j + 0.5) * tau) * np.float32(tau) * trans
        tail = rig.frame_s - k_sub * tau
        if tail > 1e-9:
            trans = trans_of(k_sub, k_sub * tau, rig.frame_s)
            acc += self.source.rate(k_sub * tau + tail / 2) * np.float32(tail) * trans
        acc += np.float32(rig.dark_current_e_s * rig.frame_s)
        # A frame's noise is drawn as simulate draws the noise its methods share.
        noise = SensorNoise(acc.shape, self.rng)
        frame = Frame(expose(acc, rig, noise), self._frames, 0.0)
        self._frames += 1
        return frame

    def expose_pattern(
        self, open_cells: np.ndarray | None, exposure_s: float, light: bool = True
    ) -> np.ndarray:
        """A still exposure of ``exposure_s`` through a static mask (None: all open);
        ``light=False`` is a dark frame (lens capped)."""
        rig = self.rig
        lam = np.zeros(self.source.radiance.shape, np.float32)
        if light:
            rate = self.source.rate(0.0)
            trans = 1.0 if open_cells is None else self.transmission(open_cells)
            lam += rate * np.float32(exposure_s) * trans
        lam += np.float32(rig.dark_current_e_s * exposure_s)
        return expose(lam, rig, self.rng)
