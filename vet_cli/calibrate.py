"""vet calibrate: measure a rig's LCoS homography, dark current, bias, leakage and gain ratio."""

from __future__ import annotations

import click

from ._common import Progress, command, log, verbosity_options
from .options import rig_options, rig_overrides, rig_profile_choice, rig_profile_option
from .outputs import Output, check_outputs, force_option, profile_file, scene_file
from .params import SEED, SIZE


@click.command(
    "calibrate",
    help="""Calibrate RIG (or recorded frames) into the calibration file CAL.

The LCoS shows Gray-code patterns (and their inverses) to the VET camera looking at a
flat bright field; decoding them gives the cell each pixel sees and, by RANSAC, the
cell -> pixel homography. Dark frames at two exposures give bias and dark current,
the LCoS all closed vs all open gives the leakage map, and the measurement camera on
the same field gives the measurement-to-VET gain ratio. CAL (.exr or .npz) holds the
maps as layers and the numbers in its metadata (vet info CAL); vet capture
--calibration CAL uses it.

With --rig sim the emulated rig images a flat field; --true-homography, --leakage,
--dark-current and --lcos set the truth that calibration must find, and the errors
against it are logged and stored. With --frames FOLDER the frames come from files
(PNG, TIFF, or camera raws through rawpy; names in docs/calibration.md), including a
chessboard both cameras see and a switching series, from which the measurement
camera's mapping, the trigger offset and the switching time are found, the
measurement camera's gain and vignetting (its flat field through that mapping), and
the trigger jitter and drop rate (meas_timestamps.csv: frame_id,timestamp_s per frame
the measurement camera gave on the subframe clock).

A rig (sim or RIG.toml) is recorded live into that layout through its own devices and
calibrated from it as --frames would: the flat fields and Gray code, --board-poses
chessboard poses with all cells open (on a real rig you place the board when prompted
and press Enter; standard input must be a terminal), a switching series (every cell
closed at subframe 20 on the subframe clock, the VET exposure stepped across it; a
camera whose exposure the host cannot set skips it with a warning) and --clock-frames
subframes of the measurement camera's frame ids and timestamps. --save-frames DIR keeps
the recorded folder (a rig file otherwise records into a temporary folder that is then
removed; --rig sim without --save-frames renders the parts from its truth).

\b
Example:
  vet calibrate --rig sim --size 320x256 --lcos 256x150 --true-homography example \\
      --leakage 0.003 --dark-current 15 -o cal.exr
  vet calibrate --frames recorded/ --lcos 1024x600 -o cal.npz
  vet calibrate --rig sim --size 320x240 --save-frames frames/ -o cal.npz
  vet calibrate --rig rig.toml --board-poses 4 --save-frames frames/ -o cal.npz
  vet capture --rig sim --size 320x256 --calibration cal.exr -o cap1
""",
)
@click.option(
    "--rig",
    "rig_spec",
    default=None,
    help="'sim' or a rig TOML file (its [params] also serve --frames).",
)
@click.option(
    "-o", "--output", required=True, help="Calibration file (.exr or .npz), or - for stdout (EXR)."
)
@click.option(
    "--frames", "frames_dir", default=None, metavar="FOLDER", help="Calibrate from recorded frames."
)
@click.option(
    "--true-homography",
    default=None,
    metavar="H",
    help="[sim] True cell->pixel homography: 'a,b,c,d,e,f,g,h,i', a JSON file, or 'example' "
    "(a rotated, zoomed, keystoned one) [the nominal one].",
)
@click.option(
    "--save-frames",
    default=None,
    metavar="DIR",
    help="Record the rig's frames live into DIR in the --frames layout (an empty or new "
    "folder; --force replaces the frames of a used one) and calibrate from it.",
)
@click.option(
    "--board-poses",
    type=click.IntRange(0, 99),
    default=2,
    show_default=True,
    help="[live] Chessboard poses recorded (a real rig prompts for each on a terminal); 0: "
    "none, and no measurement-to-VET mapping.",
)
@click.option(
    "--clock-frames",
    type=click.IntRange(0, 2_000_000),
    default=20000,
    show_default=True,
    help="[live] Subframes the measurement camera's frame ids and timestamps are recorded "
    "over (trigger jitter, drop rate); 0: none.",
)
@click.option("--scene", default=None, help="[sim] Scene instead of the flat field.")
@click.option("--size", type=SIZE, default=None, help="[sim] Sensor size [1280x1024].")
@click.option("--seed", type=SEED, default=0, show_default=True, help="[sim] Noise seed.")
@click.option(
    "--average",
    type=click.IntRange(1, 1000),
    default=4,
    show_default=True,
    help="Frames averaged per dark, open, closed and flat exposure.",
)
@rig_options
@rig_profile_option(default="realistic")
@force_option
@verbosity_options
@command("calibrate")
def cli(
    rig_spec: str | None,
    output: str,
    frames_dir: str | None,
    true_homography: str | None,
    save_frames: str | None,
    board_poses: int,
    clock_frames: int,
    scene: str | None,
    size: tuple[int, int] | None,
    seed: int,
    average: int,
    force: bool,
    **kwargs,
) -> None:
    from stages import calibrate as c

    if rig_spec is None and frames_dir is None:
        raise click.UsageError("give --rig sim|RIG.toml or --frames FOLDER")
    if save_frames is not None and (rig_spec is None or frames_dir is not None):
        raise click.UsageError(
            "--save-frames records a rig live: give --rig sim|RIG.toml, not --frames"
        )
    check_outputs(
        [Output("-o", output), Output("--save-frames", save_frames, "folder")],
        force,
        inputs=[
            ("--rig", None if rig_spec == "sim" else rig_spec),
            ("--frames", frames_dir),
            ("--scene", scene_file(scene)),
            ("--rig-profile", profile_file(kwargs.get("rig_profile"))),
        ],
    )
    with Progress("calibrate") as progress:
        cal = c.run_calibration(
            rig_spec,
            frames_dir,
            rig_overrides(kwargs),
            profile=rig_profile_choice(kwargs),
            size=size,
            true_homography=true_homography,
            seed=seed,
            scene=scene,
            settings=c.AcquisitionSettings(frames_per_exposure=average),
            progress=progress,
            save_frames=save_frames,
            force=force,
            live=c.LiveSettings(clock_frames=clock_frames, board_poses=board_poses),
        )
    c.write_calibration(output, cal)
    fit, s = cal.homography_fit, cal.summary
    if cal.homography is not None:
        log.info(
            "homography: %d pixels decoded, reprojection RMS %.3f px, decode agreement %.4f",
            fit["n_points"],
            fit["reprojection_rms_px"],
            fit["decode_agreement"],
        )
    log.info(
        "leakage %s, dark current %s e-/s, gain ratio %s",
        *(
            f"{s[k]:.5g}" if k in s else "-"
            for k in ("leakage_median", "dark_current_median_e_s", "gain_ratio_median")
        ),
    )
    if cal.parts:
        log.info(
            "parts: %s",
            ", ".join(f"{k} {v:.4g}" for k, v in cal.parts.items() if isinstance(v, float)),
        )
    errs = cal.provenance.get("errors_vs_truth")
    if errs:
        log.info("vs emulated truth: %s", ", ".join(f"{k} {v:.3g}" for k, v in errs.items()))
