"""The fuzz suite (issue 22 item 3): mutated files through every command that reads them
either succeed or exit 1 with one clean line. See :mod:`tests.fuzz` for the mutators;
``make fuzz`` runs a longer campaign."""

from __future__ import annotations

import struct
import warnings
import zipfile

import numpy as np
import pytest

from stages.errors import FormatError
from stages.formats.layered import Layered, read_layered, write_layered
from tests.fuzz import Campaign

FAST_CASES = 24  # per kind of file; about 350 command runs


def _campaign(tmp_path, seed: int, cases: int, batch_cases: int) -> Campaign:
    camp = Campaign(tmp_path, seed)
    camp.run(cases, batch_cases=batch_cases)
    print(f"\nfuzz seed {seed}, {cases} cases per kind:\n{camp.summary()}")
    return camp


def test_seeds_pass_every_reader(tmp_path):
    camp = Campaign(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    for kind in ("capture", "capture_measure", "hdr", "motion", "calibration"):
        for fmt in ("npz", "exr"):
            path = tmp_path / f"{kind}.{fmt}"
            write_layered(path, camp.seeds[kind])
            reader = "capture" if kind == "capture_measure" else kind
            camp.read(reader, path, out, f"seed {path.name}", deblur=True)
    write_layered(tmp_path / "scene.exr", camp.seeds["scene"])
    camp.read("scene", tmp_path / "scene.exr", out, "seed scene.exr", deblur=True)
    (tmp_path / "rig.toml").write_text(camp.seeds["rig"])
    camp.rig(tmp_path / "rig.toml", "seed rig.toml")
    assert not camp.bad
    assert {o for _, o in camp.counts} == {"ok"}


@pytest.mark.timeout(300)
def test_fuzz_every_reader_fails_cleanly(tmp_path):
    camp = _campaign(tmp_path, seed=1, cases=FAST_CASES, batch_cases=2)
    assert not camp.bad, "\n".join(camp.bad[:20])
    assert not camp.warned, "\n".join(camp.warned[:20])
    readers = {r for r, _ in camp.counts}
    assert len(readers) == 14
    assert sum(n for (_, o), n in camp.counts.items() if o == "ok") > 50
    assert sum(n for (_, o), n in camp.counts.items() if o == "refused") > 50


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("seed", [2, 3])
def test_fuzz_long_campaign(tmp_path, seed):
    camp = _campaign(tmp_path, seed=seed, cases=300, batch_cases=10)
    assert not camp.bad, "\n".join(camp.bad[:20])


# --- what the fuzzer found (each fails before its fix) -------------------------------------


def test_capture_whose_measuring_layer_has_other_channels_is_refused(tmp_path):
    # Found by the fuzzer: a bit flip renamed M02's channel B to Z; reading stacked the
    # measuring layers and failed with "internal error (ValueError ...)".
    camp = Campaign(tmp_path)
    data = camp.seeds["capture"]
    m = data.layers["M02"]
    data.layers["M02"] = m[:, :, :2]
    data.channels["M02"] = ["R", "Z"]
    write_layered(tmp_path / "c.npz", data)
    with pytest.raises(FormatError, match=r"layer 'M02' has channels \['R', 'Z'\]; allowed"):
        read_layered(tmp_path / "c.npz")


def test_exr_header_with_undecodable_bytes_is_refused(tmp_path):
    # Found by the fuzzer: OpenImageIO's error message quoted a damaged attribute name,
    # and decoding it raised UnicodeDecodeError ("internal error").
    field = Layered(meta={"kind": "motion", "units": "px/s"})
    field.add("motion", np.zeros((8, 8, 2), np.float32), ["u", "v"])
    path = tmp_path / "m.exr"
    write_layered(path, field)
    raw = path.read_bytes()
    assert b"capDate" in raw
    path.write_bytes(raw.replace(b"capDate\0", b"capDate\x87", 1))  # name runs on
    with pytest.raises(FormatError, match="bytes that are not text"):
        read_layered(path)


def test_motion_field_of_absurd_speed_is_refused(tmp_path):
    # Found by the fuzzer: a velocity of 1e30 px/s made vet simulate run for 50 s
    # (OpenCV's border reflection walks the distance).
    field = Layered(meta={"kind": "motion", "units": "px/s"})
    v = np.zeros((24, 32, 2), np.float32)
    v[3, 4, 0] = 1e30
    field.add("motion", v, ["u", "v"])
    write_layered(tmp_path / "m.npz", field)
    with pytest.raises(FormatError, match=r"motion: velocities up to 1e\+30 px/s; allowed"):
        read_layered(tmp_path / "m.npz")


def _npy_with_header(header: str) -> bytes:
    raw = header.encode("latin1")
    raw += b" " * (64 - (10 + len(raw) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(raw)) + raw


def test_npz_member_with_unterminated_header_is_refused(tmp_path):
    # Found by the fuzzer: numpy parses .npy headers with tokenize, whose TokenError is no
    # ValueError ("internal error (TokenError ...)" in vet info and vet batch's discovery).
    from stages.batch.discover import UNREADABLE, probe_kind

    path = tmp_path / "m.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("__meta__.npy", _npy_with_header("{'descr': '<U9', 'shape': (4,"))
        zf.writestr("__channels__.npy", _npy_with_header("{}"))
    with pytest.raises(FormatError, match="member '__meta__.npy' is not a NumPy array"):
        read_layered(path)
    assert probe_kind(path) == UNREADABLE


def test_rig_homography_that_overflows_is_refused_without_warnings(tmp_path):
    # Found by the fuzzer: a homography of 1e308 printed numpy's overflow warning lines
    # above the error.
    from stages.formats.schema import Rig, validate

    h = [[1e308, 0, 0], [0, 1e308, 0], [0, 0, 1]]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(FormatError, match="rig: homography: condition number 1e"):
            validate(Rig, {"homography": h}, "rig")


def test_info_mean_of_huge_values_does_not_overflow(tmp_path):
    # Found by the fuzzer: float32 values near 3e38 made vet info's mean overflow
    # (numpy's RuntimeWarning on stderr; an error under -W error).
    from stages.formats.hdr import HDRImage, write_hdr
    from stages.info import describe

    write_hdr(tmp_path / "h.exr", HDRImage(np.full((8, 8, 1), 3e38, np.float32), ["Y"], {}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mean = describe(tmp_path / "h.exr")["layers"]["(image)"]["mean"]
    assert mean == pytest.approx(3e38, rel=1e-6)


def test_npz_member_needing_a_newer_zip_version_is_refused(tmp_path):
    # Found by the fuzzer: zipfile raises NotImplementedError ("zip file version 10.9")
    # for a member whose central directory asks for a newer zip version.
    from stages.batch.discover import UNREADABLE, probe_kind

    path = tmp_path / "c.npz"
    field = Layered(meta={"kind": "motion", "units": "px/s"})
    field.add("motion", np.zeros((4, 4, 2), np.float32), ["u", "v"])
    write_layered(path, field)
    raw = bytearray(path.read_bytes())
    at = raw.index(b"PK\x01\x02")  # first central directory entry
    raw[at + 6 : at + 8] = struct.pack("<H", 109)  # version needed to extract
    path.write_bytes(bytes(raw))
    with pytest.raises(FormatError, match="zip file version 10.9"):
        read_layered(path)
    assert probe_kind(path) == UNREADABLE


def test_manifest_failure_record_of_the_wrong_type_is_set_aside(tmp_path):
    # Found by the fuzzer: a failure whose step was a number passed the manifest check and
    # vet batch's summary table failed on it ("internal error (TypeError ...)").
    import json

    from stages.batch.manifest import MANIFEST_NAME, Manifest

    record = {
        "input": {"path": "a.exr"},
        "status": "failed",
        "failure": {"step": 3, "reason": "x", "key": None},
    }
    data = {"format": "vet-batch-manifest", "format_version": 1, "captures": {"a.exr": record}}
    (tmp_path / MANIFEST_NAME).write_text(json.dumps(data))
    warning = Manifest.load(tmp_path).load_warning
    assert "captures.a.exr.failure.step: must be a valid string" in warning


@pytest.mark.timeout(60)
def test_translation_by_a_billion_pixels_renders_at_once():
    # Found with the fuzzer's slow motion field: OpenCV's mirrored border walks the
    # distance, so `vet simulate --motion translate:1e9,0` ran for minutes. A shift by
    # whole mirror periods (2 x the size) is the same picture.
    from stages.motion import Translate
    from stages.scenes import load_scene

    scene = load_scene("builtin:interior", (32, 24)).radiance
    near = Translate(3.0, -2.0).render(scene, 1.0)
    far = Translate(64 * 10**7 + 3.0, -48 * 10**7 - 2.0).render(scene, 1.0)
    np.testing.assert_array_equal(far, near)
