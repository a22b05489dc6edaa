"""The declared schema of everything vet reads: file metadata, rig files, batch manifests.

Every reader validates what it parsed here before any work: the metadata of captures,
HDR images, motion fields and calibrations (:func:`check_meta`, by ``kind``; files
without a vet ``kind`` are foreign images and pass), their pixel layers against it
(:func:`check_layers`: sizes, channels, subframe time bins, mask codes, exposure times),
rig TOML files (:func:`check_rig_file`) and batch manifests (:func:`check_manifest`).
Types are strict (a string is never a number, a bool never an int), numbers finite, and
every range is stated in the message: one line naming the file, the field and what is
allowed, raised as :class:`~stages.errors.FormatError` (exit 1 at the command line).

The models are `pydantic <https://docs.pydantic.dev>`_ v2 classes; their JSON Schema is
``Model.model_json_schema()``. Keys a model does not name are kept and not checked (files
carry free-form provenance parameters, statistics and notes), except in rig parameters,
where an unknown name is a typo.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..errors import FormatError
from ..rig import MAX_SUBFRAMES

#: Largest sensor side (pixels) and LCoS side (cells) accepted.
MAX_SENSOR_SIDE = 65536
MAX_LCOS_SIDE = 16384
#: Fastest motion a motion field may hold, in image sizes (the larger side) per second.
MAX_SPEED_IMAGES_PER_S = 100
#: Most channels of one layer (Y, or R, G, B, plus spare).
MAX_LAYER_CHANNELS = 16

Float = Annotated[float, Field(strict=True, allow_inf_nan=False)]
Int = Annotated[int, Field(strict=True)]
Str = Annotated[str, Field(strict=True, max_length=65536)]
Positive = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]
SensorSide = Annotated[int, Field(strict=True, ge=1, le=MAX_SENSOR_SIDE)]
LcosSide = Annotated[int, Field(strict=True, ge=1, le=MAX_LCOS_SIDE)]
SensorSize = Annotated[list[SensorSide], Field(min_length=2, max_length=2)]
LcosGrid = Annotated[list[LcosSide], Field(min_length=2, max_length=2)]
Row3 = Annotated[list[Float], Field(min_length=3, max_length=3)]
Matrix3 = Annotated[list[Row3], Field(min_length=3, max_length=3)]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)


class Rig(BaseModel):
    """:class:`~stages.rig.RigParams` as stored in files (units in the names)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    frame_s: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=3600)] = 0.99975
    subframe_s: Positive = 0.00758
    full_well_e: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=1e9)] = 1e4
    read_noise_e: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1e6)] = 5.0
    adc_bits: Annotated[int, Field(strict=True, ge=4, le=24)] = 12
    dark_current_e_s: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1e9)] = 10.0
    threshold_frac: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=1)] = 0.8
    latency_subframes: Annotated[int, Field(strict=True, ge=0, le=MAX_SUBFRAMES)] = 1
    leakage: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, lt=1)] = 0.002
    lcos_cells: LcosGrid = [1024, 600]
    sensor_size: SensorSize = [1280, 1024]
    measure_fraction: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=100)] = 1.0
    homography: Matrix3 | Annotated[list, Field(max_length=0)] = []
    black_level_dn: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=2**24)] = 64.0
    # The parts of a real rig (stages.optics; the defaults are the ideal rig).
    measure_size: SensorSize | Annotated[list, Field(max_length=0)] = []
    measure_homography: Matrix3 | Annotated[list, Field(max_length=0)] = []
    measure_k1: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-1, le=1)] = 0.0
    measure_k2: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-1, le=1)] = 0.0
    measure_gain: Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0, le=100)] = 1.0
    measure_vignetting: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=10)] = 0.0
    relay_blur_px: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=100)] = 0.0
    leakage_spread: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=1)] = 0.0
    leakage_seed: Annotated[int, Field(strict=True, ge=0, le=2**63 - 1)] = 0
    switch_s: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=3600)] = 0.0
    trigger_offset_s: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=3600)] = 0.0
    trigger_jitter_s: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, le=3600)] = 0.0
    drop_rate: Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0, lt=1)] = 0.0

    @model_validator(mode="after")
    def _consistent(self) -> Rig:
        if self.subframe_s > self.frame_s:
            raise ValueError(
                f"subframe_s: {self.subframe_s} s is longer than the frame "
                f"(frame_s = {self.frame_s} s); allowed (0, frame_s]"
            )
        n = self.frame_s / self.subframe_s
        if n > MAX_SUBFRAMES:
            raise ValueError(
                f"subframe_s: {self.subframe_s:g} s gives {n:.3g} subframes per frame; "
                f"allowed at most {MAX_SUBFRAMES} (subframe_s >= frame_s / {MAX_SUBFRAMES})"
            )
        if self.homography:
            h = np.asarray(self.homography, float)
            w, hh = self.lcos_cells
            with np.errstate(all="ignore"):
                if not abs(np.linalg.det(h)) >= 1e-12:
                    raise ValueError("homography: must be an invertible 3x3 matrix")
                corners = np.array([[0, 0, 1], [w, 0, 1], [0, hh, 1], [w, hh, 1]], float) @ h.T
                xy = corners[:, :2] / corners[:, 2:]
            if not np.isfinite(xy).all():
                raise ValueError("homography: maps LCoS corners to infinity")
            if np.any(corners[:, 2] <= 0):
                raise ValueError("homography: maps LCoS corners behind the sensor (w <= 0)")
            sw, sh = self.sensor_size
            if (
                min(xy[:, 0].max(), xy[:, 1].max()) <= 0
                or xy[:, 0].min() >= sw
                or (xy[:, 1].min() >= sh)
            ):
                raise ValueError(
                    f"lcos_cells: the {w}x{hh} LCoS grid, through the homography, misses the "
                    f"{sw}x{sh} sensor entirely"
                )
        return self


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
    radiance_scale: Positive | None = None
    units: Any = None


