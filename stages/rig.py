"""Rig parameters: every number that describes a VET rig, with the defaults of DESIGN.md §2.

A :class:`RigParams` travels inside every capture's metadata so that each later stage
reconstructs with exactly the physics that made the data.

One schema. The fields of :class:`RigParams` are the one table of the rig's numbers: each
names its type, its allowed range (pydantic ``Field`` bounds) and its default once.
:data:`RIG_MODEL` is the pydantic model built from that table, with the relations between
fields (:func:`check_relations`: a subframe within the frame, homographies finite,
invertible and onto the sensor, a measurement camera that sees the VET frame, ...). It
checks every rig: one made in code (``RigParams(...)`` raises :class:`InputError`) and one
read from a file (:mod:`stages.formats.schema` validates files' ``rig`` with it, where
types are strict: a string is never a number, a bool never an int).
"""

import dataclasses
import math
import re
import typing
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, model_validator

from .errors import InputError

#: Most subframes one frame may hold (``frame_s / subframe_s``): bounds the work and
#: memory of every stage that walks the subframes.
MAX_SUBFRAMES = 100_000
#: Largest sensor side (pixels) and LCoS side (cells) accepted.
MAX_SENSOR_SIDE = 65536
MAX_LCOS_SIDE = 16384
#: Most measuring subframes a rig may drop, as a probability: a link that loses more
#: than half its frames leaves too few to threshold on.
MAX_DROP_RATE = 0.5
#: How far (in sensor sizes) beyond the sensor a homography may put a corner of the LCoS
#: or of the measurement camera: farther is no optics, but a number gone wrong.
MAX_REACH_SIZES = 10
#: Largest condition number of a homography (a finite, invertible, sane one).
MAX_CONDITION = 1e12
#: Least share of the VET sensor the measurement camera must image.
MIN_MEASURE_COVER = 0.5
#: Most VET pixels (along a side) one measuring pixel may span.
MAX_MEASURE_PIXEL_PX = 8.0


def _real(
    lo: float | None = None,
    hi: float | None = None,
    *,
    above: float | None = None,
    below: float | None = None,
) -> Any:
    """A finite float field, ``lo <= v <= hi`` (``above < v``, ``v < below``)."""
    return Annotated[
        float, Field(strict=True, allow_inf_nan=False, ge=lo, le=hi, gt=above, lt=below)
    ]


def _whole(lo: int, hi: int) -> Any:
    """An int field, ``lo <= v <= hi`` (never a bool, never a float)."""
    return Annotated[int, Field(strict=True, ge=lo, le=hi)]


_SensorSide = _whole(1, MAX_SENSOR_SIDE)
_LcosSide = _whole(1, MAX_LCOS_SIDE)
_Row3 = Annotated[list[_real()], Field(min_length=3, max_length=3)]
#: A 3x3 matrix, or empty for the default.
_Matrix3 = Annotated[list[_Row3], Field(max_length=3)]
#: (width, height), or empty for the default.
_SizeOrNone = Annotated[tuple[_SensorSide, ...], Field(max_length=2)]


def default_homography(
    lcos_cells: tuple[int, int], sensor_size: tuple[int, int]
) -> list[list[float]]:
    """Homography mapping LCoS cell coordinates onto sensor pixel coordinates.

    The default rig images the whole LCoS onto the whole sensor (a pure scale): cell
    centre ``(i + 0.5)`` lands on pixel coordinate ``(i + 0.5) * sensor / cells``.
    Coordinates are continuous with pixel ``(0, 0)`` covering ``[0, 1) x [0, 1)``.
    """
    sx = sensor_size[0] / lcos_cells[0]
    sy = sensor_size[1] / lcos_cells[1]
    return [[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]]


