"""Cameras: the measurement sensor and the VET sensor of a rig.

A :class:`Camera` yields frames in DN as ``ndarray of shape (H, W, C)`` float32 with a
frame index and a timestamp. Its public methods wrap ``_do_*`` hooks, so drivers only
implement the hooks (python-microscope style).

- :class:`OpenCVCamera`: a V4L2 device (manual exposure in the driver's units, raw
  16-bit frames with ``CAP_PROP_CONVERT_RGB`` off), or a video file / image sequence /
  folder of PNG or TIFF frames for replaying a recorded measuring stream.
- the emulated rig's cameras are in :mod:`.emulated_cameras`.
"""

from __future__ import annotations

import abc
import glob
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DeviceError, InputError


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

    def set_exposure_s(self, seconds: float) -> float | None:
        """Set the exposure to ``seconds`` from the host; returns the exposure the camera
        reports back (s; cameras round), or None where it cannot be set this way (the
        default; calibration's switching series needs it)."""
        return None

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
#: A V4L2 driver's exposure unit (``V4L2_CID_EXPOSURE_ABSOLUTE``), seconds.
V4L2_EXPOSURE_UNIT_S = 1e-4


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
        is_device = self._is_v4l2()
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

    def set_exposure_s(self, seconds: float) -> float | None:
        """A V4L2 device's manual exposure in its units of 100 us (read back: the driver
        rounds); None for a replayed source or a driver that refuses it."""
        import cv2

        self.open()
        if self._cap is None or not self._is_v4l2():
            return None
        units = max(1.0, round(float(seconds) / V4L2_EXPOSURE_UNIT_S))
        self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)
        if not self._cap.set(cv2.CAP_PROP_EXPOSURE, units):
            return None
        got = float(self._cap.get(cv2.CAP_PROP_EXPOSURE))
        if got <= 0:
            return None
        self.exposure = got
        return got * V4L2_EXPOSURE_UNIT_S

    def _is_v4l2(self) -> bool:
        src = self.source
        return isinstance(src, int) or (isinstance(src, str) and src.startswith("/dev/video"))

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
