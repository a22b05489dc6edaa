"""The declared schema (issue 22 item 1): metadata that is JSON but wrong is refused
before any work, exit 1, one line naming the field and the allowed range."""

from __future__ import annotations

import copy
import json
import re

import numpy as np
import pytest
from click.testing import CliRunner

from stages.errors import FormatError, InputError
from stages.formats import schema
from stages.formats.capture import write_capture
from stages.formats.hdr import HDRImage, write_hdr
from stages.formats.layered import read_layered, write_layered
from vet_cli.main import cli


@pytest.fixture(scope="module")
def capture_meta(tmp_path_factory):
    """A valid small capture (npz) and its metadata."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", (48, 40))
    cap = simulate(scene, parse_motion("none"), RigParams(sensor_size=(48, 40)), seed=1)["vet"]
    path = tmp_path_factory.mktemp("schema") / "c.npz"
    write_capture(path, cap)
    return path, read_layered(path)


def _mutated(tmp_path, source, change, name="bad.npz"):
    data = copy.deepcopy(source)
    change(data.meta)
    out = tmp_path / name
    write_layered(out, data)
    return out


def _hdr_static(path):
    result = CliRunner().invoke(cli, ["hdr-static", str(path), "-o", str(path) + ".hdr.exr"])
    return result.exit_code, result.stderr.strip().splitlines(), result.stdout


def _set(path: str, value):
    def change(meta):
        keys = path.split(".")
        d = meta
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value

    return change


# The issue's cases: (change, words the one-line message must hold).
ISSUE_CASES = {
    "sensor disagrees with pixels": (_set("rig.sensor_size", [64, 40]), "sensor_size"),
    "sensor 10^6 x 10^6": (
        _set("rig.sensor_size", [10**6, 10**6]),
        "rig.sensor_size.0: must be less than or equal to 65536",
    ),
    "LCoS 10^6 x 10^6": (
        _set("rig.lcos_cells", [10**6, 10**6]),
        "rig.lcos_cells.0: must be less than or equal to 16384",
    ),
    "LCoS misses the sensor": (
        _set("rig.homography", [[1, 0, 5000], [0, 1, 5000], [0, 0, 1]]),
        "rig.lcos_cells: the 1024x600 LCoS grid, through the homography, misses the 48x40 sensor",
    ),
    "subframe 1e-12 s": (
        _set("rig.subframe_s", 1e-12),
        "rig.subframe_s: 1e-12 s gives 1e+12 subframes per frame; allowed at most 100000",
    ),
    "radiance scale 0": (_set("radiance_scale", 0), "radiance_scale: must be greater than 0"),
    "provenance of the wrong type": (
        _set("provenance", "made by hand"),
        "provenance: must be a valid list",
    ),
    "provenance entry of the wrong type": (
        _set("provenance", [{"step": 3}]),
        "provenance.0.step: must be a valid string (got 3)",
    ),
    "string for a number": (
        _set("rig.frame_s", "1"),
        "rig.frame_s: must be a valid number (got '1')",
    ),
    "bool for an int": (_set("rig.adc_bits", True), "rig.adc_bits: must be a valid integer"),
    "NaN": (_set("rig.leakage", float("nan")), "rig.leakage: must be a finite number"),
    "unknown rig parameter": (_set("rig.shutter", 1), "rig.shutter: Extra inputs"),
    "bins without times": (_set("measure_times", None), "measure_times: none time bins for"),
    "bin outside the frame": (
        _set("measure_times", [[0.0, 0.5], [0.5, 2.0], [0, 0.1], [0, 0.1]]),
        "measure_times.1: [0.5, 2.0] s; allowed 0 <= start < end <= frame_s",
    ),
    "unknown method": (_set("method", "magic"), "method: must be 'vet', 'long', 'short'"),
    # Found by make test-slow's fuzz campaign: a bin's subframe count read as int('').
    "subframe count not a number": (
        _set("measure_subframes", [3, 2, "", 2]),
        "measure_subframes.2: must be a valid integer (got '')",
    ),
    "channels disagree": (_set("channels", ["Q"]), "channels: ['Q'] but layer 'I' holds"),
    "format version": (_set("format_version", 2), "format_version: must be 1"),
    "kind not a string": (_set("kind", ["capture"]), "kind: must be a string"),
}


@pytest.mark.parametrize("case", sorted(ISSUE_CASES))
def test_wrong_metadata_is_refused_naming_the_field(tmp_path, capture_meta, case):
    change, words = ISSUE_CASES[case]
    _, source = capture_meta
    bad = _mutated(tmp_path, source, change)
    code, err, out = _hdr_static(bad)
    assert code == 1 and out == ""
    assert len(err) == 1 and err[0].startswith("vet hdr-static: error: "), err
    assert words in err[0], err[0]
    assert not (tmp_path / "bad.npz.hdr.exr").exists()


def test_valid_capture_passes(tmp_path, capture_meta):
    path, _ = capture_meta
    code, err, _ = _hdr_static(path)
    assert code == 0, err


def test_the_same_check_guards_exr(tmp_path, capture_meta):
    _, source = capture_meta
    bad = _mutated(tmp_path, source, _set("rig.subframe_s", 1e-12), "bad.exr")
    with pytest.raises(FormatError, match=r"bad.exr: rig.subframe_s: 1e-12 s gives"):
        read_layered(bad)


def test_hdr_and_motion_and_calibration_metadata_are_checked(tmp_path):
    img = HDRImage(np.ones((4, 4, 1), np.float32), ["Y"], {"radiance_scale": -1.0})
    write_hdr(tmp_path / "h.exr", img)
    with pytest.raises(FormatError, match="radiance_scale: must be greater than 0"):
        read_layered(tmp_path / "h.exr")
    write_hdr(tmp_path / "u.exr", HDRImage(np.ones((4, 4, 1), np.float32), ["Y"], {"units": "W"}))
    with pytest.raises(FormatError, match="units: must be 'scene', 'DN/s' or 'unknown'"):
        read_layered(tmp_path / "u.exr")
    img = HDRImage(np.ones((4, 4, 1), np.float32), ["Y"], {}, mask=np.full((4, 4), 7, np.uint8))
    write_hdr(tmp_path / "m.exr", img)
    with pytest.raises(FormatError, match=r"mask: codes \[7\] not in mask_codes \[0, 1, 2, 3, 4\]"):
        read_layered(tmp_path / "m.exr")
    from stages.formats.layered import Layered

    field = Layered(meta={"kind": "motion", "units": "m/s"})
    field.add("motion", np.zeros((4, 4, 2), np.float32), ["u", "v"])
    write_layered(tmp_path / "f.npz", field)
    with pytest.raises(FormatError, match="units: must be 'px/s'"):
        read_layered(tmp_path / "f.npz")
    cal = Layered(meta={"kind": "calibration", "sensor_size": "4x4", "lcos_cells": [2, 2]})
    cal.add("leakage", np.zeros((4, 4, 1), np.float32), ["Y"])
    write_layered(tmp_path / "c.npz", cal)
    with pytest.raises(FormatError, match="sensor_size: must be a valid list"):
        read_layered(tmp_path / "c.npz")


def test_rig_file_fields_are_checked(tmp_path):
    from stages.devices.rigs import load_rig_file

    good = (
        '[lcos]\nurl = "/dev/ttyACM0"\n[measurement_camera]\nsource = "/dev/video0"\n'
        '[vet_camera]\nsource = "/dev/video1"\n'
    )
    p = tmp_path / "rig.toml"
    p.write_text(good)
    assert load_rig_file(p)["lcos"]["url"] == "/dev/ttyACM0"
    cases = {
        '[params]\nsubframe_s = "fast"\n': "params.subframe_s: must be a valid number",
        "[params]\nsensor_size = [1000000, 1000000]\n": "params.sensor_size.0: must be less",
        "[params]\nframe_s = 1.0\nsubframe_s = 1e-12\n": "params.subframe_s: 1e-12 s gives",
        "[params]\nfram_s = 1.0\n": "params.fram_s: Extra inputs are not permitted",
    }
    for extra, words in cases.items():
        p.write_text(extra + good)
        with pytest.raises(FormatError, match=words):
            load_rig_file(p)
    p.write_text(good.replace('url = "/dev/ttyACM0"', "url = \"/dev/ttyACM0\"\nbaudrate = 'x'"))
    with pytest.raises(FormatError, match="lcos.baudrate: must be a valid integer"):
        load_rig_file(p)


def test_calibration_folder_rig_toml_is_checked(tmp_path):
    from stages.calibrate.recorded import _folder_params

    (tmp_path / "rig.toml").write_text('[params]\nleakage = "none"\n')
    with pytest.raises(FormatError, match=r"rig.toml: \[params\]: leakage: must be a valid number"):
        _folder_params(tmp_path)


def test_damaged_manifest_is_set_aside_naming_the_field(tmp_path):
    from stages.batch.manifest import MANIFEST_NAME, Manifest

    good = {"format": "vet-batch-manifest", "format_version": 1, "captures": {}}
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(good))
    assert Manifest.load(tmp_path).load_warning is None
    bad = copy.deepcopy(good)
    bad["captures"]["a.exr"] = {"input": {"path": "a.exr", "size": "big"}, "status": "ok"}
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(bad))
    warning = Manifest.load(tmp_path).load_warning
    assert "captures.a.exr.input.size: must be a valid integer" in warning
    (tmp_path / MANIFEST_NAME).write_text("[" * 100_000 + "]" * 100_000)
    assert "nested more than" in Manifest.load(tmp_path).load_warning


def test_rig_params_refuse_too_many_subframes():
    from stages.rig import RigParams

    with pytest.raises(InputError, match="at most 100000 subframes"):
        RigParams(subframe_s=1e-9)


def test_every_model_declares_a_json_schema():
    for model in (*schema.META_MODELS.values(), schema.RigFile, schema.Manifest):
        assert model.model_json_schema()["properties"]


def test_provenance_inputs_are_file_records_or_names(tmp_path, capture_meta):
    """What stages.provenance records (path, bytes, sha256) and a rig's name both pass;
    a record with a malformed hash is refused naming the field."""
    _, source = capture_meta
    good = {"path": "cap.exr", "bytes": 12, "sha256": "ab" * 32}
    chain = [{"step": "capture", "inputs": ["sim"]}, {"step": "x", "inputs": [good]}]
    ok = _mutated(tmp_path, source, _set("provenance", chain), "ok.npz")
    assert read_layered(ok).meta["provenance"][1]["inputs"] == [good]
    chain[1]["inputs"] = [{"path": "cap.exr", "sha256": "xyz"}]
    bad = _mutated(tmp_path, source, _set("provenance", chain), "bad.npz")
    with pytest.raises(FormatError, match=r"provenance\.1\.inputs\.0"):
        read_layered(bad)


def test_one_rig_schema_the_dataclass_table():
    """Issue 53: the files' rig model is built from RigParams's own fields (types, ranges,
    defaults and relations written once): the same names and defaults, the same refusals
    in code (InputError) and in files (FormatError)."""
    import dataclasses
    import inspect

    from stages.rig import RIG_MODEL, RigParams

    assert schema.Rig is RIG_MODEL
    fields = {f.name: f for f in dataclasses.fields(RigParams)}
    assert set(RIG_MODEL.model_fields) == set(fields)
    default = RIG_MODEL()
    for name, f in fields.items():
        want = f.default_factory() if f.default is dataclasses.MISSING else f.default
        assert getattr(default, name) == want, name
    assert "0.99975" not in inspect.getsource(schema)  # (no second table of defaults)
    for bad, words in (
        ({"drop_rate": 0.999999}, "drop_rate: must be less than or equal to 0.5"),
        ({"homography": [[1e300, 0, 0], [0, 1, 0], [0, 0, 1]]}, "homography: condition"),
        ({"sensor_size": (32, 24), "measure_size": (1, 1)}, "measure_size: the 1x1"),
        ({"subframe_s": 2.0}, "subframe_s: 2.0 s is longer than the frame"),
    ):
        with pytest.raises(InputError, match=re.escape(f"invalid rig: {words}")):
            RigParams(**bad)
        with pytest.raises(FormatError, match=re.escape(f"f: {words}")):
            schema.validate(schema.Rig, {k: list(v) if isinstance(v, tuple) else v
                                         for k, v in bad.items()}, "f")  # fmt: skip