#: The fields of the parts of a real rig (:mod:`stages.optics`), ideal by default.
REAL_RIG_PARTS = (
    "measure_size",
    "measure_homography",
    "measure_k1",
    "measure_k2",
    "measure_gain",
    "measure_vignetting",
    "relay_blur_px",
    "leakage_spread",
    "leakage_seed",
    "switch_s",
    "trigger_offset_s",
    "trigger_jitter_s",
    "drop_rate",
)


@dataclass
class RigParams:
    """Physical parameters of a VET rig (units in the names; times in seconds).

    Attributes
    ----------
    frame_s : float
        Length of the VET sensor's frame Tf.
    subframe_s : float
        Length of one measuring subframe tau.
    full_well_e : float
        Full-well capacity of both sensors, electrons.
    read_noise_e : float
        Read noise, electrons rms per read.
    adc_bits : int
        ADC depth; full well maps to ``2**adc_bits - 1`` DN.
    dark_current_e_s : float
        Dark current, electrons per second.
    threshold_frac : float
        Closure threshold theta as a fraction of the full well.
    latency_subframes : int
        Subframes between the end of the subframe whose sum crossed theta and the
        moment the LCoS cell closes.
    leakage : float
        Transmittance of a closed LCoS cell (0 = perfect shutter).
    lcos_cells : (int, int)
        LCoS grid, (width, height) in cells.
    sensor_size : (int, int)
        VET sensor, (width, height) in pixels.
    measure_fraction : float
        Light on the measurement sensor relative to the VET sensor (1.0 for a 50/50
        splitter and identical sensors).
    homography : 3x3 list
        LCoS cell coordinates -> VET sensor pixel coordinates.
    black_level_dn : float
        ADC pedestal. Recorded DN are black-level subtracted (as raw pipelines deliver
        them), so read noise on dark pixels keeps its sign down to ``-black_level_dn``
        instead of clipping at zero, which would bias dark sums upwards.

    The parts of a real rig (:mod:`stages.optics` models them; every default is the
    ideal rig, where they vanish):

    measure_size : (int, int) or ()
        Measurement camera, (width, height) in pixels; empty: the VET sensor's size.
    measure_homography : 3x3 list or []
        Measurement camera pixel coordinates (undistorted) -> VET sensor pixel
        coordinates; empty: the identity.
    measure_k1, measure_k2 : float
        Radial distortion of the measurement camera about its image centre, in units of
        its half-diagonal: an undistorted point at radius r is recorded at
        ``r (1 + k1 r**2 + k2 r**4)``.
    measure_gain : float
        The measurement camera's conversion gain relative to the VET sensor's (DN per
        electron, as a factor).
    measure_vignetting : float
        Light falloff of the measurement camera: ``(1 + a r**2) ** -2`` (cos^4-like) at
        radius r in half-diagonals.
    relay_blur_px : float
        Gaussian sigma (VET pixels) of the LCoS image on the VET sensor.
    leakage_spread : float
        Per-cell leakage varies uniformly in ``leakage * [1 - s, 1 + s]`` (seeded by
        ``leakage_seed``); 0: every cell leaks ``leakage``.
    leakage_seed : int
        Seed of the per-cell leakage map.
    switch_s : float
        Liquid-crystal switching time: a closing cell's transmittance falls linearly
        from 1 to its leakage over this time.
    trigger_offset_s : float
        Measuring subframes start this long after the VET exposure.
    trigger_jitter_s : float
        Standard deviation of each measuring subframe's start about its nominal time.
    drop_rate : float
        Probability that a measuring subframe is dropped (never reaches the host).
    """

    # The one table: type and allowed range, default. Relations: check_relations.
    frame_s: _real(1e-6, 3600) = 0.99975
    subframe_s: _real(hi=3600, above=0.0) = 0.00758
    full_well_e: _real(1.0, 1e15) = 10000.0
    read_noise_e: _real(0.0, 1e6) = 5.0
    adc_bits: _whole(4, 24) = 12
    dark_current_e_s: _real(0.0, 1e9) = 10.0
    threshold_frac: _real(1e-6, 1.0) = 0.8
    latency_subframes: _whole(0, MAX_SUBFRAMES) = 1
    leakage: _real(0.0, below=1.0) = 0.002
    lcos_cells: tuple[_LcosSide, _LcosSide] = (1024, 600)
    sensor_size: tuple[_SensorSide, _SensorSide] = (1280, 1024)
    measure_fraction: _real(1e-6, 100.0) = 1.0
    homography: _Matrix3 = field(default_factory=list)
    black_level_dn: _real(0.0, 2.0**24) = 64.0
    measure_size: _SizeOrNone = ()
    measure_homography: _Matrix3 = field(default_factory=list)
    measure_k1: _real(-1.0, 1.0) = 0.0
    measure_k2: _real(-1.0, 1.0) = 0.0
    measure_gain: _real(1e-6, 100.0) = 1.0
    measure_vignetting: _real(0.0, 10.0) = 0.0
    relay_blur_px: _real(0.0, 100.0) = 0.0
    leakage_spread: _real(0.0, 1.0) = 0.0
    leakage_seed: _whole(0, 2**63 - 1) = 0
    switch_s: _real(0.0, 3600.0) = 0.0
    trigger_offset_s: _real(0.0, 3600.0) = 0.0
    trigger_jitter_s: _real(0.0, 3600.0) = 0.0
    drop_rate: _real(0.0, MAX_DROP_RATE) = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):  # (numpy scalars, as computed, are numbers)
            value = getattr(self, f.name)
            if isinstance(value, np.generic):
                setattr(self, f.name, value.item())
        for name in ("lcos_cells", "sensor_size", "measure_size"):
            value = getattr(self, name)
            if isinstance(value, (list, tuple, np.ndarray)):
                setattr(self, name, tuple(_as_int(v) for v in value))
        if isinstance(self.homography, np.ndarray):
            self.homography = self.homography.tolist()
        if isinstance(self.measure_homography, np.ndarray):
            self.measure_homography = self.measure_homography.tolist()
        self.validate()
        if not self.homography:
            self.homography = default_homography(self.lcos_cells, self.sensor_size)

    def validate(self) -> None:
        """Raise :class:`InputError` (``invalid rig: field: ...``, one line) if a field is
        outside its range or the fields contradict each other (:func:`check_relations`)."""
        try:
            RIG_MODEL.model_validate(
                {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
            )
        except ValidationError as exc:
            raise InputError(f"invalid rig: {validation_message(exc)}") from None

    @property
    def measure_shape(self) -> tuple[int, int]:
        """The measurement camera's (height, width) in pixels."""
        w, h = self.measure_size if self.measure_size else self.sensor_size
        return int(h), int(w)

    @property
    def ideal_geometry(self) -> bool:
        """Whether the measurement camera shares the VET sensor's pixel grid exactly."""
        return (
            self.measure_shape == (self.sensor_size[1], self.sensor_size[0])
            and (
                not self.measure_homography
                or np.allclose(self.measure_homography, np.eye(3), rtol=0, atol=1e-12)
            )
            and self.measure_k1 == 0
            and self.measure_k2 == 0
            and self.measure_gain == 1
            and self.measure_vignetting == 0
        )

    @property
    def ideal_shutter(self) -> bool:
        """Whether the LCoS is today's ideal one: sharp cells, one leakage, instant
        switching, cameras triggered together."""
        return (
            self.relay_blur_px == 0
            and self.leakage_spread == 0
            and self.switch_s == 0
            and self.trigger_offset_s == 0
            and self.trigger_jitter_s == 0
        )

    # Derived quantities -------------------------------------------------------------
    @property
    def n_subframes(self) -> int:
        """K: whole subframes that fit in the frame."""
        return int(math.floor(self.frame_s / self.subframe_s + 1e-9))

    @property
    def gain_dn_per_e(self) -> float:
        """ADC conversion gain: full well maps to the top code."""
        return (2**self.adc_bits - 1) / self.full_well_e

    @property
    def max_dn(self) -> float:
        return float(2**self.adc_bits - 1)

    @property
    def saturation_dn(self) -> float:
        """Codes at or above this may be clipped: the full well sits at the top code and
        read noise after the well spreads clipped pixels 3 sigma (plus one code) below it."""
        return self.max_dn - 3.0 * self.read_noise_e * self.gain_dn_per_e - 1.0

    @property
    def threshold_e(self) -> float:
        return self.threshold_frac * self.full_well_e

    @property
    def threshold_dn(self) -> float:
        return self.threshold_e * self.gain_dn_per_e

    # Serialisation -------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Every field as plain JSON values; the parts of a real rig only where they are
        not ideal (absent means ideal, so the ideal rig's metadata is what it always was)."""
        d = dataclasses.asdict(self)
        d["lcos_cells"] = list(self.lcos_cells)
        d["sensor_size"] = list(self.sensor_size)
        d["measure_size"] = list(self.measure_size)
        for f in dataclasses.fields(self):
            if f.name in REAL_RIG_PARTS:
                ideal = f.default_factory() if f.default is dataclasses.MISSING else f.default
                if d[f.name] == (list(ideal) if isinstance(ideal, tuple) else ideal):
                    del d[f.name]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "RigParams":
        """The rig of a dict of fields (a file's ``rig``, a profile's ``[params]``)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"invalid rig: unknown parameter(s) {sorted(unknown)}")
        try:
            return cls(**d)
        except (TypeError, ValueError) as exc:
            raise InputError(f"invalid rig: {exc}") from None

    def replace(self, **changes: Any) -> "RigParams":
        """A copy with ``changes``, checked as a new rig (InputError)."""
        try:
            return dataclasses.replace(self, **changes)
        except TypeError as exc:
            raise InputError(f"invalid rig: {exc}") from None


def _as_int(v: Any) -> Any:
    """A size's entry as an int when it is a whole number (the model refuses the rest)."""
    if isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)):
        return int(v)
    return v


