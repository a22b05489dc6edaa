"""vet evaluate: every method on one scene and motion; table, chart and pictures."""

from __future__ import annotations

import click

from ._common import command, log, verbosity_options


@click.command(
    "evaluate",
    help="""Run every method on SCENE moving with --motion and compare them.

One simulation pass renders the VET capture and the comparison methods (standard long
and short exposures, adaptive attenuation) from the same scene, motion and noise. Each is
reconstructed (hdr-static; deblur default, published and with the true motion) and
scored in stops against the true scene, split into dark pixels (exposed the whole frame)
and bright ones. Writes results.csv, results.md, errors.png, contact_sheet.png,
exposure_time.png and motion.png into the folder given with -o.

\b
Example:
  vet evaluate builtin:interior --motion translate:30,0 --size 320x256 -o report/
""",
)
@click.argument("scene")
@click.option("-o", "--output", required=True, metavar="DIR", help="Report folder (created).")
@click.option("--motion", default="translate:30,0", show_default=True, help="Motion SPEC.")
@click.option("--size", default=None, metavar="WxH", help="Resample the scene to this sensor size.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed for all noise.")
@verbosity_options
@command("evaluate")
def cli(scene: str, output: str, motion: str, size: str | None, seed: int) -> None:
    from stages.evaluate import results_markdown, run_evaluation, write_report
    from stages.scenes import parse_size

    ev = run_evaluation(
        scene, motion, parse_size(size), seed, progress=lambda m: log.info("evaluate: %s", m)
    )
    write_report(ev, output)
    log.info("%s", results_markdown(ev))
