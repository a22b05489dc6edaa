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
the background) each moving along its own path (:mod:`stages.motion.paths`: an affine
map per time, ``D_k(0) = 0``); the front layers occlude.
:meth:`~stages.motion.paths.TrajectoryMotion.truth` samples the paths for a capture's
truth (``truth_trajectory`` and the ``truth_layers`` layer of a capture file,
:class:`stages.formats.capture.TruthPaths`):

``shake:AMP[,SEED]``
    Camera shake: the whole image follows a smooth random path, a sum of three sinusoids
    per axis (1.3, 2.9 and 4.7 Hz, seeded phases) scaled so that the path's RMS distance
    from its start over one second is ``AMP`` pixels.
``oscillate:X,Y,W,H:AX,AY[,HZ]``
    The rectangle ``[X, X+W) x [Y, Y+H)`` swings over the still rest,
    ``D(t) = (AX, AY) sin(2 pi HZ t)`` (HZ default 1: one swing per second), occluding
    it as ``object:`` does: its velocity reverses within the frame.
``accel:X,Y,W,H:VX,VY:AX,AY``
    The rectangle moves from rest at t = 0 with velocity ``(VX, VY)`` px/s and constant
    acceleration ``(AX, AY)`` px/s^2: ``D(t) = v t + a t^2 / 2`` (a car braking: ``a``
    against ``v``).
``path:X,Y,W,H:T1,DX1,DY1;T2,DX2,DY2;...``
    The rectangle follows keyframes: displacement ``(DXi, DYi)`` px at ``Ti`` s (times
    increasing, after 0), a smooth path through (0, 0) at t = 0 and the keyframes (a
    natural cubic spline), held at the last keyframe after it.
``spin:X,Y,W,H:DEG_PER_S``
    The rectangle turns about its centre over the still rest, degrees per second,
    clockwise-positive as ``rotate:`` (a fan, a wheel): its displacement differs from
    pixel to pixel, so its truth carries a rotation per time (``linear``).
``A+B[+...]``
    Several rectangles, each of ``object``, ``oscillate``, ``accel``, ``path`` or
    ``spin``, each along its own path over the still rest; a later one passes in front
    of an earlier one. E.g. ``object:20,20,60,40:30,0+oscillate:150,100,50,50:0,10,2``.
"""

from __future__ import annotations

import logging
import math
import re

import numpy as np

from ..errors import InputError, UsageError
from .models import DenseField, Motion, NoMotion, ObjectMotion, Rotate, Translate
from .paths import (
    Accelerate,
    Glide,
    Keyframes,
    Oscillate,
    Shake,
    Spin,
    Sprite,
    Sprites,
    Swing,
    TrajectoryMotion,
)

__all__ = [
    "DenseField",
    "Motion",
    "NoMotion",
    "ObjectMotion",
    "Oscillate",
    "Rotate",
    "Shake",
    "Sprites",
    "TrajectoryMotion",
    "Translate",
    "check_in_frame",
    "load_motion_field",
    "parse_motion",
    "trajectory_times",
]

log = logging.getLogger(__name__)


def check_in_frame(motion: Motion, shape: tuple[int, int]) -> None:
    """Check a motion's rectangles against the frame they move in.

    Parameters
    ----------
    motion : Motion
        Any motion; the rectangles are those of ``object:``, ``oscillate:`` and of
        :class:`Sprites` (each checked).
    shape : tuple of int
        ``(H, W)`` of the scene at the size used, pixels.

    A rectangle partly outside the frame is usable (its part inside moves) but likely
    given for another size: a warning on the log. One wholly outside moves nothing.

    Raises
    ------
    UsageError
        The rectangle lies wholly outside the frame.
    """
    if isinstance(motion, Sprites):
        for sprite in motion.sprites:
            _check_rect(sprite, motion.spec, shape)
    elif isinstance(motion, (ObjectMotion, Oscillate)):
        _check_rect(motion, motion.spec, shape)


def _check_rect(r: ObjectMotion | Oscillate | Sprite, spec: str, shape: tuple[int, int]) -> None:
    h, w = shape
    x0, y0, x1, y1 = r.x, r.y, r.x + r.w, r.y + r.h
    rect = f"X,Y,W,H = {r.x},{r.y},{r.w},{r.h}"
    if x0 >= w or y0 >= h or x1 <= 0 or y1 <= 0:
        raise UsageError(
            f"invalid motion {spec!r}: its rectangle ({rect}) lies wholly outside the "
            f"{w}x{h} frame, so nothing would move; give one that overlaps the frame "
            f"(x 0..{w - 1}, y 0..{h - 1}: pixels of the scene at the size used)",
            option="--motion",
        )
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        log.warning(
            "motion %s: its rectangle (%s) lies partly outside the %dx%d frame; "
            "only the part inside moves (rectangles are in pixels at the size used)",
            spec,
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
    from ..formats.layered import read_layered

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
    "accel": "accel:X,Y,W,H:VX,VY:AX,AY",
    "path": "path:X,Y,W,H:T1,DX1,DY1;T2,DX2,DY2;...",
    "spin": "spin:X,Y,W,H:DEG_PER_S",
}
#: The kinds that name a rectangle and so join with ``+``.
RECTANGLES = ("object", "oscillate", "accel", "path", "spin")


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


def _rect(rest: str, spec: str, parts: int) -> tuple[list[int], list[str]]:
    """``X,Y,W,H`` and the ``parts`` fields after it of a rectangle kind's SPEC."""
    fields = rest.split(":")
    kind = spec.partition(":")[0]
    if len(fields) != 1 + parts or not all(f.strip() for f in fields):
        raise InputError(f"invalid motion {spec!r}: use {FORMS[kind]}")
    x, y, w, h = _floats(fields[0], 4, spec)
    if w <= 0 or h <= 0:
        raise InputError(f"invalid motion {spec!r}: the rectangle needs positive width and height")
    return [int(x), int(y), int(w), int(h)], fields[1:]


