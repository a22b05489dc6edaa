"""The declared schema of everything vet reads: file metadata, rig files, batch manifests.

Every reader validates what it parsed here before any work: the metadata of captures,
HDR images, motion fields and calibrations (:func:`check_meta`, by ``kind``; files
without a vet ``kind`` are foreign images and pass), their pixel layers against it
(:func:`check_layers`: sizes, channels, measuring layers one per time bin, mask codes),
rig TOML files (:func:`check_rig_file`) and batch manifests (:func:`check_manifest`).
Types are strict (a string is never a number, a bool never an int), numbers finite, a
divisor a normal float32, and every range is stated in the message: one line naming the
file, the field and what is allowed, raised as :class:`~stages.errors.FormatError` (exit 1
at the command line). Relations between fields are checked too: a rig's by its own model
(:data:`Rig` is :data:`stages.rig.RIG_MODEL`, built from :class:`~stages.rig.RigParams`'s
table of fields), a capture's time bins, subframe counts and dropped subframes by
:mod:`stages.formats.relations`.

The models are `pydantic <https://docs.pydantic.dev>`_ v2 classes; their JSON Schema is
``Model.model_json_schema()``. Keys a model does not name are kept and not checked (files
carry free-form provenance parameters, statistics and notes), except in rig parameters,
where an unknown name is a typo.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..errors import FormatError
from ..rig import (
    MAX_LCOS_SIDE,
    MAX_SENSOR_SIDE,
    MAX_SUBFRAMES,
    RIG_FIELDS_MODEL,
    RIG_MODEL,
    validation_message,
)
from . import relations

#: Fastest motion a motion field may hold, in image sizes (the larger side) per second.
MAX_SPEED_IMAGES_PER_S = 100
#: Most channels of one layer (Y, or R, G, B, plus spare).
MAX_LAYER_CHANNELS = 16
#: The smallest and largest scale a value is divided by or multiplied into float32 pixels
#: with: a normal float32 (no denormal, whose reciprocal is infinite).
FLOAT32_TINY = float(np.finfo(np.float32).tiny)
FLOAT32_MAX = float(np.finfo(np.float32).max)

Float = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Int = Annotated[int, Field(strict=True)]
Str = Annotated[str, Field(strict=True, max_length=65536)]
Positive = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]


def _normal_float32(value: float) -> float:
    if not FLOAT32_TINY <= value <= FLOAT32_MAX:
        raise ValueError(
            f"{value:g} is not a normal float32 number (pixels divided by it would be "
            f"infinite); allowed {FLOAT32_TINY:.3g} to {FLOAT32_MAX:.3g}"
        )
    return value


#: A factor pixels are divided by: finite, positive and a normal float32.
Scale = Annotated[Positive, AfterValidator(_normal_float32)]
SensorSide = Annotated[int, Field(strict=True, ge=1, le=MAX_SENSOR_SIDE)]
LcosSide = Annotated[int, Field(strict=True, ge=1, le=MAX_LCOS_SIDE)]
SensorSize = Annotated[list[SensorSide], Field(min_length=2, max_length=2)]
LcosGrid = Annotated[list[LcosSide], Field(min_length=2, max_length=2)]
Row3 = Annotated[list[Float], Field(min_length=3, max_length=3)]
Matrix3 = Annotated[list[Row3], Field(min_length=3, max_length=3)]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)


#: A rig as files store it: :data:`stages.rig.RIG_MODEL`, the model of
#: :class:`~stages.rig.RigParams`'s own table of fields (one schema of the rig).
Rig = RIG_MODEL
#: Rig fields that a caller completes (a rig file's or profile's ``[params]``): each in
#: its range; the relations are checked on the whole rig (:class:`~stages.rig.RigParams`).
RigFields = RIG_FIELDS_MODEL


class InputRecord(_Open):
    """A file a step read (:func:`stages.provenance.input_record`)."""

    path: Str
    bytes: Annotated[int, Field(strict=True, ge=0)] | None = None
    sha256: Annotated[str, Field(strict=True, pattern=r"^[0-9a-f]{64}$")] | None = None


class Provenance(_Open):
    """One link of the provenance chain (:func:`~stages.formats.capture.provenance_entry`):
    its inputs are file records or plain names (a capture's rig)."""

    step: Str
    software: Str | None = None
    command: Str | None = None
    time: Str | None = None
    inputs: list[InputRecord | Str] = []
    params: dict[str, Any] = {}


class _FileMeta(_Open):
    format_version: Literal[1] = 1
    channels: Annotated[list[Str], Field(min_length=1, max_length=MAX_LAYER_CHANNELS)] | None = None
    provenance: list[Provenance] = []
    scene: Str | None = None
    motion: Str | None = None
    seed: Int | None = None
    radiance_scale: Scale | None = None
    units: Any = None


class TruthTrajectory(BaseModel):
    """Each layer's true path (:class:`stages.formats.capture.TruthPaths`, motions along
    paths): ``disp`` per layer and time; for layers that turn, ``anchor`` per layer and
    ``linear`` (2 x 2) per layer and time; ``front`` the occluding layers, front to back."""

    model_config = ConfigDict(extra="forbid")
    times: Annotated[list[Float], Field(min_length=1, max_length=MAX_SUBFRAMES + 2)]
    disp: Annotated[
        list[
            Annotated[
                list[Annotated[list[Float], Field(min_length=2, max_length=2)]],
                Field(max_length=MAX_SUBFRAMES + 2),
            ]
        ],
        Field(min_length=1, max_length=16),
    ]
    anchor: (
        Annotated[
            list[Annotated[list[Float], Field(min_length=2, max_length=2)]],
            Field(max_length=16),
        ]
        | None
    ) = None
    linear: (
        Annotated[
            list[
                Annotated[
                    list[
                        Annotated[
                            list[Annotated[list[Float], Field(min_length=2, max_length=2)]],
                            Field(min_length=2, max_length=2),
                        ]
                    ],
                    Field(max_length=MAX_SUBFRAMES + 2),
                ]
            ],
            Field(max_length=16),
        ]
        | None
    ) = None
    front: (
        Annotated[list[Annotated[int, Field(strict=True, ge=1, le=15)]], Field(max_length=15)]
        | None
    ) = None

    @model_validator(mode="after")
    def _lengths(self) -> TruthTrajectory:
        k_n = len(self.disp)
        for k, path in enumerate(self.disp):
            if len(path) != len(self.times):
                raise ValueError(f"disp.{k}: {len(path)} displacements for {len(self.times)} times")
        if (self.anchor is None) != (self.linear is None):
            raise ValueError("anchor and linear come together (layers that turn)")
        if self.anchor is not None and len(self.anchor) != k_n:
            raise ValueError(f"anchor: {len(self.anchor)} anchors for {k_n} layers")
        for k, path in enumerate(self.linear or []):
            if len(path) != len(self.times):
                raise ValueError(f"linear.{k}: {len(path)} maps for {len(self.times)} times")
        if self.linear is not None and len(self.linear) != k_n:
            raise ValueError(f"linear: {len(self.linear)} layers' maps for {k_n} layers")
        if self.front is not None and sorted(self.front) != list(range(1, k_n)):
            raise ValueError(f"front: {self.front} is not the layers 1 .. {k_n - 1}, once each")
        return self


#: Indices on the subframe clock, one per subframe at most.
SubframeIndices = Annotated[
    list[Annotated[int, Field(strict=True, ge=0, lt=MAX_SUBFRAMES)]],
    Field(max_length=MAX_SUBFRAMES),
]
#: Subframes summed in each measuring image: one at least.
SubframeCounts = Annotated[
    list[Annotated[int, Field(strict=True, ge=1, le=MAX_SUBFRAMES)]],
    Field(max_length=MAX_SUBFRAMES),
]
#: Each measuring image's ``[start, end)``, seconds.
BinTimes = Annotated[
    list[Annotated[list[Float], Field(min_length=2, max_length=2)]],
    Field(max_length=MAX_SUBFRAMES),
]


class CaptureMeta(_FileMeta):
    """A capture's metadata (:mod:`stages.formats.capture`); the relations between its
    fields are :func:`stages.formats.relations.check_capture`'s."""

    kind: Literal["capture"]
    rig: Rig
    method: Literal["vet", "long", "short", "adaptive-attenuation"] = "vet"
    units: dict[str, Str] | None = None
    # The exposure's whole length (the frame; one subframe for a short exposure).
    integration_s: Positive | None = None
    # Whether closed pixels leak (a VET capture's LCoS) or not (a plain exposure).
    leakage_applies: bool | None = None
    measure_times: BinTimes | None = None
    truth_trajectory: TruthTrajectory | None = None
    # Measuring subframes the rig dropped (indices on the subframe clock; the stream
    # holds the others, each with its own time bin).
    measure_dropped: SubframeIndices | None = None
    # Subframes summed in each measuring image (time bins of a stream).
    measure_subframes: SubframeCounts | None = None
    rig_profile: Str | None = None

    @model_validator(mode="after")
    def _relations(self) -> CaptureMeta:
        if self.units is not None:
            for layer, unit in (("I", "DN"), ("T", "s")):
                if layer in self.units and self.units[layer] != unit:
                    raise ValueError(f"units.{layer}: {self.units[layer]!r}; allowed {unit!r}")
        relations.check_capture(self)
        return self


class HDRMeta(_FileMeta):
    """An HDR image's metadata (:mod:`stages.formats.hdr`)."""

    kind: Literal["hdr"]
    # scene: simulated captures' scene units; DN/s: recorded ones; unknown: foreign images.
    units: Literal["scene", "DN/s", "unknown"] | None = None
    rig: Rig | None = None
    mask_codes: dict[Annotated[str, Field(pattern=r"^[0-9]{1,3}$")], Str] | None = None
    display_referred: bool | None = None


class MotionMeta(_FileMeta):
    """A motion field's metadata (``vet deblur --motion-out``)."""

    kind: Literal["motion"]
    units: Literal["px/s"] = "px/s"


class CalibrationMeta(_FileMeta):
    """A calibration's metadata (``vet calibrate``)."""

    kind: Literal["calibration"]
    sensor_size: SensorSize
    lcos_cells: LcosGrid
    homography: Matrix3 | None = None
    homography_fit: dict[str, Any] = {}
    rig: Rig | None = None
    provenance: dict[str, Any] = {}
    # The parts of a real rig found (stages.calibrate.parts): rig fields, checked as such
    # on the calibration's rig (its sensor, LCoS and clock).
    parts: dict[str, Any] | None = None
    # Medians are NaN where nothing could be measured (calibration_changes skips them).
    leakage_median: float | None = None
    dark_current_median_e_s: float | None = None
    bias_median_dn: float | None = None
    gain_ratio_median: float | None = None

    @model_validator(mode="after")
    def _parts(self) -> CalibrationMeta:
        if self.parts:
            base = self.rig.model_dump() if self.rig is not None else {}
            grid = {"sensor_size": self.sensor_size, "lcos_cells": self.lcos_cells}
            try:
                Rig.model_validate({**base, **grid, **self.parts})
            except ValidationError as exc:
                raise ValueError(f"parts.{validation_message(exc)}") from None
        return self


META_MODELS: dict[str, type[_FileMeta]] = {
    "capture": CaptureMeta,
    "hdr": HDRMeta,
    "motion": MotionMeta,
    "calibration": CalibrationMeta,
}


class LcosSection(_Open):
    url: Annotated[str, Field(strict=True, min_length=1, max_length=4096)]
    baudrate: Annotated[int, Field(strict=True, ge=1, le=100_000_000)] | None = None
    link_bps: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=1e11)] | None = None
    ack_timeout_s: (
        Annotated[float, Field(strict=True, allow_inf_nan=False, ge=1e-3, le=60)] | None
    ) = None
    max_retries: Annotated[int, Field(strict=True, ge=0, le=100)] | None = None