class TruthTrajectory(BaseModel):
    """Each layer's true path (:mod:`stages.motion`, motions along paths)."""

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

    @model_validator(mode="after")
    def _lengths(self) -> TruthTrajectory:
        for k, path in enumerate(self.disp):
            if len(path) != len(self.times):
                raise ValueError(f"disp.{k}: {len(path)} displacements for {len(self.times)} times")
        return self


#: Whole numbers on the subframe clock, one per subframe at most (indices or counts).
SubframeCounts = Annotated[
    list[Annotated[int, Field(strict=True, ge=0, le=MAX_SUBFRAMES)]],
    Field(max_length=MAX_SUBFRAMES),
]


class CaptureMeta(_FileMeta):
    """A capture's metadata (:mod:`stages.formats.capture`)."""

    kind: Literal["capture"]
    rig: Rig
    method: Literal["vet", "long", "short", "adaptive-attenuation"] = "vet"
    units: dict[str, Str] | None = None
    measure_times: (
        Annotated[
            list[Annotated[list[Float], Field(min_length=2, max_length=2)]],
            Field(max_length=MAX_SUBFRAMES),
        ]
        | None
    ) = None
    truth_trajectory: TruthTrajectory | None = None
    # Measuring subframes the rig dropped (indices on the subframe clock; the stream
    # holds the others, each with its own time bin).
    measure_dropped: SubframeCounts | None = None
    # Subframes summed in each measuring image (time bins of a stream).
    measure_subframes: SubframeCounts | None = None
    rig_profile: Str | None = None

    @model_validator(mode="after")
    def _bins(self) -> CaptureMeta:
        if self.units is not None:
            for layer, unit in (("I", "DN"), ("T", "s")):
                if layer in self.units and self.units[layer] != unit:
                    raise ValueError(f"units.{layer}: {self.units[layer]!r}; allowed {unit!r}")
        top = self.rig.frame_s * (1 + 1e-6)
        for b, (start, end) in enumerate(self.measure_times or []):
            if not 0 <= start < end <= top:
                raise ValueError(
                    f"measure_times.{b}: [{start}, {end}] s; allowed 0 <= start < end <= "
                    f"frame_s ({self.rig.frame_s} s)"
                )
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
    # The parts of a real rig found (stages.calibrate.parts): rig fields, checked as such.
    parts: Rig | None = None
    # Medians are NaN where nothing could be measured (calibration_changes skips them).
    leakage_median: float | None = None
    dark_current_median_e_s: float | None = None
    bias_median_dn: float | None = None
    gain_ratio_median: float | None = None


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


