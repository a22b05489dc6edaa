"""vet capture: drive a rig (emulated or real) through one VET frame."""

from __future__ import annotations

import click

from ._common import Progress, command, log, verbosity_options
from .options import rig_options, rig_overrides, rig_profile_choice, rig_profile_option
from .outputs import (
    CAPTURE_FOLDER_FILES,
    Output,
    check_outputs,
    force_option,
    motion_file,
    profile_file,
    scene_file,
)
from .params import MOTION, SEED, SIZE, MeasureBins, positive


@click.command(
    "capture",
    help="""Capture one VET frame with RIG into the capture folder FOLDER.

RIG is 'sim', the built-in emulated rig (emulated cameras render --scene moving with
--motion; an emulated LCoS controller in its own process speaks the real serial
protocol over a pseudo-terminal), or a rig file (TOML) describing real hardware
(see stages/devices/rigs.py). T is built from when the controller reports having
applied each closure. FOLDER gets capture.exr, measure_raw.npy, capture.log and
capture.json; hdr-static and deblur accept the folder directly.

\b
Example:
  vet capture --rig sim --scene builtin:interior --motion translate:30,0 -o cap1
  vet capture --rig sim --scene scene.exr --link-bps 3e6 -o slow_link
  vet hdr-static cap1 -o cap1.hdr.exr
""",
)
@click.option("--rig", "rig_spec", required=True, help="'sim' or a rig TOML file.")
@click.option("-o", "--output", required=True, help="Capture folder (created if missing).")
@click.option(
    "--calibration",
    default=None,
    help="Calibration file from vet calibrate: the rig's parameters as it found them, which "
    "the capture thresholds with and records (the emulated rig's own physics is its truth).",
)
@click.option(
    "--scene", default="builtin:interior", show_default=True, help="[sim] Scene to render."
)
@click.option("--motion", type=MOTION, default="none", show_default=True, help="[sim] Motion SPEC.")
@click.option("--size", type=SIZE, default=None, help="[sim] Resample the scene.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="[sim] Noise and fault seed.")
@click.option(
    "--link-bps", type=positive(), default=None, help="[sim] LCoS link rate, bit/s [unthrottled]."
)
@click.option(
    "--link-fault-rate",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    help="[sim] Per-frame probability of a corrupted, dropped or delayed frame, both ways.",
)
@click.option(
    "--disconnect-at",
    type=click.IntRange(min=0),
    default=None,
    metavar="SUBFRAME",
    help="[sim] Cut the LCoS link at this device subframe.",
)
@click.option(
    "--measure-bins",
    type=MeasureBins(),
    default="all",
    show_default=True,
    help="Measuring images stored in the capture: all (every subframe) or N time bins.",
)
@click.option(
    "--raw-stream/--no-raw-stream",
    default=True,
    show_default=True,
    help="Keep every measuring subframe in measure_raw.npy.",
)
@click.option(
    "--format", "fmt", type=click.Choice(["exr", "npz"]), default="exr", show_default=True
)
@rig_options
@rig_profile_option(default="realistic")
@force_option
@verbosity_options
@command("capture")
def cli(
    rig_spec: str,
    output: str,
    calibration: str | None,
    scene: str,
    motion: str,
    size: tuple[int, int] | None,
    seed: int,
    link_bps: float | None,
    link_fault_rate: float,
    disconnect_at: int | None,
    measure_bins: int | None,
    raw_stream: bool,
    fmt: str,
    force: bool,
    **kwargs,
) -> None:
    from stages.capture import capture_frame
    from stages.devices.rigs import SimOptions, open_rig

    # As capture_frame checks it, and a capture already there is not replaced by surprise
    # (a real one cannot be retaken): before the rig opens.
    check_outputs(
        [Output("-o", output, "folder", holds=CAPTURE_FOLDER_FILES, parents=False)],
        force,
        inputs=[
            ("--rig", None if rig_spec == "sim" else rig_spec),
            ("--calibration", calibration),
            ("--scene", scene_file(scene)),
            ("--motion", motion_file(motion)),
            ("--rig-profile", profile_file(kwargs.get("rig_profile"))),
        ],
    )
    profile = rig_profile_choice(kwargs)
    overrides = rig_overrides(kwargs)
    cal = None
    known: dict = {}
    if calibration:
        from stages.calibrate import calibration_changes, emulated_rig_truth, read_calibration

        cal = read_calibration(calibration)
        known = calibration_changes(cal)  # what the host thresholds and records with
        if rig_spec == "sim":
            # The emulated rig is the one calibrated: its sensor (the scene resampled to
            # it) and, where the calibration was made on it, its truth, which the
            # calibration only estimated.
            if size is None:
                size = tuple(int(v) for v in cal.sensor_size)
            overrides.setdefault("lcos_cells", tuple(cal.lcos_cells))
            for k, v in emulated_rig_truth(cal, calibration).items():
                overrides.setdefault(k, v)
    sim = SimOptions(
        scene=scene,
        motion=motion,
        size=size,
        seed=seed,
        link_bps=link_bps,
        link_fault_rate=link_fault_rate,
        disconnect_at_subframe=disconnect_at,
        overrides=overrides,
        profile=profile,
    )
    with open_rig(rig_spec, sim, known) as rig:
        if cal is not None and tuple(cal.sensor_size) != tuple(rig.params.sensor_size):
            from stages.errors import InputError

            raise InputError(
                f"{calibration}: made for a {cal.sensor_size[0]}x{cal.sensor_size[1]} sensor, "
                f"but the rig's is {rig.params.sensor_size[0]}x{rig.params.sensor_size[1]}"
                + (" (--size sets the emulated rig's)" if rig_spec == "sim" else "")
            )
        log.debug("capture: rig %s, sensor %dx%d", rig.name, *rig.params.sensor_size)
        with Progress("capture") as progress:
            cap = capture_frame(
                rig,
                output,
                measure_bins=measure_bins,
                raw_stream=raw_stream,
                fmt=fmt,
                progress=progress,
                cell_leakage=None if cal is None else cal.cell_leakage,
            )
    if force:
        _remove_stale(output, fmt, raw_stream)
    stats = cap.meta["capture_stats"]
    log.info(
        "captured %s: %d closures, %d late (max %d subframes), %d retransmits, %d dropped subframes",
        output,
        stats["closures"],
        stats["late_closures"]["count"],
        stats["late_closures"]["max"],
        stats["link"].get("retransmits", 0),
        len(stats["dropped_subframes"]),
    )


def _remove_stale(folder: str, fmt: str, raw_stream: bool) -> None:
    """After a --force capture, remove what the replaced capture left that this one did
    not rewrite (the other format's file; the raw stream when not kept)."""
    from pathlib import Path

    stale = ["capture.npz" if fmt == "exr" else "capture.exr"]
    if not raw_stream:
        stale += ["measure_raw.npy", "measure_raw.json"]
    for name in stale:
        p = Path(folder) / name
        if p.is_file():
            p.unlink()
            log.debug("capture: removed %s of the replaced capture", p)
