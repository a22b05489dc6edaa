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
``field:PATH``
    A dense velocity field from a motion file (``kind: motion``, layer ``motion`` with
    channels ``u, v`` in px/s, as ``vet deblur --motion-out`` writes), constant in time:
    ``D(x, t) = v(x) t``, the model deblur reconstructs with. The image at ``t`` is pulled
    back along the field, so there is no occlusion: where two paths meet, both show. A
    field of another size with the scene's aspect ratio is resampled to the scene, its
    velocities scaled with it (so ``--size`` works); another aspect ratio is an error.

Motions whose velocity changes within the frame (Uda et al. 2016, Eq. 8: ``D(x, t)``
any function of time) are rigid layers on the t = 0 grid (a label per pixel, layer 0
the background) each moving along its own path ``D_k(t)`` (``D_k(0) = 0``); the front
layer occludes. :meth:`TrajectoryMotion.trajectory` samples the paths for a capture's
truth (``truth_trajectory`` and the ``truth_layers`` layer of a capture file):

``shake:AMP[,SEED]``
    Camera shake: the whole image follows a smooth random path, a sum of three sinusoids
    per axis (1.3, 2.9 and 4.7 Hz, seeded phases) scaled so that the path's RMS distance
    from its start over one second is ``AMP`` pixels.
``oscillate:X,Y,W,H:AX,AY[,HZ]``
    The rectangle ``[X, X+W) x [Y, Y+H)`` swings over the still rest,
    ``D(t) = (AX, AY) sin(2 pi HZ t)`` (HZ default 1: one swing per second), occluding
    it as ``object:`` does: its velocity reverses within the frame.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError, UsageError

log = logging.getLogger(__name__)


def _warp(img: np.ndarray, m: np.ndarray, border: int) -> np.ndarray:
    import cv2

    h, w = img.shape[:2]
    out = cv2.warpAffine(
        img, m.astype(np.float64), (w, h), flags=cv2.INTER_LINEAR, borderMode=border
    )
    if out.ndim == 2 and img.ndim == 3:
        out = out[:, :, None]
    return out


def _reflect_period(shift: float, size: int) -> float:
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
        dx, dy = _reflect_period(self.vx * t, w), _reflect_period(self.vy * t, h)
        m = np.array([[1, 0, dx], [0, 1, dy]])
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


#: Shake's frequencies (Hz) and relative amplitudes per axis (hand tremor band).
SHAKE_HZ = (1.3, 2.9, 4.7)
SHAKE_WEIGHTS = (1.0, 0.6, 0.35)


