"""vet evaluate: every method on one scene and motion; table, chart and pictures."""

from __future__ import annotations

import click

from stages.evaluate import EXTRA_ROWS, ROWS

from ._common import Progress, command, log, verbosity_options
from .options import (
    rig_options,
    rig_overrides,
    rig_profile_choice,
    rig_profile_option,
    scale_choice,
    scale_options,
)
from .outputs import (
    REPORT_FOLDER_FILES,
    Output,
    check_outputs,
    force_option,
    motion_file,
    profile_file,
    scene_file,
)
from .params import MOTION, SEED, SIZE


def _methods(ctx: click.Context, param: click.Parameter, value: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(v.strip() for v in value.split(",") if v.strip()))
    bad = [n for n in names if n not in ROWS + EXTRA_ROWS]
    if bad or not names:
        raise click.BadParameter(
            f"unknown method {', '.join(bad) or '(none)'}; choose from "
            f"{', '.join(ROWS + EXTRA_ROWS)}"
        )
    return tuple(n for n in ROWS + EXTRA_ROWS if n in names)


@click.command(
    "evaluate",
    help="""Run every method on SCENE moving with --motion and compare them.

One simulation pass renders the VET capture and the comparison methods (standard long
and short exposures, adaptive attenuation) from the same scene, motion and noise. Each is
reconstructed (hdr-static; deblur default, published and with the true motion) and
scored in stops against the true scene, split into dark pixels (exposed the whole frame)
and bright ones. Writes results.csv, results.md, errors.png, contact_sheet.png,
exposure_time.png and motion.png into the folder given with -o.

--methods runs a subset (the comparison methods alone take seconds; each deblur takes
about a minute per megapixel); vet-static-ideal-rig (not run by default) is hdr-static
with the rig's parts ignored, beside vet-static with them (--rig-profile realistic). The rig and radiance-scale options are those of
`vet simulate`; the report states which were used.

\b
Example:
  vet evaluate builtin:interior --motion translate:30,0 --size 320x256 -o report/
""",
)
@click.argument("scene")
@click.option("-o", "--output", required=True, metavar="DIR", help="Report folder (created).")
@click.option(
    "--motion", type=MOTION, default="translate:30,0", show_default=True, help="Motion SPEC."
)
@click.option("--size", type=SIZE, default=None, help="Resample the scene to this sensor size.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed for all noise.")
@click.option(
    "--methods",
    default=",".join(ROWS),
    show_default=True,
    callback=_methods,
    help="Comma-separated table rows to run.",
)
@scale_options
@rig_options
@rig_profile_option
@force_option
@verbosity_options
@command("evaluate")
def cli(
    scene: str,
    output: str,
    motion: str,
    size: tuple[int, int] | None,
    seed: int,
    methods: tuple,
    force: bool,
    **kwargs,
) -> None:
    from stages.evaluate import results_markdown, run_evaluation, write_report

    check_outputs(
        [Output("-o", output, "folder", holds=REPORT_FOLDER_FILES)],
        force,
        inputs=[
            ("SCENE", scene_file(scene)),
            ("--motion", motion_file(motion)),
            ("--rig-profile", profile_file(kwargs.get("rig_profile"))),
        ],
    )
    scale, reach = scale_choice(kwargs)
    with Progress("evaluate", delay_s=0.0, counts=False) as progress:
        ev = run_evaluation(
            scene,
            motion,
            size,
            seed,
            rows=methods,
            progress=progress.note,
            on_step=progress,
            rig_changes=rig_overrides(kwargs),
            rig_profile=rig_profile_choice(kwargs),
            scale=scale,
            reach_subframes=reach,
        )
    write_report(ev, output)
    log.info("%s", results_markdown(ev))
