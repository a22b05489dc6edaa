"""What ``vet calibrate`` does: choose recorded frames, the emulated rig or a rig file."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..rig import RigParams
from .acquire import AcquisitionSettings
from .calfile import Calibration
from .emulated import calibrate_sim, compare_to_truth
from .frames import ProgressFn
from .geometry import parse_homography
from .live import AskFn, LiveSettings, check_live, record_rig_folder
from .recorded import calibrate_from_folder

log = logging.getLogger("vet.calibrate")


def run_calibration(
    rig_spec: str | None,
    frames: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    *,
    size: tuple[int, int] | None = None,
    true_homography: str | None = None,
    seed: int = 0,
    scene: str | None = None,
    settings: AcquisitionSettings | None = None,
    progress: ProgressFn | None = None,
    profile: str = "ideal",
    save_frames: str | Path | None = None,
    force: bool = False,
    live: LiveSettings | None = None,
) -> Calibration:
    """What ``vet calibrate`` does: from recorded ``frames``, the emulated rig, or a rig file.

    Parameters
    ----------
    rig_spec : str or None
        ``"sim"``, a rig TOML file, or None (only with ``frames``).
    frames : path, optional
        Folder of recorded frames (:func:`calibrate_from_folder`); a rig file's
        ``[params]`` and ``overrides`` then describe the rig.
    overrides : dict, optional
        RigParams overrides (on ``sim``: the emulated truth).
    size, true_homography, seed, scene, profile :
        Emulated rig only: sensor (width, height); the true homography as text for
        :func:`parse_homography`; noise seed; a scene instead of the flat field; the rig
        profile (:func:`stages.optics.rig_profile`) whose parts are found too.
    settings : AcquisitionSettings, optional
    progress : callable(done, total), optional
    save_frames : path, optional
        Record the rig's calibration frames live into this folder in the ``--frames``
        layout (:func:`.live.record_rig_folder`; a non-empty folder only with ``force``)
        and calibrate from the folder, as ``--frames`` would. On ``sim`` the provenance
        gets the emulated truth's parts and ``errors_vs_truth``
        (:func:`.emulated_folder.compare_parts_to_truth`). A rig file is always recorded
        this way, into a temporary folder (removed afterwards) without ``save_frames``.
    live : LiveSettings, optional
        What the live recording records beyond the flat fields (chessboard poses, the
        frame clock's length, the switching series).

    Returns
    -------
    Calibration
    """
    overrides = dict(overrides or {})
    if frames is not None:
        params = None
        if rig_spec not in (None, "sim") or overrides:
            base: dict[str, Any] = {}
            if rig_spec not in (None, "sim"):
                from ..devices.rigs import load_rig_file

                base = dict(load_rig_file(rig_spec).get("params", {}))
            params = RigParams.from_dict({**base, **overrides})
        return calibrate_from_folder(frames, params, progress=progress)
    if rig_spec is None:
        raise InputError("nothing to calibrate: give a rig or a folder of frames")
    if save_frames is not None and rig_spec == "sim":
        if true_homography or scene:
            raise InputError(
                "saving frames needs the emulated rig (--rig sim) with its flat field and "
                "nominal homography"
            )
        return _calibrate_saved(
            save_frames, size, overrides, seed, profile, settings, force, progress, live
        )
    if rig_spec == "sim":
        from ..optics import rig_profile

        wh = size or RigParams().sensor_size
        cells = rig_profile(profile, wh, **overrides).lcos_cells  # (the profile's grid)
        true_h = None if true_homography is None else parse_homography(true_homography, cells, wh)
        return calibrate_sim(wh, overrides, true_h, seed, scene, progress, settings, profile)
    from ..devices.rigs import load_rig_file, open_rig

    if overrides or true_homography or size or scene:
        log.warning(
            "calibrate: emulated-rig and rig options are ignored with a rig file "
            "(rig parameters belong in its [params])"
        )
    load_rig_file(rig_spec)  # a bad rig file first (exit 1)
    check_live(None, live or LiveSettings())  # then before any device is opened
    with open_rig(rig_spec) as rig:
        return calibrate_live(rig, save_frames, settings, live, force, progress)


def calibrate_live(
    rig: Any,
    save_frames: str | Path | None = None,
    settings: AcquisitionSettings | None = None,
    live: LiveSettings | None = None,
    force: bool = False,
    progress: ProgressFn | None = None,
    ask: AskFn | None = None,
) -> Calibration:
    """Record an open ``rig``'s calibration frames live (:func:`.live.record_rig_folder`)
    into ``save_frames`` (a temporary folder, removed afterwards, when None) and calibrate
    from the folder (:func:`calibrate_from_folder`). The provenance's ``live`` holds the
    rig and what was recorded; ``source`` is the rig when the folder was temporary."""
    if save_frames is not None:
        info = record_rig_folder(rig, save_frames, settings, live, force, progress, ask)
        cal = calibrate_from_folder(save_frames, progress=progress)
    else:
        check_live(rig, live or LiveSettings(), ask)
        with tempfile.TemporaryDirectory(prefix="vet-cal-") as tmp:
            folder = Path(tmp) / "frames"
            info = record_rig_folder(rig, folder, settings, live, False, progress, ask)
            cal = calibrate_from_folder(folder, progress=progress)
        cal.provenance["source"] = f"rig:{rig.name}"
    cal.provenance["live"] = {"rig": rig.name, "rig_meta": dict(rig.meta), **info}
    return cal


def _calibrate_saved(
    folder: str | Path,
    size: tuple[int, int] | None,
    overrides: dict[str, Any],
    seed: int,
    profile: str,
    settings: AcquisitionSettings | None,
    force: bool,
    progress: ProgressFn | None,
    live: LiveSettings | None,
) -> Calibration:
    """Record the emulated rig's frames live into ``folder`` (:func:`calibrate_live`),
    calibrate from it, compare with the emulated truth."""
    from ..optics import PARTS
    from .emulated import open_sim_calibration_rig
    from .emulated_folder import compare_parts_to_truth

    with open_sim_calibration_rig(size, overrides, None, seed, None, profile) as rig:
        truth = rig.params
        cal = calibrate_live(rig, folder, settings, live, force, progress)
    log.info("calibrate: emulated rig's frames written to %s", folder)
    d = truth.to_dict()
    cal.provenance["emulated_truth"] = {
        k: d[k] for k in ("leakage", "dark_current_e_s", "measure_fraction", *PARTS) if k in d
    }
    errors = compare_to_truth(
        cal,
        np.asarray(truth.homography),
        truth.leakage,
        truth.dark_current_e_s,
        truth.measure_fraction,
    )
    errors.update(compare_parts_to_truth(cal, truth))
    cal.provenance["errors_vs_truth"] = errors
    return cal
