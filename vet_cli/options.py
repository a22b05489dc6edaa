"""Options shared by several commands (rig parameters, the simulated radiance scale)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from .params import SIZE, FiniteFloatRange, non_negative, positive

# (option, RigParams field, type with the valid range, help). The ranges are those
# RigParams.validate enforces, so a bad value is a usage error before any work.
RIG_OPTIONS = [
    ("--frame-s", "frame_s", positive(), "Frame length Tf, seconds [0.99975]."),
    ("--subframe-s", "subframe_s", positive(), "Measuring subframe length, seconds [0.00758]."),
    ("--full-well", "full_well_e", positive(), "Full well, electrons [10000]."),
    ("--read-noise", "read_noise_e", non_negative(), "Read noise, electrons rms [5]."),
    ("--adc-bits", "adc_bits", click.IntRange(4, 24), "ADC depth, bits [12]."),
    ("--dark-current", "dark_current_e_s", non_negative(), "Dark current, electrons/s [10]."),
    (
        "--threshold",
        "threshold_frac",
        FiniteFloatRange(0, 1, min_open=True),
        "Closure threshold, fraction of full well [0.8].",
    ),
    ("--latency", "latency_subframes", click.IntRange(min=0), "Closure latency, subframes [1]."),
    (
        "--leakage",
        "leakage",
        FiniteFloatRange(0, 1, max_open=True),
        "LCoS leakage (closed-cell transmittance) [0.002].",
    ),
]


def rig_options(f: Callable) -> Callable:
    for opt, _field, typ, hlp in reversed(RIG_OPTIONS):
        f = click.option(opt, type=typ, default=None, help=hlp)(f)
    f = click.option(
        "--lcos",
        "lcos",
        type=SIZE,
        default=None,
        help="LCoS grid in cells [1024x600; the realistic profile: the published rig's "
        "1024x600 on 1280x1024 pixels, scaled to the sensor].",
    )(f)
    return f


def rig_profile_option(f: Callable | None = None, *, default: str = "ideal") -> Callable:
    """``--rig-profile``: the rig's optics and timing (:func:`rig_profile_choice`).
    ``default``: ``ideal`` (simulate, evaluate) or ``realistic`` (the emulated rig of
    capture and calibrate, which stands for hardware)."""
    if f is None:
        return lambda g: rig_profile_option(g, default=default)
    f = click.option(
        "--rig-profile",
        "rig_profile",
        default=default,
        show_default=True,
        metavar="ideal|realistic|FILE.toml",
        help="The rig's optics and timing: ideal (one pixel grid, sharp instant LCoS), "
        "realistic (the published rig's two cameras, relay blur, per-cell leakage, "
        "switching time, trigger offset, jitter and dropped frames) or a TOML file "
        "([params] of the rig fields, optional profile = NAME to start from). Options "
        "above override it.",
    )(f)
    return f


def rig_profile_choice(kwargs: dict[str, Any]) -> str:
    """Pop ``--rig-profile`` out of kwargs: a profile name or an existing file (else a
    usage error)."""
    import os

    from stages.optics import PROFILES

    spec = kwargs.pop("rig_profile", None) or "ideal"
    if spec not in PROFILES and not os.path.isfile(spec):
        raise click.BadParameter(
            f"{spec!r}: choose {', '.join(PROFILES)} or an existing TOML file",
            param_hint="'--rig-profile'",
        )
    return spec


def rig_overrides(kwargs: dict[str, Any]) -> dict[str, Any]:
    """Pop the rig options out of a command's kwargs as RigParams field overrides."""
    out: dict[str, Any] = {}
    for opt, field, _typ, _h in RIG_OPTIONS:
        key = opt.lstrip("-").replace("-", "_")
        val = kwargs.pop(key, None)
        if val is not None:
            out[field] = val
    lcos = kwargs.pop("lcos", None)
    if lcos:
        out["lcos_cells"] = tuple(lcos)
    if out:  # values valid alone may still disagree (a subframe longer than the frame)
        from stages.errors import InputError
        from stages.rig import RigParams

        try:
            RigParams(**out)
        except InputError as exc:
            raise click.UsageError(f"{exc} (rig options)") from None
    return out


def scale_options(f: Callable) -> Callable:
    """``--radiance-scale`` (absolute) or ``--reach-subframes`` (relative to the scene)."""
    f = click.option(
        "--reach-subframes",
        type=positive(),
        default=None,
        metavar="N",
        help="Set the radiance scale so that the scene's 99.9th-percentile luminance "
        "reaches the threshold in N measuring subframes [1]; 8 is a scene three stops "
        "dimmer.",
    )(f)
    f = click.option(
        "--radiance-scale",
        type=positive(),
        default=None,
        help="Electrons/s per scene unit [p99.9 luminance reaches the threshold in one subframe].",
    )(f)
    return f


def scale_choice(kwargs: dict[str, Any]) -> tuple[float | None, float]:
    """Pop :func:`scale_options` out of kwargs as ``(scale, reach_subframes)``."""
    scale = kwargs.pop("radiance_scale", None)
    reach = kwargs.pop("reach_subframes", None)
    if scale is not None and reach is not None:
        raise click.UsageError("give --radiance-scale or --reach-subframes, not both")
    return scale, 1.0 if reach is None else float(reach)
