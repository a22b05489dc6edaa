"""The motions with one velocity per pixel, constant in time (none, translate, object,
rotate, field), and the warp every motion renders with (:mod:`stages.motion`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError


def warp(img: np.ndarray, m: np.ndarray, border: int) -> np.ndarray:
    import cv2

    h, w = img.shape[:2]
    out = cv2.warpAffine(
        img, m.astype(np.float64), (w, h), flags=cv2.INTER_LINEAR, borderMode=border
    )
    if out.ndim == 2 and img.ndim == 3:
        out = out[:, :, None]
    return out


def reflect_period(shift: float, size: int) -> float:
    """``shift`` less whole periods of a mirrored border (``2 * size``): the same picture
    under ``BORDER_REFLECT``, whose cost in OpenCV grows with the distance (a shift of
    1e9 pixels ran for minutes). Shifts within one period are returned unchanged."""
    period = 2.0 * size
    return math.fmod(shift, period) if abs(shift) > period else shift


class Motion:
    """Base class: a motion that can render the scene at any time."""

    spec: str = "none"

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        """Scene (H, W, C) as seen at time ``t`` seconds."""
        return scene

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        """True image velocity at t = 0, ``ndarray of shape (H, W, 2)`` (u, v) px/s."""
        return np.zeros((*shape, 2), np.float32)

    @property
    def is_still(self) -> bool:
        return True


@dataclass
class NoMotion(Motion):
    spec: str = "none"


@dataclass
class Translate(Motion):
    vx: float
    vy: float

    @property
    def spec(self) -> str:  # type: ignore[override]
        return f"translate:{self.vx:g},{self.vy:g}"

    @property
    def is_still(self) -> bool:
        return self.vx == 0 and self.vy == 0

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        h, w = scene.shape[:2]
        dx, dy = reflect_period(self.vx * t, w), reflect_period(self.vy * t, h)
        m = np.array([[1, 0, dx], [0, 1, dy]])
        return warp(scene, m, cv2.BORDER_REFLECT)

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        v = np.empty((*shape, 2), np.float32)
        v[..., 0], v[..., 1] = self.vx, self.vy
        return v


@dataclass
class ObjectMotion(Motion):
    x: int
    y: int
    w: int
    h: int
    vx: float
    vy: float

    @property
    def spec(self) -> str:  # type: ignore[override]
        return f"object:{self.x},{self.y},{self.w},{self.h}:{self.vx:g},{self.vy:g}"

    @property
    def is_still(self) -> bool:
        return self.vx == 0 and self.vy == 0

    def _mask(self, shape: tuple[int, int]) -> np.ndarray:
        m = np.zeros(shape, np.float32)
        m[max(self.y, 0) : self.y + self.h, max(self.x, 0) : self.x + self.w] = 1.0
        return m

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        m = np.array([[1, 0, self.vx * t], [0, 1, self.vy * t]])
        obj = warp(scene, m, cv2.BORDER_CONSTANT)
        alpha = warp(self._mask(scene.shape[:2]), m, cv2.BORDER_CONSTANT)[..., None]
        return scene + alpha * (obj - scene)

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        v = np.zeros((*shape, 2), np.float32)
        m = self._mask(shape) > 0
        v[m, 0], v[m, 1] = self.vx, self.vy
        return v


@dataclass
class Rotate(Motion):
    deg_per_s: float
    cx: float | None = None
    cy: float | None = None

    @property
    def spec(self) -> str:  # type: ignore[override]
        c = "" if self.cx is None else f",{self.cx:g},{self.cy:g}"
        return f"rotate:{self.deg_per_s:g}{c}"

    @property
    def is_still(self) -> bool:
        return self.deg_per_s == 0

    def _centre(self, shape: tuple[int, int]) -> tuple[float, float]:
        h, w = shape
        return (
            w / 2 - 0.5 if self.cx is None else self.cx,
            h / 2 - 0.5 if self.cy is None else self.cy,
        )

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        cx, cy = self._centre(scene.shape[:2])
        # cv2 angles are counter-clockwise in a y-down image; ours are clockwise-positive.
        m = cv2.getRotationMatrix2D((cx, cy), -self.deg_per_s * t, 1.0)
        return warp(scene, m, cv2.BORDER_REFLECT)

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        cx, cy = self._centre(shape)
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
        w = math.radians(self.deg_per_s)
        return np.stack([-w * (yy - cy), w * (xx - cx)], axis=-1).astype(np.float32)


class DenseField(Motion):
    """A per-pixel velocity field, constant in time (``field:PATH``; module docstring)."""

    def __init__(self, path: str, field: np.ndarray):
        self.path = path
        self.field = np.ascontiguousarray(field, dtype=np.float32)
        self._cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    @property
    def spec(self) -> str:  # type: ignore[override]
        return f"field:{self.path}"

    @property
    def is_still(self) -> bool:
        return not np.any(self.field)

    def _on(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The field resampled to ``shape`` (H, W) and that grid's pixel coordinates."""
        hit = self._cache.get(shape)
        if hit is not None:
            return hit
        import cv2

        h, w = shape
        fh, fw = self.field.shape[:2]
        if abs((fw / fh) / (w / h) - 1.0) > 0.01:
            raise InputError(
                f"motion field {self.path}: {fw}x{fh} does not fit a {w}x{h} scene "
                "(another aspect ratio)"
            )
        field = self.field
        if (fh, fw) != (h, w):
            interp = cv2.INTER_AREA if w < fw else cv2.INTER_LINEAR
            field = cv2.resize(field, (w, h), interpolation=interp)
            field = field * np.array([w / fw, h / fh], np.float32)
        gy, gx = np.mgrid[0:h, 0:w].astype(np.float32)
        hit = (np.ascontiguousarray(field, dtype=np.float32), gx, gy)
        self._cache[shape] = hit
        return hit

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        field, gx, gy = self._on(scene.shape[:2])
        map_x = gx - field[..., 0] * np.float32(t)
        map_y = gy - field[..., 1] * np.float32(t)
        # Scenes have 1 or 3 channels: one remap call (OpenCV takes up to 4).
        out = cv2.remap(scene, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        return out.reshape(scene.shape)

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        return self._on(shape)[0].copy()