class CameraSection(_Open):
    # OpenCV cameras need a source (checked by stages.devices.rigs); GenICam ones name a
    # device instead (their keys are checked by stages.devices.genicam).
    source: (
        Annotated[str, Field(strict=True, min_length=1, max_length=4096)]
        | Annotated[int, Field(strict=True, ge=0, le=1024)]
        | None
    ) = None
    exposure: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1e9)] | None = None


class RigFile(_Open):
    """A rig TOML file (:mod:`stages.devices.rigs`)."""

    # A rig file describes its hardware whole: its [params] hold their relations.
    params: Rig = Rig()
    lcos: LcosSection
    measurement_camera: CameraSection
    vet_camera: CameraSection


class ManifestInput(_Open):
    path: Str
    # Absent when the capture could not be read at all.
    size: Annotated[int, Field(strict=True, ge=0)] | None = None
    mtime_ns: Int | None = None
    sha256: Annotated[str, Field(strict=True, pattern=r"^[0-9a-f]{64}$")] | None = None


class ManifestStep(_Open):
    key: Str
    output: Str | None = None
    version: Str | None = None
    params: dict[str, Any] = {}
    sha256: Annotated[str, Field(strict=True, pattern=r"^[0-9a-f]{64}$")] | None = None
    size: Annotated[int, Field(strict=True, ge=0)] | None = None
    mtime_ns: Int | None = None


