"""The calibration file: :class:`Calibration`, its reading, writing and validation,
and how it changes a rig's :class:`~stages.rig.RigParams`.

Stored as a :class:`~stages.formats.layered.Layered` file with ``kind = "calibration"``
(EXR or npz): the per-pixel maps as layers, the numbers in the metadata.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from ..rig import RigParams

CALIBRATION_KIND = "calibration"


@dataclass
class Calibration:
    """A rig calibration; any part may be missing (None) when its frames were.

    Attributes
    ----------
    sensor_size : (int, int)
        VET sensor (width, height), pixels.
    lcos_cells : (int, int)
        LCoS grid (width, height), cells.
    homography : ndarray of shape (3, 3) or None
        LCoS cell coordinates -> VET pixel coordinates.
    homography_fit : dict
        ``n_points``, ``n_inliers``, ``reprojection_rms_px``, ``decode_agreement``.
    cell_x, cell_y : ndarray of shape (H, W) or None
        Decoded cell per pixel (-1 undecoded).
    bias_dn : ndarray of shape (H, W) or None
        Dark-frame intercept, DN.
    dark_current_e_s : ndarray of shape (H, W) or None
        Dark current, electrons per second.
    leakage : ndarray of shape (H, W) or None
        Closed-cell transmittance per pixel (NaN where unmeasurable; about 1 outside
        the LCoS footprint).
    gain_ratio : ndarray of shape (H, W) or None
        Measurement-camera over VET-camera signal rate per pixel.
    cell_leakage : ndarray of shape (H, W) or None
        Leakage of the LCoS cell in which each pixel's centre lies: the per-cell map
        through the relay blur (:func:`.cell_leakage.leakage_per_cell`), NaN outside the LCoS.
    summary : dict
        Scalars: ``leakage_median``, ``dark_current_median_e_s``, ``bias_median_dn``,
        ``gain_ratio_median``.
    rig : dict
        The rig parameters used (gain etc.), :meth:`RigParams.to_dict`.
    parts : dict
        The parts of a real rig found (:mod:`.parts`): RigParams fields such as
        ``measure_homography``, ``measure_k1``, ``measure_k2``, ``trigger_offset_s``,
        ``switch_s``, ``relay_blur_px``, ``measure_vignetting``, ``measure_gain`` with
        ``measure_fraction`` (their product is what a flat field measures:
        :mod:`.meas_flat`), ``trigger_jitter_s``, ``drop_rate``.
    provenance : dict
        Source (rig or folder), settings, frames used, skipped parts, software.
    """

    sensor_size: tuple[int, int]
    lcos_cells: tuple[int, int]
    homography: np.ndarray | None = None
    homography_fit: dict[str, Any] = field(default_factory=dict)
    cell_x: np.ndarray | None = None
    cell_y: np.ndarray | None = None
    bias_dn: np.ndarray | None = None
    dark_current_e_s: np.ndarray | None = None
    leakage: np.ndarray | None = None
    gain_ratio: np.ndarray | None = None
    cell_leakage: np.ndarray | None = None
    summary: dict[str, float] = field(default_factory=dict)
    rig: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    parts: dict[str, Any] = field(default_factory=dict)

    _LAYERS = (
        "cell_x",
        "cell_y",
        "bias_dn",
        "dark_current_e_s",
        "leakage",
        "gain_ratio",
        "cell_leakage",
    )
    _LAYER_NAMES = {
        "cell_x": "cell_x",
        "cell_y": "cell_y",
        "bias_dn": "bias",
        "dark_current_e_s": "dark_current",
        "leakage": "leakage",
        "gain_ratio": "gain_ratio",
        "cell_leakage": "cell_leakage",
    }

    def to_layered(self):
        """As a :class:`~stages.formats.layered.Layered` (``kind = "calibration"``)."""
        from ..formats.layered import Layered

        meta: dict[str, Any] = {
            "kind": CALIBRATION_KIND,
            "sensor_size": list(self.sensor_size),
            "lcos_cells": list(self.lcos_cells),
            "homography": None if self.homography is None else np.asarray(self.homography).tolist(),
            "homography_fit": self.homography_fit,
            "rig": self.rig,
            "provenance": self.provenance,
            **({"parts": self.parts} if self.parts else {}),
            "layer_units": {
                "cell_x": "cell",
                "cell_y": "cell",
                "bias": "DN",
                "dark_current": "e-/s",
                "leakage": "transmittance",
                "gain_ratio": "measurement/VET",
                "cell_leakage": "transmittance",
            },
            **self.summary,
        }
        out = Layered(meta=meta)
        for attr in self._LAYERS:
            arr = getattr(self, attr)
            if arr is not None:
                out.add(self._LAYER_NAMES[attr], arr, ["Y"])
        if not out.layers:
            raise InputError("the calibration measured nothing that can be stored")
        return out

    @classmethod
    def from_layered(cls, data, what: str = "calibration") -> Calibration:
        """From a :class:`~stages.formats.layered.Layered` read from a file."""
        meta = data.meta
        if meta.get("kind") != CALIBRATION_KIND:
            raise FormatError(
                f"{what}: not a calibration (kind: {meta.get('kind') or 'not a vet file'})"
            )
        try:
            hom = meta.get("homography")
            cal = cls(
                sensor_size=tuple(int(v) for v in meta["sensor_size"]),
                lcos_cells=tuple(int(v) for v in meta["lcos_cells"]),
                homography=None if hom is None else np.asarray(hom, dtype=np.float64).reshape(3, 3),
                homography_fit=dict(meta.get("homography_fit") or {}),
                rig=dict(meta.get("rig") or {}),
                provenance=dict(meta.get("provenance") or {}),
                parts=dict(meta.get("parts") or {}),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(f"{what}: calibration metadata is damaged ({exc})") from None
        for key in (
            "leakage_median",
            "dark_current_median_e_s",
            "bias_median_dn",
            "gain_ratio_median",
        ):
            if meta.get(key) is not None:
                cal.summary[key] = float(meta[key])
        for attr in cls._LAYERS:
            arr = data.layers.get(cls._LAYER_NAMES[attr])
            if arr is not None:
                setattr(cal, attr, arr[:, :, 0])
        leak = cal.cell_leakage
        if leak is not None:
            if leak.shape != (cal.sensor_size[1], cal.sensor_size[0]):
                raise FormatError(f"{what}: its cell_leakage layer is not the sensor's size")
            seen = leak[~np.isnan(leak)]
            if not (np.isfinite(seen).all() and (seen >= 0).all() and (seen < 1).all()):
                raise FormatError(f"{what}: its cell_leakage layer holds values outside [0, 1)")
        return cal


def write_calibration(path: str | Path, cal: Calibration) -> None:
    """Write atomically (EXR or npz by extension; ``-`` is stdout)."""
    from ..formats.layered import write_layered

    write_layered(path, cal.to_layered())


def read_calibration(path: str | Path) -> Calibration:
    """Read a calibration file written by :func:`write_calibration`."""
    from ..formats.layered import read_layered

    what = "standard input" if str(path) == "-" else str(path)
    return Calibration.from_layered(read_layered(path), what)


def apply_calibration(params: RigParams, cal: Calibration) -> RigParams:
    """Rig parameters with the calibrated homography, leakage, dark current and gain ratio,
    and the parts of a real rig found (``cal.parts``, which take precedence: with the
    measurement camera's gain and vignetting fitted, ``measure_fraction`` is the one in
    ``parts``, not the gain ratio's median, which holds the gain and vignetting too).

    Parameters
    ----------
    params : RigParams
        The rig as configured.
    cal : Calibration
        Must have been measured on a rig with the same LCoS grid and sensor size.

    Returns
    -------
    RigParams
        A copy; parts missing from the calibration keep their configured values.

    Raises
    ------
    InputError
        The calibration belongs to a different LCoS grid or sensor.
    """
    return params.replace(**calibration_changes(cal, params))


def calibration_changes(cal: Calibration, params: RigParams | None = None) -> dict[str, Any]:
    """The RigParams fields a calibration sets (checked against ``params`` if given)."""
    if params is not None:
        if tuple(params.lcos_cells) != tuple(cal.lcos_cells):
            raise InputError(
                f"calibration is for a {cal.lcos_cells[0]}x{cal.lcos_cells[1]} LCoS, the rig has "
                f"{params.lcos_cells[0]}x{params.lcos_cells[1]}"
            )
        if tuple(params.sensor_size) != tuple(cal.sensor_size):
            raise InputError(
                f"calibration is for a {cal.sensor_size[0]}x{cal.sensor_size[1]} sensor, the rig "
                f"has {params.sensor_size[0]}x{params.sensor_size[1]}"
            )
    out: dict[str, Any] = {"lcos_cells": tuple(cal.lcos_cells)}
    if cal.homography is not None:
        out["homography"] = np.asarray(cal.homography, float).tolist()
    s = cal.summary
    if s.get("leakage_median") is not None and np.isfinite(s["leakage_median"]):
        out["leakage"] = float(min(max(s["leakage_median"], 0.0), 0.999))
    if s.get("dark_current_median_e_s") is not None and np.isfinite(s["dark_current_median_e_s"]):
        out["dark_current_e_s"] = float(max(s["dark_current_median_e_s"], 0.0))
    if (
        s.get("gain_ratio_median") is not None
        and np.isfinite(s["gain_ratio_median"])
        and s["gain_ratio_median"] > 0
    ):
        out["measure_fraction"] = float(s["gain_ratio_median"])
    out.update(cal.parts)
    return out


def emulated_rig_truth(cal: Calibration, what: str = "calibration") -> dict[str, Any]:
    """The RigParams fields of the emulated rig that ``cal`` was made on (its provenance's
    ``emulated_truth``; empty for a real rig's): the physics ``vet capture --rig sim
    --calibration`` gives its emulated rig, whose host knows only
    :func:`calibration_changes`. FormatError if the record is damaged."""
    import dataclasses

    truth = cal.provenance.get("emulated_truth") or {}
    if not isinstance(truth, dict):
        raise FormatError(f"{what}: its record of the emulated rig's truth is damaged")
    names = {f.name for f in dataclasses.fields(RigParams)}
    out = {k: v for k, v in truth.items() if k in names}
    grid = {"sensor_size": tuple(cal.sensor_size), "lcos_cells": tuple(cal.lcos_cells)}
    try:
        RigParams(**{**grid, **out})  # (the rig of the calibration's own sensor)
    except (InputError, TypeError, ValueError) as exc:
        raise FormatError(
            f"{what}: its record of the emulated rig's truth is damaged ({exc})"
        ) from None
    return out


def calibration_overrides(path: str | Path) -> dict[str, Any]:
    """RigParams overrides from a calibration file (for ``vet capture --calibration``).

    The calibration holds only for the sensor size it was measured at
    (``Calibration.sensor_size``); :func:`apply_calibration` checks that, this does not.
    """
    return calibration_changes(read_calibration(path))
