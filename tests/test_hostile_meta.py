"""Issue 52's hostile metadata and outputs: metadata that contradicts itself is refused
(exit 1, one line naming the file and the field, nothing written), and no command writes
a non-finite pixel with exit 0. Each case failed on the code before (accepted with wrong
results, or an internal error)."""

from __future__ import annotations

import copy
import struct
import warnings
import zipfile

import numpy as np
import pytest
from click.testing import CliRunner

from stages.formats import write_capture
from tests.hostile import write_unchecked
from vet_cli.main import cli

TAU = 0.00758


def run(*args):
    from vet_cli._common import State

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = CliRunner().invoke(cli, [str(a) for a in args])
    finally:
        State.verbosity = 0
    assert not caught, [str(w.message) for w in caught]
    return result


def refused(result, command: str, *words: str) -> str:
    """The one error line of a clean refusal holding ``words``."""
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == 1, (result.exit_code, result.stderr, result.exception)
    assert len(lines) == 1 and lines[0].startswith(f"vet {command}: error: "), lines
    assert "internal error" not in lines[0] and result.stdout == ""
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Small simulated captures (32x24): four time bins, the whole stream, one bin."""
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import load_scene
    from stages.simulate import simulate

    scene = load_scene("builtin:interior", (32, 24))
    rig = RigParams(sensor_size=(32, 24))
    out = {}
    for name, bins in (("bins", 4), ("stream", None), ("one", 1)):
        cap = simulate(scene, parse_motion("translate:20,0"), rig, seed=1, measure_bins=bins)
        out[name] = cap["vet"].to_layered()
    return out


def _write(tmp_path, captures, which, change, name="bad.npz"):
    data = copy.deepcopy(captures[which])
    change(data.meta, data)
    path = tmp_path / name
    write_unchecked(path, data)
    return path


def _both_refuse(path, tmp_path, *words):
    """``vet info`` and ``vet hdr-static`` refuse ``path`` naming ``words``; no output."""
    refused(run("info", path), "info", *words)
    refused(run("hdr-static", path, "-o", tmp_path / "h.exr"), "hdr-static", *words)
    assert not (tmp_path / "h.exr").exists()


def _swap(meta, data):
    t = meta["measure_times"]
    t[0], t[1] = t[1], t[0]


def _overlap(meta, data):
    t = meta["measure_times"]
    t[1][0] = t[0][1] - 3 * TAU


def _one_half_second(meta, data):
    # The stream's bins 65 to 130 (one subframe each) made one bin of 0.5 s (66 subframes)
    # whose count says 1, as every other bin's: in order, disjoint and in the frame, but
    # its window and its count contradict each other.
    t = meta["measure_times"]
    for b in range(66, len(t)):
        del data.layers[f"M{b:02d}"], data.channels[f"M{b:02d}"]
    meta["measure_times"] = t[:65] + [[t[65][0], t[-1][1]]]
    meta["measure_subframes"] = [1] * 66


def _all_but_one_half(meta, data):
    t = meta["measure_times"]
    for b in range(1, len(t)):
        t[b] = [0.49, 0.99]


CASES = {
    "measure_times out of order": ("bins", _swap, ["measure_times.1", "in order"]),
    "measure_times overlapping": ("bins", _overlap, ["measure_times.1", "disjoint"]),
    "one bin of 0.5 s among subframes": (
        "stream",
        _one_half_second,
        ["measure_subframes.65: 1 subframes in a bin of 66"],
    ),
    "all bins but one 0.5 s": ("bins", _all_but_one_half, ["measure_times.2", "disjoint"]),
    "bins off the subframe clock": (
        "bins",
        lambda m, d: m["measure_times"][1].__setitem__(1, m["measure_times"][1][1] - TAU / 2),
        ["measure_times.1", "whole subframes"],
    ),
    "measure_subframes all 0": (
        "bins",
        lambda m, d: m.__setitem__("measure_subframes", [0] * 4),
        ["measure_subframes.0: must be greater than or equal to 1"],
    ),
    "measure_subframes of the wrong length": (
        "bins",
        lambda m, d: m.__setitem__("measure_subframes", [33, 33]),
        ["measure_subframes: 2 counts for 4 time bins"],
    ),
    "measure_subframes more than the window": (
        "bins",
        lambda m, d: m["measure_subframes"].__setitem__(0, 60),
        ["measure_subframes.0: 60 subframes in a bin of 33"],
    ),
    "measure_dropped of 100000 entries": (
        "bins",
        lambda m, d: m.__setitem__("measure_dropped", [5] * 100_000),
        ["measure_dropped: 100000 indices", "131 subframes"],
    ),
    "measure_dropped out of range": (
        "bins",
        lambda m, d: m.__setitem__("measure_dropped", [3, 131]),
        ["measure_dropped: 2 indices up to 131"],
    ),
    "measure_dropped twice the same": (
        "bins",
        lambda m, d: m.__setitem__("measure_dropped", [3, 3]),
        ["measure_dropped.1: 3 after 3"],
    ),
    "radiance_scale denormal": (
        "bins",
        lambda m, d: m.__setitem__("radiance_scale", 1e-320),
        ["radiance_scale: ", "not a normal float32"],
    ),
    "rig full well denormal": (
        "bins",
        lambda m, d: m["rig"].__setitem__("full_well_e", 5e-324),
        ["rig.full_well_e: must be greater than or equal to 1"],
    ),
    "integration longer than the frame": (
        "bins",
        lambda m, d: m.__setitem__("integration_s", 5.0),
        ["integration_s: 5.0 s; allowed at most the frame"],
    ),
    "measuring layers out of sequence": (
        "bins",
        lambda m, d: (
            d.layers.__setitem__("M07", d.layers.pop("M03")),
            d.channels.__setitem__("M07", d.channels.pop("M03")),
        ),
        ["measuring layer 'M07' out of sequence"],
    ),
    "measure_times without their layers": (
        "one",
        lambda m, d: d.layers.pop("M00"),
        ["measure_times: 1 time bins for 0 measuring layers"],
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("ext", ["npz", "exr"])
def test_metadata_that_contradicts_itself_is_refused(tmp_path, captures, case, ext):
    which, change, words = CASES[case]
    path = _write(tmp_path, captures, which, change, f"bad.{ext}")
    _both_refuse(path, tmp_path, str(path), *words)


def test_valid_captures_still_read(tmp_path, captures):
    for which in captures:
        path = _write(tmp_path, captures, which, lambda m, d: None, f"{which}.npz")
        assert run("info", path).exit_code == 0
        assert run("hdr-static", path, "-o", tmp_path / f"{which}.hdr.exr").exit_code == 0


def _meta_text_with(path, old: bytes, new: bytes):
    """The npz at ``path`` with its metadata's JSON text edited (a number no JSON writer
    of Python would write: 5000 digits)."""
    with zipfile.ZipFile(path) as zf:
        members = [(i.filename, zf.read(i)) for i in zf.infolist()]
    import io

    out = []
    for name, raw in members:
        if name == "__meta__.npy":
            text = str(np.load(io.BytesIO(raw))).encode().replace(old, new, 1).decode()
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.array(text), allow_pickle=False)
            raw = buf.getvalue()
        out.append((name, raw))
    with zipfile.ZipFile(path, "w") as zf:
        for name, raw in out:
            zf.writestr(name, raw)


@pytest.mark.parametrize("where", [b'"seed": 1', b'"adc_bits": 12'])
def test_a_5000_digit_integer_is_refused(tmp_path, captures, where):
    path = _write(tmp_path, captures, "bins", lambda m, d: None)
    key = where.split(b":")[0]
    _meta_text_with(path, where, key + b": " + b"9" * 5000)
    _both_refuse(path, tmp_path, "integer of 5000 digits; allowed at most 20")


def test_npz_with_two_members_of_one_name_is_refused(tmp_path, captures):
    # The second __meta__ says the radiance is 1000 times smaller: never read it.
    path = _write(tmp_path, captures, "bins", lambda m, d: None)
    data = copy.deepcopy(captures["bins"])
    data.meta["radiance_scale"] *= 1000
    other = tmp_path / "other.npz"
    write_unchecked(other, data)
    with zipfile.ZipFile(other) as zf:
        second = zf.read("__meta__.npy")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (zipfile warns of the duplicate name)
        with zipfile.ZipFile(path, "a") as zf:
            zf.writestr("__meta__.npy", second)
    _both_refuse(path, tmp_path, "member '__meta__.npy' is in the .npz twice")


def _encrypt(path, member: str) -> None:
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        raw[zf.getinfo(member).header_offset + 6] |= 1
    pos = raw.find(b"PK\x01\x02")
    while pos >= 0:
        n = struct.unpack_from("<H", raw, pos + 28)[0]
        if raw[pos + 46 : pos + 46 + n] == member.encode():
            raw[pos + 8] |= 1
        pos = raw.find(b"PK\x01\x02", pos + 4)
    path.write_bytes(bytes(raw))


@pytest.mark.parametrize("member", ["layer:T.npy", "__meta__.npy"])
def test_encrypted_npz_member_is_refused_and_fails_alone_in_a_batch(tmp_path, captures, member):
    path = _write(tmp_path, captures, "bins", lambda m, d: None)
    _encrypt(path, member)
    _both_refuse(path, tmp_path, f"member '{member}' is encrypted")
    root = tmp_path / "root"
    root.mkdir()
    path.rename(root / "bad.npz")
    write_unchecked(root / "good.npz", copy.deepcopy(captures["bins"]))
    r = run("batch", root, "-o", tmp_path / "out", "-j", "1", "--steps", "hdr-static")
    assert r.exit_code == 3, r.stderr  # (some captures failed; the others done)
    assert "is encrypted" in r.stderr and "internal error" not in r.stderr
    assert (tmp_path / "out" / "good.hdr.exr").is_file()


@pytest.mark.parametrize("origin", [(100_000, -100_000), (3, 0)])
def test_exr_data_window_away_from_the_origin_is_refused(tmp_path, captures, origin):
    import OpenImageIO as oiio

    path = _write(tmp_path, captures, "bins", lambda m, d: None, "c.exr")
    buf = oiio.ImageBuf(str(path))
    buf.set_origin(*origin)
    buf.write(str(tmp_path / "w.exr"))
    _both_refuse(tmp_path / "w.exr", tmp_path, f"data window at ({origin[0]}")


def test_zero_exposure_without_leakage_is_refused(tmp_path, captures):
    # T = 0 everywhere with leakage 0: every pixel saw no light (was: every pixel infinite).
    def change(meta, data):
        meta["rig"]["leakage"] = 0.0
        data.layers["T"][:] = 0

    path = _write(tmp_path, captures, "bins", change)
    r = run("hdr-static", path, "-o", tmp_path / "h.exr")
    refused(r, "hdr-static", "T is 0 s at 768 of 768 pixels", "saw no light")
    assert not (tmp_path / "h.exr").exists()


def test_a_single_measuring_bin_deblurs_cleanly(tmp_path, captures):
    # Was: IndexError from the default method. One bin holds no motion: refused for an
    # estimate, a result when the motion is given.
    path = tmp_path / "one.npz"
    write_unchecked(path, copy.deepcopy(captures["one"]))
    refused(run("deblur", path, "-o", tmp_path / "d.exr"), "deblur", "1 measuring image")
    assert not (tmp_path / "d.exr").exists()
    r = run("deblur", path, "-o", tmp_path / "d.exr", "--motion-init", "zero")
    assert r.exit_code == 0, r.stderr


def test_a_capture_without_measuring_images_deblurs_cleanly(tmp_path, captures):
    # All subframes dropped (drop_rate near 1): deblur said AttributeError.
    def change(meta, data):
        for k in [k for k in data.layers if k.startswith("M0")]:
            del data.layers[k]
        meta.update(measure_times=[], measure_subframes=[], measure_dropped=list(range(131)))

    path = _write(tmp_path, captures, "bins", change)
    refused(run("deblur", path, "-o", tmp_path / "d.exr"), "deblur", "no measuring images")


RIG_PROFILES = {
    "homography 1e300": (
        "homography = [[1e300, 0, 0], [0, 1, 0], [0, 0, 1]]",
        "homography: condition number 1e+300",
    ),
    "measure_homography 1e300": (
        "measure_homography = [[1e300, 0, 0], [0, 1e300, 0], [0, 0, 1]]",
        "measure_homography: condition number",
    ),
    "drop_rate 0.999999": ("drop_rate = 0.999999", "drop_rate: must be less than or equal to 0.5"),
    "measure_size 1x1": ("measure_size = [1, 1]", "measure_size: the 1x1 measurement camera"),
    "5000-digit integer": ("leakage_seed = " + "9" * 5000, "not a valid TOML file"),
    "30-digit integer": ("leakage_seed = " + "9" * 30, "integer of 30 digits"),
}


@pytest.mark.parametrize("case", sorted(RIG_PROFILES))
def test_rig_profile_that_makes_no_rig_is_refused(tmp_path, case):
    line, words = RIG_PROFILES[case]
    profile = tmp_path / "rig.toml"
    profile.write_text(f"[params]\n{line}\n")
    r = run("simulate", "builtin:interior", "--size", "32x24", "--rig-profile", profile, "-o",
            tmp_path / "s.npz")  # fmt: skip
    refused(r, "simulate", str(profile), words)
    assert not (tmp_path / "s.npz").exists()


def _raw_hdr(path, value):
    from stages.formats.hdr import HDRImage
    from tests.hostile import write_unchecked as write

    img = HDRImage(np.full((24, 32, 3), value, np.float32), ["R", "G", "B"], {"units": "DN/s"})
    write(path, img.to_layered())


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_tonemap_of_a_non_finite_hdr_image_is_refused(tmp_path, value):
    # Was: a black PNG, exit 0, with RuntimeWarnings naming source files.
    _raw_hdr(tmp_path / "h.exr", value)
    r = run("tonemap", tmp_path / "h.exr", "-o", tmp_path / "h.png")
    refused(r, "tonemap", "2304 of 2304 radiance values are NaN or infinite")
    assert not (tmp_path / "h.png").exists()


def test_no_output_is_written_with_a_non_finite_pixel(tmp_path, captures):
    from stages.errors import OutputError
    from stages.formats.hdr import HDRImage, write_hdr

    img = HDRImage(np.ones((4, 5, 1), np.float32), ["Y"], {"units": "DN/s"})
    img.radiance[2, 3, 0] = np.inf
    # (a mono image is stored as R, G, B)
    with pytest.raises(OutputError, match="layer 'image' holds 3 NaN or infinite values of 60"):
        write_hdr(tmp_path / "h.exr", img)
    assert list(tmp_path.iterdir()) == []
    from stages.formats.capture import Capture

    data = copy.deepcopy(captures["bins"])
    cap = Capture.from_layered(data)
    cap.truth[0, 0, 0] = np.nan
    with pytest.raises(OutputError, match="layer 'truth' holds 1 NaN"):
        write_capture(tmp_path / "c.npz", cap)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("layer", "words"),
    [
        ("I", "I holds values beyond +/-"),
        ("M02", "measuring image M02 holds values beyond +/-"),
        ("truth_motion", "truth_motion: velocities up to 1e+30 px/s"),
    ],
)
def test_values_no_sensor_records_are_refused(tmp_path, captures, layer, words):
    # Found by make fuzz: a measuring pixel of 1e30 DN (finite) overflowed float32 in
    # deblur's robust weights (numpy's RuntimeWarning on stderr).
    def change(meta, data):
        data.layers[layer][3, 4, 0] = 1e30

    path = _write(tmp_path, captures, "bins", change, "big.exr")
    r = run("deblur", path, "-o", tmp_path / "d.exr", "--motion-init", "truth")
    refused(r, "deblur", words)
    assert not (tmp_path / "d.exr").exists()