class ManifestFailure(_Open):
    step: Str
    reason: Str
    key: Str | None = None


class ManifestCapture(_Open):
    input: ManifestInput
    status: Literal["ok", "failed"]
    steps: dict[str, ManifestStep] = {}
    failure: ManifestFailure | None = None


class Manifest(_Open):
    """A batch manifest (:mod:`stages.batch.manifest`)."""

    format: Literal["vet-batch-manifest"]
    format_version: Literal[1]
    captures: dict[str, ManifestCapture]


# --- checking ----------------------------------------------------------------------------


_message = validation_message


def validate(model: type[BaseModel], data: Any, what: str) -> BaseModel:
    """``model`` validated from ``data``; FormatError ``"{what}: field: ..."`` if not."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise FormatError(f"{what}: {_message(exc)}") from None


def check_meta(meta: dict[str, Any], what: str) -> BaseModel | None:
    """Validate a file's metadata by its ``kind``; None for a kind vet does not read
    (a foreign image has none; the reader of each kind refuses the others).

    Raises
    ------
    FormatError
        A field of the wrong type or out of range.
    """
    kind = meta.get("kind")
    if kind is not None and not isinstance(kind, str):
        raise FormatError(f"{what}: kind: must be a string (got {kind!r:.40})")
    model = META_MODELS.get(kind or "")
    if model is None:
        return None
    return validate(model, meta, what)


def check_layers(
    meta: dict[str, Any], layers: dict[str, np.ndarray], channels: dict[str, list[str]], what: str
) -> None:
    """Cross-check a vet file's pixel layers ``(H, W, C)`` with its (valid) metadata.

    Every layer's channel count; the image's channels against ``channels``; a capture's
    layers' channels, and its measuring layers (``M00``, ``M01``... in order, of one size)
    against ``measure_times`` (:func:`_check_measuring_layers`); a motion field's
    velocities against :data:`MAX_SPEED_IMAGES_PER_S`; an HDR image's mask codes against
    ``mask_codes``. (Layer sizes against the declared sensor and measurement camera sizes
    are checked by the container readers, before the pixels are read:
    :class:`stages.formats.container.SizeCheck`.)

    Raises
    ------
    FormatError
        One line naming the field that disagrees with the pixels.
    """
    kind = meta.get("kind")
    if kind not in META_MODELS:
        return
    for name, chans in channels.items():
        if len(chans) > MAX_LAYER_CHANNELS:
            raise FormatError(f"{what}: layer {name!r} has {len(chans)} channels; allowed 1 to 16")
    declared = meta.get("channels")
    base = "I" if kind == "capture" else ""
    if declared is not None and base in channels and list(declared) != list(channels[base]):
        raise FormatError(
            f"{what}: channels: {declared} but layer {base or 'image'!r} holds {channels[base]}"
        )
    if kind == "capture":
        bins = measuring_layers(layers)
        _check_capture_channels(channels, bins, what)
        _check_measuring_layers(meta, layers, bins, what)
        if "truth_motion" in layers:
            _check_motion(layers["truth_motion"], what, "truth_motion")
    if kind == "motion" and "motion" in layers:
        _check_motion(layers["motion"], what, "motion")
    if kind == "hdr" and "mask" in layers:
        _check_mask(meta.get("mask_codes"), layers["mask"], what)


def measuring_layers(layers: dict[str, np.ndarray]) -> list[str]:
    """A capture's measuring layers (``M`` and digits), in the order of their numbers."""
    names = [k for k in layers if len(k) >= 3 and k[0] == "M" and k[1:].isdigit()]
    return sorted(names, key=lambda k: int(k[1:]))