def _keyframes(text: str, spec: str) -> tuple[tuple[float, float, float], ...]:
    keys = tuple(tuple(_floats(k, 3, spec)) for k in text.split(";"))
    times = [0.0] + [k[0] for k in keys]
    if any(b <= a for a, b in zip(times, times[1:], strict=False)):
        raise InputError(
            f"invalid motion {spec!r}: keyframe times must increase after 0 s; use {FORMS['path']}"
        )
    return keys  # type: ignore[return-value]


def _sprite(spec: str) -> Sprite:
    """One rectangle kind's SPEC as a :class:`Sprite`."""
    kind, _, rest = spec.partition(":")
    if kind == "object":
        r, (vel,) = _rect(rest, spec, 1)
        return Glide(*r, *_floats(vel, 2, spec))
    if kind == "oscillate":
        o = _oscillate(rest, spec)
        return Swing(o.x, o.y, o.w, o.h, o.ax, o.ay, o.hz)
    if kind == "accel":
        r, (vel, acc) = _rect(rest, spec, 2)
        return Accelerate(*r, *_floats(vel, 2, spec), *_floats(acc, 2, spec))
    if kind == "path":
        r, (keys,) = _rect(rest, spec, 1)
        return Keyframes(*r, keys=_keyframes(keys, spec))
    if kind == "spin":
        r, (rate,) = _rect(rest, spec, 1)
        return Spin(*r, _floats(rate, 1, spec)[0])
    raise InputError(
        f"invalid motion {spec!r}: only rectangles ({', '.join(RECTANGLES)}) join with +"
    )


def _oscillate(rest: str, spec: str) -> Oscillate:
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


def _object(rest: str, spec: str) -> ObjectMotion:
    rect, sep, vel = rest.partition(":")
    x, y, w, h = _floats(rect, 4, spec)
    if not sep or not vel.strip():
        raise InputError(
            f"invalid motion {spec!r}: the velocity part is missing; "
            "use object:X,Y,W,H:VX,VY (e.g. object:80,64,160,128:40,0)"
        )
    vx, vy = _floats(vel, 2, spec)
    if w <= 0 or h <= 0:
        raise InputError(f"invalid motion {spec!r}: the rectangle needs positive width and height")
    return ObjectMotion(int(x), int(y), int(w), int(h), vx, vy)


def _rotate(rest: str, spec: str) -> Rotate:
    if len(rest.split(",")) == 1:
        return Rotate(_floats(rest, 1, spec)[0])
    d, cx, cy = _floats(rest, 3, spec)
    return Rotate(d, cx, cy)


def _shake(rest: str, spec: str) -> Shake:
    parts = rest.split(",")
    amp, seed = _floats(rest, 2, spec) if len(parts) == 2 else (_floats(rest, 1, spec)[0], 0)
    if amp < 0 or seed != int(seed) or seed < 0:
        raise InputError(
            f"invalid motion {spec!r}: the amplitude must be >= 0 and the seed a whole number"
        )
    return Shake(amp, int(seed))


def _field(rest: str, spec: str) -> DenseField:
    if not rest:
        raise InputError(f"invalid motion {spec!r}: field:PATH needs a motion file")
    return load_motion_field(rest)


_SINGLE = {
    "translate": lambda rest, spec: Translate(*_floats(rest, 2, spec)),
    "object": _object,
    "rotate": _rotate,
    "shake": _shake,
    "oscillate": _oscillate,
    "field": _field,
}


def parse_motion(spec: str | None) -> Motion:
    """Parse a motion SPEC (see the module docstring); raise InputError with the grammar."""
    if spec is None or spec.strip() in ("", "none"):
        return NoMotion()
    spec = spec.strip()
    kind, _, rest = spec.partition(":")
    parts = re.split(r"\+(?=\s*[a-z]+:)", spec) if kind != "field" else [spec]
    if len(parts) > 1:
        return Sprites([_sprite(part.strip()) for part in parts])
    if kind in _SINGLE:
        return _SINGLE[kind](rest, spec)
    if kind in RECTANGLES:
        return Sprites([_sprite(spec)])
    raise InputError(
        f"invalid motion {spec!r}: use none, " + ", ".join(FORMS.values()) + ", field:PATH,"
        " or rectangles joined by +"
    )
