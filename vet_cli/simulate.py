"""vet simulate: render a capture from a scene with known motion."""

from __future__ import annotations

import click

from ._common import Progress, command, log, verbosity_options
from .options import (
    rig_options,
    rig_overrides,
    rig_profile_choice,
    rig_profile_option,
    scale_choice,
    scale_options,
)
from .outputs import Output, check_outputs, force_option, motion_file, profile_file, scene_file
from .params import MOTION, SEED, SIZE, MeasureBins

BUILTINS = "interior, chart"
METHODS = ["vet", "long", "short", "adaptive-attenuation"]


@click.command(
    "simulate",
    help=f"""Render what a VET rig records from SCENE moving with --motion.

SCENE is any linear image OpenImageIO reads (EXR, HDR, TIFF, PFM) or builtin:NAME, a
procedural scene (builtins: {BUILTINS}). The capture keeps the true scene at t = 0 and
the true motion for scoring. --method renders a comparison method instead of VET
from the same scene, motion and noise.

\b
Motion SPEC: none | translate:VX,VY | object:X,Y,W,H:VX,VY | rotate:DEG_PER_S[,CX,CY]
(pixels or degrees per second) | field:PATH (a motion file, as vet deblur --motion-out
writes: velocity per pixel in px/s, constant in time). Motions that change within the
frame, stored with their true trajectory: shake:AMP[,SEED] (camera shake, AMP px rms) |
oscillate:X,Y,W,H:AX,AY[,HZ] | accel:X,Y,W,H:VX,VY:AX,AY (px/s, px/s^2) |
path:X,Y,W,H:T1,DX1,DY1;T2,DX2,DY2;... (keyframes: s, px; a smooth path through them) |
spin:X,Y,W,H:DEG_PER_S (the rectangle turns about its centre) | rectangles joined by +,
each on its own path, the later in front (e.g. object:10,10,40,30:30,0+spin:90,60,40,40:90).

\b
Example:
  vet simulate builtin:interior --motion translate:30,0 --seed 1 -o cap.exr
""",
)
@click.argument("scene")
@click.option(
    "-o", "--output", required=True, help="Capture file (.exr or .npz), or - for stdout (EXR)."
)
@click.option(
    "--motion", type=MOTION, default="none", show_default=True, help="Motion SPEC (see above)."
)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed for all noise.")
@click.option("--size", type=SIZE, default=None, help="Resample the scene to this sensor size.")
@click.option(
    "--method",
    type=click.Choice(METHODS),
    default="vet",
    show_default=True,
    help="What records the scene.",
)
@click.option(
    "--measure-bins",
    type=MeasureBins(),
    default="all",
    show_default=True,
    help="Measuring images stored in the capture: all (every subframe, compact) or N "
    "time bins (0: none).",
)
@scale_options
@rig_options
@rig_profile_option
@force_option
@verbosity_options
@command("simulate")
def cli(
    scene: str,
    output: str,
    motion: str,
    seed: int,
    size: tuple[int, int] | None,
    method: str,
    measure_bins: int | None,
    force: bool,
    **kwargs,
) -> None:
    from stages.formats import write_capture
    from stages.motion import check_in_frame, parse_motion
    from stages.optics import rig_profile
    from stages.scenes import load_scene
    from stages.simulate import Radiance, simulate

    check_outputs(
        [Output("-o", output)],
        force,
        inputs=[
            ("SCENE", scene_file(scene)),
            ("--motion", motion_file(motion)),
            ("--rig-profile", profile_file(kwargs.get("rig_profile"))),
        ],
    )
    scale, reach = scale_choice(kwargs)
    profile = rig_profile_choice(kwargs)
    overrides = rig_overrides(kwargs)
    mot = parse_motion(motion)
    sc = load_scene(scene, size)
    h, w = sc.radiance.shape[:2]
    check_in_frame(mot, (h, w))
    rig = rig_profile(profile, (w, h), **overrides)
    log.debug("simulate: %s %dx%d %s, %d subframes", scene, w, h, mot.spec, rig.n_subframes)
    with Progress(f"simulate {method}") as progress:
        caps = simulate(
            sc,
            mot,
            rig,
            seed=seed,
            methods=[method],
            measure_bins=measure_bins,
            progress=progress,
            radiance=Radiance(scale, reach),
        )
    caps[method].meta["rig_profile"] = profile
    write_capture(output, caps[method])