def _check_capture_channels(channels: dict[str, list[str]], bins: list[str], what: str) -> None:
    image = channels.get("I")
    if image is None:
        return
    wanted = {"T": ["Y"], "A": ["Y"], "truth_motion": ["u", "v"], "truth_layers": ["Y"]}
    wanted.update({k: image for k in (*bins, "truth")})
    for name, chans in wanted.items():
        if name in channels and list(channels[name]) != list(chans):
            raise FormatError(
                f"{what}: layer {name!r} has channels {channels[name]}; allowed {chans}"
            )


def _check_measuring_layers(
    meta: dict[str, Any], layers: dict[str, np.ndarray], bins: list[str], what: str
) -> None:
    """The measuring layers are ``M00`` to ``M{B-1}`` (two digits at least), of one size,
    one per ``measure_times`` bin."""
    expected = [f"M{b:02d}" for b in range(len(bins))]
    if bins != expected:
        odd = next(n for n, e in zip(bins, expected, strict=True) if n != e)
        raise FormatError(
            f"{what}: measuring layer {odd!r} out of sequence; allowed M00 to "
            f"{expected[-1]}, one per time bin"
        )
    sizes = sorted({layers[k].shape[:2] for k in bins})
    if len(sizes) > 1:
        raise FormatError(
            f"{what}: measuring layers have different sizes "
            f"{', '.join(f'{w}x{h}' for h, w in sizes)}; allowed one"
        )
    times = meta.get("measure_times")
    if (bins or times) and (times is None or len(times) != len(bins)):
        n = "none" if times is None else len(times)
        raise FormatError(
            f"{what}: measure_times: {n} time bins for {len(bins)} measuring layers; "
            "allowed one [start, end] per layer"
        )