def _message(exc: ValidationError) -> str:
    """The first error as ``field: what is wrong (got value)``."""
    err = exc.errors(include_url=False)[0]
    loc = ".".join(str(p) for p in err["loc"])
    msg = str(err["msg"])
    if msg.startswith("Value error, "):
        return f"{loc}.{msg[13:]}" if loc else msg[13:]
    msg = msg.replace("Input should be", "must be").replace("Field required", "is missing")
    got = err.get("input")
    shown = (
        "" if err["type"] == "missing" or isinstance(got, (dict, list)) else f" (got {got!r:.60})"
    )
    return f"{loc or 'metadata'}: {msg}{shown}"


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

    A capture's I channels against ``channels`` and its measuring layers against
    ``measure_times``; an HDR image's mask codes against ``mask_codes``; a motion
    field's velocities against :data:`MAX_SPEED_IMAGES_PER_S`; a capture's measuring
    layers share one size. (Layer sizes against the declared sensor and measurement
    camera sizes are checked by the container readers, before the pixels are read:
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
        bins = [k for k in layers if len(k) >= 3 and k[0] == "M" and k[1:].isdigit()]
        image = channels.get("I")
        wanted = {"T": ["Y"], "A": ["Y"], "truth_motion": ["u", "v"], "truth_layers": ["Y"]}
        wanted.update({k: image for k in (*bins, "truth")})
        for name, chans in wanted.items():
            if name in channels and image is not None and list(channels[name]) != list(chans):
                raise FormatError(
                    f"{what}: layer {name!r} has channels {channels[name]}; allowed {chans}"
                )
        sizes = sorted({layers[k].shape[:2] for k in bins})
        if len(sizes) > 1:
            raise FormatError(
                f"{what}: measuring layers have different sizes "
                f"{', '.join(f'{w}x{h}' for h, w in sizes)}; allowed one"
            )
        times = meta.get("measure_times")
        if bins and (times is None or len(times) != len(bins)):
            n = "none" if times is None else len(times)
            raise FormatError(
                f"{what}: measure_times: {n} time bins for {len(bins)} measuring layers; "
                "allowed one [start, end] per layer"
            )
    if kind == "motion" and "motion" in layers:
        field = layers["motion"]
        top = MAX_SPEED_IMAGES_PER_S * max(field.shape[:2])
        speed = float(np.abs(field).max()) if field.size else 0.0
        if not np.isfinite(speed):
            raise FormatError(f"{what}: motion: the field holds non-finite velocities")
        if speed > top:
            raise FormatError(
                f"{what}: motion: velocities up to {speed:.3g} px/s; allowed at most "
                f"{top:g} px/s ({MAX_SPEED_IMAGES_PER_S} image sizes per second)"
            )
    if kind == "hdr" and "mask" in layers:
        codes = meta.get("mask_codes")
        allowed = {int(k) for k in codes} if codes else {0, 1, 2, 3}
        found = np.unique(layers["mask"]).tolist()
        bad = [v for v in found if not (np.isfinite(v) and v == int(v) and int(v) in allowed)]
        if bad:
            shown = [int(v) if np.isfinite(v) and v == int(v) else v for v in bad[:5]]
            raise FormatError(f"{what}: mask: codes {shown} not in mask_codes {sorted(allowed)}")


def check_rig_file(data: dict[str, Any], what: str) -> RigFile:
    """Validate a parsed rig TOML file (sections ``params``, ``lcos``, cameras)."""
    return validate(RigFile, data, what)  # type: ignore[return-value]


def check_rig_params(data: dict[str, Any], what: str) -> dict[str, Any]:
    """The ``[params]`` table of a parsed rig TOML file, validated as :class:`Rig`
    (for readers that use only the parameters, such as a calibration folder's
    ``rig.toml``); returns it as a plain dict for :meth:`RigParams.from_dict`."""
    params = data.get("params", {})
    validate(Rig, params, f"{what}: [params]")
    return dict(params)


def check_manifest(data: Any, what: str) -> Manifest:
    """Validate a parsed batch manifest."""
    return validate(Manifest, data, what)  # type: ignore[return-value]
