"""The steps a batch can run on each capture: a registry of name -> file-to-file function.

Each :class:`Step` turns one input file into one output file, ``run(input_path,
output_path, params)``, writing atomically (every writer in :mod:`stages.formats` does).
Steps run in pipeline order (:data:`PIPELINE_ORDER`): ``hdr-static`` and ``deblur`` read
the capture, ``tonemap`` reads the HDR image of the last HDR step chosen (``deblur``'s
when it runs, else ``hdr-static``'s).

A step whose implementation module cannot be imported (``deblur`` before
:mod:`stages.deblur` exists) is *unavailable*: asking for it stops the run before any
work with a clear message (:func:`check_available`). ``stages.deblur`` plugs in by
providing either ``batch_step(input_path, output_path, params)`` or
``deblur(capture, **params)`` returning an :class:`~stages.formats.hdr.HDRImage` (or a
tuple whose first HDR image is taken).

More steps can be added with :func:`register_step`.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import InputError, VetError

#: Signature of a step's implementation: ``run(input_path, output_path, params)``.
StepFunction = Callable[[str, str, dict[str, Any]], None]


class StepSpecError(InputError):
    """Unknown step, unknown parameter or bad parameter value: a usage error."""


@dataclass(frozen=True)
class Step:
    """One batch step.

    Attributes
    ----------
    name : str
        Name used on the command line (``--steps``) and in the manifest.
    suffix : str
        Appended to the capture's output stem to name the output (``.hdr.exr``).
    consumes : str
        ``"capture"`` (reads the capture) or ``"hdr"`` (reads the previous HDR output).
    produces : str
        ``"hdr"`` or ``"display"``.
    module : str
        Module that must be importable for the step to be available.
    run : StepFunction
        The implementation.
    defaults : mapping
        Parameters and their defaults. Every parameter is part of the step's fingerprint
        in the manifest, so changing one reruns the step.
    open_params : bool
        Whether parameters not in ``defaults`` are accepted (passed through as given).
    version : str
        Bumped when the step's output changes for the same input and parameters.
    validate : callable, optional
        ``validate(params)`` raises :class:`StepSpecError` for bad values.
    """

    name: str
    suffix: str
    consumes: str
    produces: str
    module: str
    run: StepFunction
    defaults: Mapping[str, Any] = field(default_factory=dict)
    open_params: bool = False
    version: str = "1"
    validate: Callable[[dict[str, Any]], None] | None = None


# --------------------------------------------------------------- implementations


def run_hdr_static(input_path: str, output_path: str, params: dict[str, Any]) -> None:
    """``hdr-static`` step: capture file -> HDR EXR (no parameters)."""
    from ..formats import read_capture, write_hdr
    from ..hdr_static import hdr_static
    from ..provenance import record_inputs

    img = hdr_static(read_capture(input_path))
    record_inputs(img.meta, [input_path])
    write_hdr(output_path, img)


def run_deblur(input_path: str, output_path: str, params: dict[str, Any]) -> None:
    """``deblur`` step: capture file -> HDR EXR through :mod:`stages.deblur`."""
    from ..formats import HDRImage, read_capture, write_hdr

    mod = importlib.import_module("stages.deblur")
    hook = getattr(mod, "batch_step", None)
    if callable(hook):
        hook(input_path, output_path, dict(params))
        return
    fn = getattr(mod, "deblur", None)
    if not callable(fn):
        raise VetError(
            "stages.deblur provides neither batch_step() nor deblur(); cannot run the deblur step"
        )
    result = fn(read_capture(input_path), **params)
    if isinstance(result, tuple | list):
        result = next((r for r in result if isinstance(r, HDRImage)), None)
    if not isinstance(result, HDRImage):
        raise VetError("stages.deblur.deblur() returned no HDR image")
    from ..provenance import record_inputs

    record_inputs(result.meta, [input_path])
    write_hdr(output_path, result)


#: What ``--param deblur.NAME=VALUE`` may set, and the values each takes (``vet deblur``'s
#: options).
DEBLUR_PARAMS = {
    "method": ("vet", "paper"),
    "motion_init": ("layers", "farneback", "dis", "truth", "zero", None),
    "fuse_still": (True, False, "auto", None),
    "tile": ("auto", "none", None, "an integer >= 64"),
}


def _validate_deblur(params: dict[str, Any]) -> None:
    """Refuse deblur parameters that ``stages.deblur.deblur`` would reject per capture."""
    for key, value in params.items():
        if key not in DEBLUR_PARAMS:
            raise StepSpecError(
                f"step 'deblur' has no parameter {key!r} (its parameters: "
                f"{', '.join(DEBLUR_PARAMS)})"
            )
        allowed = DEBLUR_PARAMS[key]
        if key == "tile" and isinstance(value, int) and not isinstance(value, bool):
            from ..deblur.tiles import MIN_TILE_PX

            if value >= MIN_TILE_PX:
                continue
        if not any(value is a or (isinstance(a, str) and value == a) for a in allowed):
            shown = ", ".join("null" if a is None else str(a).lower() for a in allowed)
            raise StepSpecError(f"deblur {key} must be one of {shown}, not {value!r}")
    if params.get("method") == "paper" and params.get("fuse_still") not in (None, "auto"):
        raise StepSpecError("deblur fuse_still applies to method vet only")


def run_tonemap(input_path: str, output_path: str, params: dict[str, Any]) -> None:
    """``tonemap`` step: HDR EXR -> display image (PNG by default)."""
    from ..formats import read_hdr
    from ..formats.images import write_display_image
    from ..tonemap import tonemap

    img = read_hdr(input_path)
    display = tonemap(img.radiance, operator=params["operator"], exposure=float(params["exposure"]))
    write_display_image(output_path, display, bits=int(params["bits"]))


def _validate_tonemap(params: dict[str, Any]) -> None:
    from ..tonemap import OPERATORS

    if params["operator"] not in OPERATORS:
        raise StepSpecError(
            f"tonemap operator {params['operator']!r} unknown; choose from {', '.join(OPERATORS)}"
        )
    given = params["exposure"]
    try:
        params["exposure"] = float(given)
    except (TypeError, ValueError):
        params["exposure"] = math.nan
    if not abs(params["exposure"]) <= 64:  # (NaN too)
        raise StepSpecError(
            f"tonemap exposure must be a number of stops within +/-64, not {given!r}"
        )
    if params["bits"] not in (8, 16):
        raise StepSpecError(f"tonemap bits must be 8 or 16, not {params['bits']!r}")


#: Registered steps by name.
STEPS: dict[str, Step] = {}
#: Order in which chosen steps run for a capture.
PIPELINE_ORDER: list[str] = []


def register_step(step: Step, before: str | None = None) -> None:
    """Add (or replace) a step; ``before`` places it ahead of another in the pipeline."""
    STEPS[step.name] = step
    if step.name in PIPELINE_ORDER:
        PIPELINE_ORDER.remove(step.name)
    if before is not None and before in PIPELINE_ORDER:
        PIPELINE_ORDER.insert(PIPELINE_ORDER.index(before), step.name)
    else:
        PIPELINE_ORDER.append(step.name)


register_step(Step("hdr-static", ".hdr.exr", "capture", "hdr", "stages.hdr_static", run_hdr_static))
register_step(
    Step(
        "deblur",
        ".deblur.exr",
        "capture",
        "hdr",
        "stages.deblur",
        run_deblur,
        open_params=True,
        validate=_validate_deblur,
    )
)
register_step(
    Step(
        "tonemap",
        ".png",
        "hdr",
        "display",
        "stages.tonemap",
        run_tonemap,
        defaults={"operator": "log", "exposure": 0.0, "bits": 8},
        validate=_validate_tonemap,
    )
)

#: Steps run when none are named.
DEFAULT_STEPS = ("hdr-static", "tonemap")


def unavailable_reason(name: str) -> str | None:
    """Why step ``name`` cannot run here, or ``None`` when it can."""
    step = STEPS[name]
    try:
        if importlib.util.find_spec(step.module) is None:
            return f"step {name!r} is not available in this version of vet ({step.module} does not exist yet)"
        importlib.import_module(step.module)
    except Exception as exc:  # an optional dependency missing, a broken install
        return f"step {name!r} is not available: importing {step.module} failed ({type(exc).__name__}: {exc})"
    return None


def check_available(names: list[str]) -> None:
    """Raise :class:`VetError` naming the first chosen step that cannot run here."""
    for name in names:
        reason = unavailable_reason(name)
        if reason:
            raise VetError(reason)


def parse_steps(text: str | list[str] | tuple[str, ...] | None) -> list[str]:
    """Chosen steps (comma-separated or a list) in pipeline order, checked.

    Raises
    ------
    StepSpecError
        Unknown or repeated step, or ``tonemap`` without an HDR step before it.
    """
    if text is None:
        names = list(DEFAULT_STEPS)
    elif isinstance(text, str):
        names = [s.strip() for s in text.split(",") if s.strip()]
    else:
        names = list(text)
    if not names:
        raise StepSpecError("no steps given")
    for n in names:
        if n not in STEPS:
            raise StepSpecError(f"unknown step {n!r}; choose from {', '.join(PIPELINE_ORDER)}")
    if len(set(names)) != len(names):
        raise StepSpecError("a step is named twice in --steps")
    ordered = [n for n in PIPELINE_ORDER if n in names]
    for i, n in enumerate(ordered):
        if STEPS[n].consumes == "hdr" and not any(STEPS[m].produces == "hdr" for m in ordered[:i]):
            raise StepSpecError(f"step {n!r} needs an HDR step before it (hdr-static or deblur)")
    return ordered


def resolve_params(
    steps: list[str], overrides: Mapping[str, Mapping[str, Any]] | None = None
) -> dict[str, dict[str, Any]]:
    """Each chosen step's parameters: its defaults updated with ``overrides[step]``.

    Raises
    ------
    StepSpecError
        Parameters for a step that is not chosen or not known, unknown parameter names,
        or bad values.
    """
    overrides = dict(overrides or {})
    for name in overrides:
        if name not in STEPS:
            raise StepSpecError(f"parameter for unknown step {name!r}")
        if name not in steps and overrides[name]:
            raise StepSpecError(f"parameters given for step {name!r}, which is not in --steps")
    out: dict[str, dict[str, Any]] = {}
    for name in steps:
        step = STEPS[name]
        params = dict(step.defaults)
        for key, value in dict(overrides.get(name, {})).items():
            if key not in params and not step.open_params:
                known = ", ".join(sorted(step.defaults)) or "none"
                raise StepSpecError(
                    f"step {name!r} has no parameter {key!r} (its parameters: {known})"
                )
            params[key] = value
        if step.validate is not None:
            step.validate(params)
        out[name] = params
    return out