def _check_motion(field: np.ndarray, what: str, name: str) -> None:
    top = MAX_SPEED_IMAGES_PER_S * max(field.shape[:2])
    speed = float(np.abs(field).max()) if field.size else 0.0
    if not np.isfinite(speed):
        raise FormatError(f"{what}: {name}: the field holds non-finite velocities")
    if speed > top:
        raise FormatError(
            f"{what}: {name}: velocities up to {speed:.3g} px/s; allowed at most "
            f"{top:g} px/s ({MAX_SPEED_IMAGES_PER_S} image sizes per second)"
        )


def _check_mask(codes: dict[str, str] | None, mask: np.ndarray, what: str) -> None:
    allowed = {int(k) for k in codes} if codes else {0, 1, 2, 3}
    found = np.unique(mask).tolist()
    bad = [v for v in found if not (np.isfinite(v) and v == int(v) and int(v) in allowed)]
    if bad:
        shown = [int(v) if np.isfinite(v) and v == int(v) else v for v in bad[:5]]
        raise FormatError(f"{what}: mask: codes {shown} not in mask_codes {sorted(allowed)}")


def check_rig_file(data: dict[str, Any], what: str) -> RigFile:
    """Validate a parsed rig TOML file (sections ``params``, ``lcos``, cameras)."""
    return validate(RigFile, data, what)  # type: ignore[return-value]


def check_rig_params(data: dict[str, Any], what: str, whole: bool = True) -> dict[str, Any]:
    """The ``[params]`` table of a parsed rig TOML file, validated as :data:`Rig` (a
    whole rig: a calibration folder's ``rig.toml``) or, not ``whole``, field by field as
    :data:`RigFields` (a profile that the caller's sensor size completes: the relations
    hold on the rig made of both); returns it as a plain dict for
    :meth:`RigParams.from_dict`."""
    params = data.get("params", {})
    validate(Rig if whole else RigFields, params, f"{what}: [params]")
    return dict(params)


def check_manifest(data: Any, what: str) -> Manifest:
    """Validate a parsed batch manifest."""
    return validate(Manifest, data, what)  # type: ignore[return-value]