# --- relations between fields ------------------------------------------------------------


def check_relations(rig: Any) -> None:
    """Raise ValueError ``"field: what is wrong; allowed ..."`` where fields of ``rig``
    (a validated :data:`RIG_MODEL`, each field in its own range) contradict each other."""
    _check_clock(rig)
    if rig.leakage * (1 + rig.leakage_spread) >= 1:
        raise ValueError(
            f"leakage_spread: leakage {rig.leakage:g} * (1 + {rig.leakage_spread:g}) reaches "
            "1; allowed below 1"
        )
    hom = rig.homography or default_homography(rig.lcos_cells, rig.sensor_size)
    _check_onto_sensor(hom, rig.lcos_cells, rig.sensor_size, "homography", "LCoS")
    _check_measurement_camera(rig)


def _check_clock(rig: Any) -> None:
    """The subframes within the frame; switching, trigger offset and jitter within it."""
    frame, sub = rig.frame_s, rig.subframe_s
    if sub > frame:
        raise ValueError(
            f"subframe_s: {sub} s is longer than the frame (frame_s = {frame} s); subframe "
            "length must be in (0, frame length]"
        )
    n = frame / sub
    if n > MAX_SUBFRAMES:
        raise ValueError(
            f"subframe_s: {sub:g} s gives {n:.3g} subframes per frame; allowed at most "
            f"{MAX_SUBFRAMES} subframes (subframe_s >= frame_s / {MAX_SUBFRAMES})"
        )
    whole = math.floor(n + 1e-9) * sub
    for name, value, top, what in (
        ("switch_s", rig.switch_s, frame, "the frame length"),
        ("trigger_offset_s", rig.trigger_offset_s, frame - whole + 1e-12,
         "the frame after its whole subframes"),
        ("trigger_jitter_s", rig.trigger_jitter_s, sub, "one subframe"),
    ):  # fmt: skip
        if value > top:
            raise ValueError(f"{name}: {value:g} s; allowed at most {what} ({max(top, 0):.6g} s)")


