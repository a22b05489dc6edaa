"""Motions along paths: rigid layers on the t = 0 grid (a label per pixel, layer 0 the
background), each moving along its own path, whose velocity may change within the frame
(Uda et al. 2016, Eq. 8: ``D(x, t)`` any function of time); the front layers occlude.

A layer's motion is an affine map per time, ``x(t) = A_k(t) x0 + b_k(t)`` (pixel
centres on integers, x right, y down): a translation for every kind but ``spin``, a
rotation about the rectangle's centre for ``spin``. :meth:`TrajectoryMotion.truth`
samples the maps for a capture's truth (:class:`stages.formats.capture.TruthPaths`).

Rectangles over the still rest (``object``, ``oscillate``, ``accel``, ``path``,
``spin``, and several of them joined by ``+``) are rendered as a print of the
rectangle's pixels at t = 0 moved over the picture: warped by the layer's map at ``t``
(bilinear), its edges anti-aliased by the warped rectangle's coverage, the later layers
in front; the area a rectangle uncovers shows the still scene beneath (the scene's own
pixels), as ``object:`` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..formats.capture import TruthPaths
from .models import Motion, reflect_period, warp

#: Shake's frequencies (Hz) and relative amplitudes per axis (hand tremor band).
SHAKE_HZ = (1.3, 2.9, 4.7)
SHAKE_WEIGHTS = (1.0, 0.6, 0.35)


class TrajectoryMotion(Motion):
    """Base of the layered motions with paths: subclasses give the label map and each
    layer's displacement ``offsets(t)``; one whose layers turn also gives ``maps``."""

    def labels(self, shape: tuple[int, int]) -> np.ndarray:
        """Layer of each pixel at t = 0, (H, W) int32 (0: background)."""
        raise NotImplementedError

    def offsets(self, t: np.ndarray) -> np.ndarray:
        """Each layer's displacement (of its anchor) at times ``t`` (M,): (K, M, 2) px."""
        raise NotImplementedError

    def anchors(self) -> np.ndarray:
        """The point of each layer that :meth:`offsets` follows, (K, 2) px (x, y)."""
        return np.zeros((len(self.offsets(np.zeros(1))), 2))

    def linear(self, t: np.ndarray) -> np.ndarray | None:
        """Each layer's linear part about its anchor at times ``t``, (K, M, 2, 2); None
        where every layer translates."""
        return None

    def front(self) -> list[int]:
        """The moving layers front to back (every layer but the background)."""
        return list(range(len(self.anchors()) - 1, 0, -1))

    def truth(self, shape: tuple[int, int], times: np.ndarray) -> TruthPaths:
        """The paths sampled at ``times`` (M,) s, with the label map of ``shape``."""
        t = np.asarray(times, np.float64)
        return TruthPaths(
            labels=self.labels(shape),
            times=t,
            disp=self.offsets(t),
            anchor=self.anchors(),
            linear=self.linear(t),
            front=self.front(),
        )

    def trajectory(
        self, shape: tuple[int, int], times: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(labels (H, W) int32, displacement (K, M, 2) px)`` at ``times`` (M,) s."""
        return self.labels(shape), self.offsets(np.asarray(times, np.float64))

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        """Velocity at t = 0 (H, W, 2) px/s (a central difference of the maps)."""
        dt = 1e-4
        paths = self.truth(shape, np.array([-dt, dt]))
        rate = (paths.maps()[:, 1] - paths.maps()[:, 0]) / (2 * dt)  # (K, 2, 3)
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
        m = rate[paths.labels]  # (H, W, 2, 3)
        v = m[..., 0] * xx[..., None] + m[..., 1] * yy[..., None] + m[..., 2]
        return v.astype(np.float32)

    @property
    def is_still(self) -> bool:
        return False


@dataclass
class Shake(TrajectoryMotion):
    amp: float
    seed: int = 0

    @property
    def spec(self) -> str:  # type: ignore[override]
        return f"shake:{self.amp:g},{self.seed}"

    @property
    def is_still(self) -> bool:
        return self.amp == 0

    def _path(self, t: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        phases = rng.uniform(0, 2 * math.pi, (2, len(SHAKE_HZ)))
        out = np.zeros((len(t), 2))
        for a in range(2):
            for f, wgt, ph in zip(SHAKE_HZ, SHAKE_WEIGHTS, phases[a], strict=True):
                out[:, a] += wgt * (np.sin(2 * math.pi * f * t + ph) - math.sin(ph))
        # Scale to the stated RMS distance from the start over one second.
        grid = np.linspace(0, 1, 201)
        ref = np.zeros((len(grid), 2))
        for a in range(2):
            for f, wgt, ph in zip(SHAKE_HZ, SHAKE_WEIGHTS, phases[a], strict=True):
                ref[:, a] += wgt * (np.sin(2 * math.pi * f * grid + ph) - math.sin(ph))
        rms = float(np.sqrt(np.mean(np.sum(ref**2, axis=1)))) or 1.0
        return out * (self.amp / rms)

    def labels(self, shape: tuple[int, int]) -> np.ndarray:
        return np.zeros(shape, np.int32)

    def offsets(self, t: np.ndarray) -> np.ndarray:
        return self._path(np.atleast_1d(t))[None]

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        h, w = scene.shape[:2]
        dx, dy = self._path(np.array([t]))[0]
        m = np.array([[1, 0, reflect_period(dx, w)], [0, 1, reflect_period(dy, h)]])
        return warp(scene, m, cv2.BORDER_REFLECT)


@dataclass
class Oscillate(TrajectoryMotion):
    x: int
    y: int
    w: int
    h: int
    ax: float
    ay: float
    hz: float = 1.0

    @property
    def spec(self) -> str:  # type: ignore[override]
        return f"oscillate:{self.x},{self.y},{self.w},{self.h}:{self.ax:g},{self.ay:g},{self.hz:g}"

    @property
    def is_still(self) -> bool:
        return (self.ax == 0 and self.ay == 0) or self.hz == 0

    def labels(self, shape: tuple[int, int]) -> np.ndarray:
        m = np.zeros(shape, np.int32)
        m[max(self.y, 0) : self.y + self.h, max(self.x, 0) : self.x + self.w] = 1
        return m

    def offsets(self, t: np.ndarray) -> np.ndarray:
        s = np.sin(2 * math.pi * self.hz * np.atleast_1d(t))
        out = np.zeros((2, len(s), 2))
        out[1, :, 0] = self.ax * s
        out[1, :, 1] = self.ay * s
        return out

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        dx, dy = self.offsets(np.array([t]))[1, 0]
        m = np.array([[1, 0, dx], [0, 1, dy]])
        obj = warp(scene, m, cv2.BORDER_CONSTANT)
        mask = self.labels(scene.shape[:2]).astype(np.float32)
        alpha = warp(mask, m, cv2.BORDER_CONSTANT)[..., None]
        return scene + alpha * (obj - scene)


# --- rectangles along paths, alone or several ---------------------------------------


@dataclass
class Sprite:
    """A rectangle ``[x, x + w) x [y, y + h)`` of the scene at t = 0 moving over the
    rest along a path: subclasses give :meth:`offsets` (of its centre) and, when it
    turns, :meth:`angles`."""

    x: int
    y: int
    w: int
    h: int

    kind = "object"

    @property
    def rect(self) -> str:
        return f"{self.x},{self.y},{self.w},{self.h}"

    @property
    def centre(self) -> tuple[float, float]:
        """The rectangle's centre, pixel centres on integers."""
        return self.x + (self.w - 1) / 2, self.y + (self.h - 1) / 2

    def offsets(self, t: np.ndarray) -> np.ndarray:
        """Displacement of the centre at times ``t`` (M,): (M, 2) px."""
        raise NotImplementedError

    def angles(self, t: np.ndarray) -> np.ndarray | None:
        """Clockwise turn about the centre at times ``t`` (M,), radians; None: none."""
        return None

    @property
    def is_still(self) -> bool:
        return False


@dataclass
class Glide(Sprite):
    """``object:X,Y,W,H:VX,VY``: constant velocity, px/s."""

    vx: float = 0.0
    vy: float = 0.0

    @property
    def spec(self) -> str:
        return f"object:{self.rect}:{self.vx:g},{self.vy:g}"

    def offsets(self, t: np.ndarray) -> np.ndarray:
        return np.stack([self.vx * t, self.vy * t], axis=-1)

    @property
    def is_still(self) -> bool:
        return self.vx == 0 and self.vy == 0


@dataclass
class Swing(Sprite):
    """``oscillate:X,Y,W,H:AX,AY[,HZ]``: ``D(t) = (AX, AY) sin(2 pi HZ t)``."""

    ax: float = 0.0
    ay: float = 0.0
    hz: float = 1.0

    @property
    def spec(self) -> str:
        return f"oscillate:{self.rect}:{self.ax:g},{self.ay:g},{self.hz:g}"

    def offsets(self, t: np.ndarray) -> np.ndarray:
        s = np.sin(2 * math.pi * self.hz * t)
        return np.stack([self.ax * s, self.ay * s], axis=-1)

    @property
    def is_still(self) -> bool:
        return (self.ax == 0 and self.ay == 0) or self.hz == 0


@dataclass
class Accelerate(Sprite):
    """``accel:X,Y,W,H:VX,VY:AX,AY``: ``D(t) = v t + a t^2 / 2`` (px/s, px/s^2)."""

    vx: float = 0.0
    vy: float = 0.0
    ax: float = 0.0
    ay: float = 0.0

    @property
    def spec(self) -> str:
        return f"accel:{self.rect}:{self.vx:g},{self.vy:g}:{self.ax:g},{self.ay:g}"

    def offsets(self, t: np.ndarray) -> np.ndarray:
        return np.stack(
            [self.vx * t + self.ax * t * t / 2, self.vy * t + self.ay * t * t / 2], axis=-1
        )

    @property
    def is_still(self) -> bool:
        return not any((self.vx, self.vy, self.ax, self.ay))


@dataclass
class Keyframes(Sprite):
    """``path:X,Y,W,H:T1,DX1,DY1;T2,DX2,DY2;...``: the displacement through (0, 0) at
    t = 0 and each keyframe (seconds increasing, px), a cubic spline with zero
    acceleration at its ends (scipy's natural ``CubicSpline``), held at the last
    keyframe's after it."""

    keys: tuple[tuple[float, float, float], ...] = field(default_factory=tuple)

    @property
    def spec(self) -> str:
        return f"path:{self.rect}:" + ";".join(f"{t:g},{dx:g},{dy:g}" for t, dx, dy in self.keys)

    def offsets(self, t: np.ndarray) -> np.ndarray:
        from scipy.interpolate import CubicSpline

        k = np.array([(0.0, 0.0, 0.0), *self.keys])
        spline = CubicSpline(k[:, 0], k[:, 1:], bc_type="natural")
        return spline(np.clip(t, 0.0, k[-1, 0]))

    @property
    def is_still(self) -> bool:
        return all(dx == 0 and dy == 0 for _, dx, dy in self.keys)


@dataclass
class Spin(Sprite):
    """``spin:X,Y,W,H:DEG_PER_S``: the rectangle turns about its centre, clockwise-positive
    in the y-down image (as ``rotate:``), its centre still."""

    deg_per_s: float = 0.0

    @property
    def spec(self) -> str:
        return f"spin:{self.rect}:{self.deg_per_s:g}"

    def offsets(self, t: np.ndarray) -> np.ndarray:
        return np.zeros((len(t), 2))

    def angles(self, t: np.ndarray) -> np.ndarray:
        return np.radians(self.deg_per_s) * t

    @property
    def is_still(self) -> bool:
        return self.deg_per_s == 0


@dataclass
class Sprites(TrajectoryMotion):
    """Rectangles over the still rest (layer k + 1 is ``sprites[k]``), each along its own
    path, the later ones in front (module docstring); ``A+B`` in a motion SPEC."""

    sprites: list[Sprite]

    @property
    def spec(self) -> str:  # type: ignore[override]
        return "+".join(s.spec for s in self.sprites)

    @property
    def is_still(self) -> bool:
        return all(s.is_still for s in self.sprites)

    def labels(self, shape: tuple[int, int]) -> np.ndarray:
        m = np.zeros(shape, np.int32)
        for k, s in enumerate(self.sprites, 1):  # (the later in front where they overlap)
            m[max(s.y, 0) : s.y + s.h, max(s.x, 0) : s.x + s.w] = k
        return m

    def anchors(self) -> np.ndarray:
        return np.array([(0.0, 0.0)] + [s.centre for s in self.sprites])

    def offsets(self, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, np.float64))
        return np.stack([np.zeros((len(t), 2))] + [s.offsets(t) for s in self.sprites])

    def linear(self, t: np.ndarray) -> np.ndarray | None:
        t = np.atleast_1d(np.asarray(t, np.float64))
        if all(s.angles(t) is None for s in self.sprites):
            return None
        out = np.zeros((len(self.sprites) + 1, len(t), 2, 2))
        out[..., 0, 0] = out[..., 1, 1] = 1.0
        for k, s in enumerate(self.sprites, 1):
            a = s.angles(t)
            if a is not None:  # (clockwise in the y-down image)
                c, sn = np.cos(a), np.sin(a)
                out[k, :, 0, 0], out[k, :, 0, 1] = c, -sn
                out[k, :, 1, 0], out[k, :, 1, 1] = sn, c
        return out

    def render(self, scene: np.ndarray, t: float) -> np.ndarray:
        import cv2

        if self.is_still:
            return scene
        shape = scene.shape[:2]
        maps = self.truth(shape, np.array([t])).maps()[:, 0]  # (K, 2, 3)
        labels = self.labels(shape)
        out = scene
        for k in range(1, len(maps)):  # back to front
            mask = (labels == k).astype(np.float32)
            layer = warp(scene, maps[k], cv2.BORDER_CONSTANT)
            alpha = warp(mask, maps[k], cv2.BORDER_CONSTANT)[..., None]
            out = out + alpha * (layer - out)
        return out