class TrajectoryMotion(Motion):
    """Base of the layered motions with paths: subclasses give the label map and the
    moving layer's displacement ``offset(t) -> (dx, dy)``."""

    def labels(self, shape: tuple[int, int]) -> np.ndarray:
        """Layer of each pixel at t = 0, (H, W) int32 (0: background)."""
        raise NotImplementedError

    def offsets(self, t: np.ndarray) -> np.ndarray:
        """Each layer's displacement at times ``t`` (M,): (K, M, 2) px."""
        raise NotImplementedError

    def trajectory(
        self, shape: tuple[int, int], times: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(labels (H, W) int32, displacement (K, M, 2) px)`` at ``times`` (M,) s."""
        return self.labels(shape), self.offsets(np.asarray(times, np.float64))

    def velocity(self, shape: tuple[int, int]) -> np.ndarray:
        """Velocity at t = 0 (H, W, 2) px/s (a central difference of the paths)."""
        dt = 1e-4
        v = (self.offsets(np.array([dt]))[:, 0] - self.offsets(np.array([-dt]))[:, 0]) / (2 * dt)
        return v[self.labels(shape)].astype(np.float32)

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
        m = np.array([[1, 0, _reflect_period(dx, w)], [0, 1, _reflect_period(dy, h)]])
        return _warp(scene, m, cv2.BORDER_REFLECT)


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
        obj = _warp(scene, m, cv2.BORDER_CONSTANT)
        mask = self.labels(scene.shape[:2]).astype(np.float32)
        alpha = _warp(mask, m, cv2.BORDER_CONSTANT)[..., None]
        return scene + alpha * (obj - scene)


def check_in_frame(motion: Motion, shape: tuple[int, int]) -> None:
    """Check an ``object:`` or ``oscillate:`` rectangle against the frame it moves in.

    Parameters
    ----------
    motion : Motion
        Any motion; only :class:`ObjectMotion` and :class:`Oscillate` have a rectangle.
    shape : tuple of int
        ``(H, W)`` of the scene at the size used, pixels.

    A rectangle partly outside the frame is usable (its part inside moves) but likely
    given for another size: a warning on the log. One wholly outside moves nothing.

    Raises
    ------
    UsageError
        The rectangle lies wholly outside the frame.
    """
    if not isinstance(motion, (ObjectMotion, Oscillate)):
        return
    h, w = shape
    x0, y0, x1, y1 = motion.x, motion.y, motion.x + motion.w, motion.y + motion.h
    rect = f"X,Y,W,H = {motion.x},{motion.y},{motion.w},{motion.h}"
    if x0 >= w or y0 >= h or x1 <= 0 or y1 <= 0:
        raise UsageError(
            f"invalid motion {motion.spec!r}: its rectangle ({rect}) lies wholly outside the "
            f"{w}x{h} frame, so nothing would move; give one that overlaps the frame "
            f"(x 0..{w - 1}, y 0..{h - 1}: pixels of the scene at the size used)",
            option="--motion",
        )
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        log.warning(
            "motion %s: its rectangle (%s) lies partly outside the %dx%d frame; "
            "only the part inside moves (rectangles are in pixels at the size used)",
            motion.spec,
            rect,
            w,
            h,
        )


def trajectory_times(frame_s: float, subframe_s: float, n_subframes: int) -> np.ndarray:
    """The times a capture's true trajectory is sampled at: 0, each subframe's mid-time
    (where the simulator renders), and the frame's end, seconds."""
    mids = (np.arange(n_subframes) + 0.5) * subframe_s
    return np.concatenate([[0.0], mids, [frame_s]])


def load_motion_field(path: str) -> DenseField:
    """Read a motion file (``kind: motion``) as a :class:`DenseField`; InputError if it
    is not one or holds non-finite velocities."""
    from .formats.layered import read_layered

    what = "standard input" if path == "-" else path
    data = read_layered(path)
    kind = data.meta.get("kind")
    if kind != "motion" or "motion" not in data.layers:
        raise InputError(
            f"{what}: not a motion field (kind {kind!r}; expected a file written by "
            "vet deblur --motion-out)"
        )
    chans = data.channels["motion"]
    if sorted(chans) != ["u", "v"]:
        raise InputError(f"{what}: motion layer has channels {chans}, expected u, v")
    layer = data.layers["motion"]
    field = np.stack([layer[..., chans.index("u")], layer[..., chans.index("v")]], axis=-1)
    if not np.isfinite(field).all():
        raise InputError(f"{what}: the motion field holds non-finite velocities")
    return DenseField(path, field)


#: The valid form of each motion SPEC kind, for messages.
FORMS = {
    "translate": "translate:VX,VY",
    "object": "object:X,Y,W,H:VX,VY",
    "rotate": "rotate:DEG_PER_S[,CX,CY]",
    "shake": "shake:AMP[,SEED]",
    "oscillate": "oscillate:X,Y,W,H:AX,AY[,HZ]",
}


def _floats(text: str, n: int, spec: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        form = FORMS.get(spec.partition(":")[0])
        raise InputError(
            f"invalid motion {spec!r}: expected {n} comma-separated numbers in {text!r}"
            + (f"; use {form}" if form else "")
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
        rect, sep, vel = rest.partition(":")
        x, y, w, h = _floats(rect, 4, spec)
        if not sep or not vel.strip():
            raise InputError(
                f"invalid motion {spec!r}: the velocity part is missing; "
                "use object:X,Y,W,H:VX,VY (e.g. object:80,64,160,128:40,0)"
            )
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
    if kind == "shake":
        parts = rest.split(",")
        amp, seed = _floats(rest, 2, spec) if len(parts) == 2 else (_floats(rest, 1, spec)[0], 0)
        if amp < 0 or seed != int(seed) or seed < 0:
            raise InputError(
                f"invalid motion {spec!r}: the amplitude must be >= 0 and the seed a whole number"
            )
        return Shake(amp, int(seed))
    if kind == "oscillate":
        rect, sep, amp = rest.partition(":")
        x, y, w, h = _floats(rect, 4, spec)
        parts = amp.split(",")
        vals = _floats(amp, 3, spec) if len(parts) == 3 else [*_floats(amp, 2, spec), 1.0]
        if not sep or w <= 0 or h <= 0 or vals[2] < 0:
            raise InputError(
                f"invalid motion {spec!r}: use oscillate:X,Y,W,H:AX,AY[,HZ] with a positive "
                "width and height and HZ >= 0"
            )
        return Oscillate(int(x), int(y), int(w), int(h), *vals)
    if kind == "field":
        if not rest:
            raise InputError(f"invalid motion {spec!r}: field:PATH needs a motion file")
        return load_motion_field(rest)
    raise InputError(
        f"invalid motion {spec!r}: use none, translate:VX,VY, object:X,Y,W,H:VX,VY,"
        " rotate:DEG_PER_S[,CX,CY], shake:AMP[,SEED], oscillate:X,Y,W,H:AX,AY[,HZ]"
        " or field:PATH"
    )