def _corners(size: tuple[int, int]) -> np.ndarray:
    w, h = size
    return np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float)


def _check_onto_sensor(
    hom: list, size: tuple[int, int], sensor: tuple[int, int], name: str, what: str
) -> np.ndarray:
    """``hom`` maps a grid of ``size`` (W, H) onto the sensor: finite, well conditioned,
    in front of it and not all off it; an LCoS's corners within :data:`MAX_REACH_SIZES`
    sensor sizes (a camera may see far beyond the sensor). Returns the corners' (4, 2)
    images."""
    h = np.asarray(hom, float)
    if h.shape != (3, 3):
        raise ValueError(f"{name}: must be a 3x3 matrix")
    with np.errstate(all="ignore"):
        cond = float(np.linalg.cond(h)) if np.isfinite(h).all() else math.inf
        corners = _corners(size) @ h.T
        xy = corners[:, :2] / corners[:, 2:]
    if not cond <= MAX_CONDITION:
        raise ValueError(
            f"{name}: condition number {cond:.3g}; allowed at most {MAX_CONDITION:g} (a finite, "
            "invertible 3x3 matrix)"
        )
    if not np.isfinite(xy).all():
        raise ValueError(f"{name}: maps {what} corners to infinity")
    if np.any(corners[:, 2] <= 0):
        raise ValueError(f"{name}: maps {what} corners behind the sensor (w <= 0)")
    sw, sh = sensor
    if min(xy[:, 0].max(), xy[:, 1].max()) <= 0 or xy[:, 0].min() >= sw or xy[:, 1].min() >= sh:
        field_name = "lcos_cells" if what == "LCoS" else "measure_size"
        raise ValueError(
            f"{field_name}: the {size[0]}x{size[1]} {what} grid, through the {name}, misses "
            f"the {sw}x{sh} sensor entirely"
        )
    far = MAX_REACH_SIZES
    if what == "LCoS" and np.any(
        np.abs(xy - [sw / 2, sh / 2]) > [(far + 0.5) * sw, (far + 0.5) * sh]
    ):
        raise ValueError(
            f"{name}: maps the {what}'s corners as far as ({xy[:, 0].max():.3g}, "
            f"{xy[:, 1].max():.3g}) px; allowed within {far} sensor sizes of the "
            f"{sw}x{sh} sensor"
        )
    return xy


