"""Motion models: how the scene moves during a frame, for rendering and as ground truth.

Convention (DESIGN.md §1): the image at time ``t`` is ``L(x, t) = L0(x - D(x, t))``: content
moves by ``+D``. Velocities are in pixels per second; ``t = 0`` is the frame start.

Specs
-----
``none``
    A still scene.
``translate:VX,VY``
    The whole scene moves ``(VX, VY)`` pixels per second.
``object:X,Y,W,H:VX,VY``
    The rectangle ``[X, X+W) x [Y, Y+H)`` of the scene (at t = 0) moves over the still
    rest, occluding it; the area it uncovers shows the still scene beneath (the scene's
    own pixels, like sliding a print of that region over the picture).
``rotate:DEG_PER_S[,CX,CY]``
    The scene rotates about ``(CX, CY)`` (default: the centre), degrees per second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError


def _warp(img: np.ndarray, m: np.ndarray, border: int) -> np.ndarray:
    import cv2

    h, w = img.shape[:2]
    out = cv2.warpAffine(
        img, m.astype(np.float64), (w, h), flags=cv2.INTER_LINEAR, borderMode=border
    )
    if out.ndim == 2 and img.ndim == 3:
        out = out[:, :, None]
    return out


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
        m = np.array([[1, 0, self.vx * t], [0, 1, self.vy * t]])
        return _warp(scene, m, cv2.BORDER_REFLECT)

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
        obj = _warp(scene, m, cv2.BORDER_CONSTANT)
        alpha = _warp(self._mask(scene.shape[:2]), m, cv2.BORDER_CONSTANT)[..., None]
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
        return _warp(scene, m, cv2.BORDER_REFLECT)

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        cx, cy = self._centre(shape)
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
        w = math.radians(self.deg_per_s)
        return np.stack([-w * (yy - cy), w * (xx - cx)], axis=-1).astype(np.float32)


def _floats(text: str, n: int, spec: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise InputError(
            f"invalid motion {spec!r}: expected {n} comma-separated numbers in {text!r}"
        )
    return vals


def parse_motion(spec: str | None) -> Motion:
    """Parse a motion SPEC (see the module docstring); raise InputError with the grammar."""
    if spec is None or spec.strip() in ("", "none"):
        return NoMotion()
    spec = spec.strip()
    kind, _, rest = spec.partition(":")
    if kind == "translate":
        vx, vy = _floats(rest, 2, spec)
        return Translate(vx, vy)
    if kind == "object":
        rect, _, vel = rest.partition(":")
        x, y, w, h = _floats(rect, 4, spec)
        vx, vy = _floats(vel, 2, spec)
        if w <= 0 or h <= 0:
            raise InputError(
                f"invalid motion {spec!r}: the rectangle needs positive width and height"
            )
        return ObjectMotion(int(x), int(y), int(w), int(h), vx, vy)
    if kind == "rotate":
        parts = rest.split(",")
        if len(parts) == 1:
            return Rotate(_floats(rest, 1, spec)[0])
        d, cx, cy = _floats(rest, 3, spec)
        return Rotate(d, cx, cy)
    raise InputError(
        f"invalid motion {spec!r}: use none, translate:VX,VY, object:X,Y,W,H:VX,VY or rotate:DEG_PER_S[,CX,CY]"
    )
