"""Rig parameters: every number that describes a VET rig, with the defaults of DESIGN.md §2.

A :class:`RigParams` travels inside every capture's metadata so that each later stage
reconstructs with exactly the physics that made the data.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .errors import InputError

#: Most subframes one frame may hold (``frame_s / subframe_s``): bounds the work and
#: memory of every stage that walks the subframes.
MAX_SUBFRAMES = 100_000


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

    frame_s: float = 0.99975
    subframe_s: float = 0.00758
    full_well_e: float = 10000.0
    read_noise_e: float = 5.0
    adc_bits: int = 12
    dark_current_e_s: float = 10.0
    threshold_frac: float = 0.8
    latency_subframes: int = 1
    leakage: float = 0.002
    lcos_cells: tuple[int, int] = (1024, 600)
    sensor_size: tuple[int, int] = (1280, 1024)
    measure_fraction: float = 1.0
    homography: list[list[float]] = field(default_factory=list)
    black_level_dn: float = 64.0
    measure_size: tuple[int, ...] = ()
    measure_homography: list[list[float]] = field(default_factory=list)
    measure_k1: float = 0.0
    measure_k2: float = 0.0
    measure_gain: float = 1.0
    measure_vignetting: float = 0.0
    relay_blur_px: float = 0.0
    leakage_spread: float = 0.0
    leakage_seed: int = 0
    switch_s: float = 0.0
    trigger_offset_s: float = 0.0
    trigger_jitter_s: float = 0.0
    drop_rate: float = 0.0

    def __post_init__(self) -> None:
        self.lcos_cells = (int(self.lcos_cells[0]), int(self.lcos_cells[1]))
        self.sensor_size = (int(self.sensor_size[0]), int(self.sensor_size[1]))
        self.measure_size = tuple(int(v) for v in self.measure_size)
        if not self.homography:
            self.homography = default_homography(self.lcos_cells, self.sensor_size)
        self.validate()

    def validate(self) -> None:
        """Raise :class:`InputError` with a full sentence if a parameter is nonsense."""
        checks = [
            (self.frame_s > 0, "frame length must be positive"),
            (0 < self.subframe_s <= self.frame_s, "subframe length must be in (0, frame length]"),
            (
                self.frame_s <= MAX_SUBFRAMES * self.subframe_s,
                f"a frame may hold at most {MAX_SUBFRAMES} subframes "
                f"(subframe length >= frame length / {MAX_SUBFRAMES})",
            ),
            (self.full_well_e > 0, "full well must be positive"),
            (self.read_noise_e >= 0, "read noise must be non-negative"),
            (4 <= self.adc_bits <= 24, "ADC depth must be 4 to 24 bits"),
            (self.dark_current_e_s >= 0, "dark current must be non-negative"),
            (
                0 < self.threshold_frac <= 1,
                "threshold must be a fraction of the full well in (0, 1]",
            ),
            (self.latency_subframes >= 0, "latency must be a non-negative number of subframes"),
            (0 <= self.leakage < 1, "leakage must be in [0, 1)"),
            (min(self.lcos_cells) > 0, "LCoS grid must have positive size"),
            (min(self.sensor_size) > 0, "sensor must have positive size"),
            (self.measure_fraction > 0, "measurement light fraction must be positive"),
            (self.black_level_dn >= 0, "black level must be non-negative"),
            (
                len(self.measure_size) == 0
                or (len(self.measure_size) == 2 and min(self.measure_size) > 0),
                "measurement camera size must be (width, height) in pixels",
            ),
            (abs(self.measure_k1) <= 1 and abs(self.measure_k2) <= 1, "distortion |k| <= 1"),
            (self.measure_gain > 0, "measurement gain must be positive"),
            (0 <= self.measure_vignetting <= 10, "vignetting must be in [0, 10]"),
            (0 <= self.relay_blur_px <= 100, "relay blur must be in [0, 100] px"),
            (0 <= self.leakage_spread <= 1, "leakage spread must be in [0, 1]"),
            (
                0 <= self.leakage * (1 + self.leakage_spread) < 1,
                "leakage * (1 + leakage_spread) must be below 1",
            ),
            (0 <= self.switch_s <= self.frame_s, "switching time must be in [0, frame length]"),
            (
                0
                <= self.trigger_offset_s
                <= self.frame_s - self.n_subframes * self.subframe_s + 1e-12,
                "trigger offset must fit in the frame after its whole subframes",
            ),
            (0 <= self.trigger_jitter_s <= self.subframe_s, "jitter must be in [0, subframe]"),
            (0 <= self.drop_rate < 1, "drop rate must be in [0, 1)"),
        ]
        for ok, message in checks:
            if not ok:
                raise InputError(f"invalid rig: {message}")
        h = np.asarray(self.homography, dtype=float)
        if h.shape != (3, 3) or not np.all(np.isfinite(h)) or abs(np.linalg.det(h)) < 1e-12:
            raise InputError("invalid rig: homography must be a finite, invertible 3x3 matrix")
        if self.measure_homography:
            m = np.asarray(self.measure_homography, dtype=float)
            if m.shape != (3, 3) or not np.all(np.isfinite(m)) or abs(np.linalg.det(m)) < 1e-12:
                raise InputError(
                    "invalid rig: measure_homography must be a finite, invertible 3x3 matrix"
                )

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
    def from_dict(cls, d: dict[str, Any]) -> RigParams:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"invalid rig: unknown parameter(s) {sorted(unknown)}")
        try:
            return cls(**d)
        except (TypeError, ValueError) as exc:
            raise InputError(f"invalid rig: {exc}") from None

    def replace(self, **changes: Any) -> RigParams:
        return dataclasses.replace(self, **changes)