def _check_measurement_camera(rig: Any) -> None:
    """The measurement camera images most of the VET sensor, each of its pixels no more
    than :data:`MAX_MEASURE_PIXEL_PX` VET pixels wide."""
    if len(rig.measure_size) not in (0, 2):
        raise ValueError("measure_size: must be [width, height] in pixels, or empty")
    if not rig.measure_size and not rig.measure_homography:
        return
    size = tuple(rig.measure_size) or tuple(rig.sensor_size)
    hom = rig.measure_homography or np.eye(3).tolist()
    xy = _check_onto_sensor(hom, size, rig.sensor_size, "measure_homography", "measurement camera")
    pixel = math.sqrt(abs(_area(xy)) / (size[0] * size[1]))
    if pixel > MAX_MEASURE_PIXEL_PX:
        raise ValueError(
            f"measure_size: a pixel of the {size[0]}x{size[1]} measurement camera spans "
            f"{pixel:.3g} VET pixels; allowed at most {MAX_MEASURE_PIXEL_PX:g}"
        )
    cover = _cover(np.asarray(hom, float), size, rig)
    if cover < MIN_MEASURE_COVER:
        sw, sh = rig.sensor_size
        raise ValueError(
            f"measure_size: the {size[0]}x{size[1]} measurement camera images "
            f"{100 * cover:.3g}% of the {sw}x{sh} VET sensor; allowed at least "
            f"{100 * MIN_MEASURE_COVER:g}%"
        )


def _area(xy: np.ndarray) -> float:
    """Area of the quadrilateral of corners (0,0), (w,0), (0,h), (w,h)'s images."""
    quad = xy[[0, 1, 3, 2]]
    x, y = quad[:, 0], quad[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _cover(hom: np.ndarray, size: tuple[int, int], rig: Any, grid: int = 48) -> float:
    """The share of the VET sensor's pixels (on a ``grid`` x ``grid`` sample) that fall in
    the measurement camera's frame (through the inverse homography and the camera's
    radial distortion, as :func:`stages.optics.vet_to_measure`)."""
    sw, sh = rig.sensor_size
    xs = (np.arange(min(grid, sw)) + 0.5) * sw / min(grid, sw)
    ys = (np.arange(min(grid, sh)) + 0.5) * sh / min(grid, sh)
    x, y = np.meshgrid(xs, ys)
    with np.errstate(all="ignore"):
        inv = np.linalg.inv(hom)
        w = inv[2, 0] * x + inv[2, 1] * y + inv[2, 2]
        u = (inv[0, 0] * x + inv[0, 1] * y + inv[0, 2]) / w
        v = (inv[1, 0] * x + inv[1, 1] * y + inv[1, 2]) / w
        cx, cy, r0 = size[0] / 2, size[1] / 2, math.hypot(*size) / 2
        qx, qy = (u - cx) / r0, (v - cy) / r0
        r2 = qx * qx + qy * qy
        f = 1 + rig.measure_k1 * r2 + rig.measure_k2 * r2 * r2
        du, dv = cx + r0 * qx * f, cy + r0 * qy * f
        inside = (w > 0) & (du >= 0) & (du < size[0]) & (dv >= 0) & (dv < size[1])
    return float(inside.mean())


# --- the model ---------------------------------------------------------------------------


def _relations(model: BaseModel) -> BaseModel:
    check_relations(model)
    return model


def _rig_model(relations: bool) -> type[BaseModel]:
    """The pydantic model of :class:`RigParams`'s table (its fields, types, ranges and
    defaults), with :func:`check_relations` if ``relations``; unknown names are refused
    (a typo)."""
    hints = typing.get_type_hints(RigParams, include_extras=True)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(RigParams):
        default = (
            Field(default_factory=f.default_factory)
            if f.default is dataclasses.MISSING
            else f.default
        )
        fields[f.name] = (hints[f.name], default)
    checks = {"relations": model_validator(mode="after")(_relations)} if relations else {}
    return create_model(
        "Rig" if relations else "RigFields",
        __config__=ConfigDict(extra="forbid"),
        __doc__=":class:`~stages.rig.RigParams` as stored in files (units in the names).",
        __validators__=checks,
        **fields,
    )


#: The model of a whole rig in files: :class:`RigParams`'s fields with their relations.
RIG_MODEL = _rig_model(relations=True)
#: The fields alone, for a part of a rig that others complete (a profile's or a rig
#: file's ``[params]``: the relations hold once the caller's sensor size joins them).
RIG_FIELDS_MODEL = _rig_model(relations=False)


def validation_message(exc: ValidationError) -> str:
    """The first error of ``exc`` as one line ``field: what is wrong (got value)``."""
    err = exc.errors(include_url=False)[0]
    loc = ".".join(str(p) for p in err["loc"])
    msg = str(err["msg"])
    if msg.startswith("Value error, "):  # (a relation names its field: "subframe_s: ...")
        msg = msg[13:]
        joint = "." if re.match(r"[A-Za-z_][\w.]*: ", msg) else ": "
        return f"{loc}{joint}{msg}" if loc else msg
    msg = msg.replace("Input should be", "must be").replace("Field required", "is missing")
    got = err.get("input")
    shown = (
        ""
        if err["type"] == "missing" or isinstance(got, (dict, list, tuple))
        else f" (got {got!r:.60})"
    )
    return f"{loc or 'metadata'}: {msg}{shown}"
