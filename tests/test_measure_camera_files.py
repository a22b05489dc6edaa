"""Capture files from a rig whose measurement camera has its own resolution (issue 20):
the measuring images at the camera's size beside the VET image, in a second part of an
EXR or as arrays of their own shape in an npz, through every command that reads them.
Known answers, seeded; small frames (48x40 VET, 40x30 measuring)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.errors import FormatError
from stages.formats import read_capture, read_layered, write_capture, write_layered
from stages.formats.container import json_default
from stages.formats.layered import Layered, _oiio
from stages.motion import parse_motion
from stages.optics import rig_profile
from stages.scenes import load_scene
from stages.simulate import simulate
from tests.hostile import write_unchecked

#: Measurement pixel -> VET pixel: the 40x30 camera sees the whole 48x40 frame.
HOM = [[1.2, 0.0, 0.0], [0.0, 40 / 30, 0.0], [0.0, 0.0, 1.0]]
RIG_TOML = (
    "[params]\nmeasure_size = [40, 30]\n"
    "measure_homography = [[1.2, 0.0, 0.0], [0.0, 1.3333, 0.0], [0.0, 0.0, 1.0]]\n"
)


def run_cli(*args):
    from click.testing import CliRunner

    from vet_cli._common import State
    from vet_cli.main import cli

    try:
        return CliRunner().invoke(cli, list(map(str, args)))
    finally:
        State.verbosity = 0


def one_error_line(r, command: str) -> str:
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 1, r.output
    assert len(lines) == 1 and lines[0].startswith(f"vet {command}: error: "), lines
    return lines[0]


@pytest.fixture(scope="module")
def captures():
    """The same still chart, 48x40, from a 40x30 measurement camera: four float32 time
    bins, and the whole int16 stream of 131 subframes. Seed 1."""
    rig = rig_profile("ideal", (48, 40), measure_size=(40, 30), measure_homography=HOM)
    scene = load_scene("builtin:chart", (48, 40))
    motion = parse_motion("translate:5,0")
    return {
        bins: simulate(scene, motion, rig, seed=1, measure_bins=bins)["vet"] for bins in (4, None)
    }


def _parts(path) -> list[tuple[str, int, int, int, int, list[str]]]:
    """Each part of an EXR: name, data window size, display window size, channels."""
    inp = _oiio().ImageInput.open(str(path))
    out = []
    try:
        i = 0
        while inp.seek_subimage(i, 0):
            s = inp.spec()
            name = s.get_string_attribute("oiio:subimagename", "")
            out.append((name, s.width, s.height, s.full_width, s.full_height, list(s.channelnames)))
            i += 1
        inp.geterror()
    finally:
        inp.close()
    return out


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_time_bins_of_their_own_size_round_trip_bit_for_bit(tmp_path, captures, ext):
    cap = captures[4]
    assert cap.I.shape == (40, 48, 1) and cap.measure.shape == (4, 30, 40, 1)
    assert cap.measure.dtype == np.float32
    path = tmp_path / f"c.{ext}"
    write_capture(path, cap)
    back = read_capture(path)
    for name in ("I", "T", "measure", "measure_times", "truth", "truth_motion"):
        a, b = getattr(back, name), getattr(cap, name)
        assert a.shape == b.shape and a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert back.rig == cap.rig and back.rig.measure_size == (40, 30)
    expected = cap.to_layered().meta
    expected["channel_order"] = {k: v for k, v in cap.to_layered().channels.items()}
    assert read_layered(path).meta == json.loads(json.dumps(expected, default=json_default))


def test_the_whole_stream_of_its_own_size_round_trips_compact(tmp_path, captures):
    """int16 stream: npz keeps it bit for bit, EXR as HALF (exact to 2048, the nearest
    even number up to 4096: numpy's float16 rounding)."""
    cap = captures[None]
    assert cap.measure.shape == (131, 30, 40, 1) and cap.measure.dtype == np.int16
    write_capture(tmp_path / "c.npz", cap)
    write_capture(tmp_path / "c.exr", cap)
    npz, exr = read_capture(tmp_path / "c.npz"), read_capture(tmp_path / "c.exr")
    assert npz.measure.dtype == np.int16
    np.testing.assert_array_equal(npz.measure, cap.measure)
    assert exr.measure.dtype == np.float16
    np.testing.assert_array_equal(exr.measure, cap.measure.astype(np.float16))
    a, b = read_layered(tmp_path / "c.exr"), read_layered(tmp_path / "c.npz")
    assert a.meta == b.meta and a.channels == b.channels
    for k in ("I", "T", "truth", "truth_motion"):
        np.testing.assert_array_equal(a.layers[k], b.layers[k])


def test_exr_layout_is_a_second_part_of_the_cameras_size(tmp_path, captures):
    write_capture(tmp_path / "c.exr", captures[4])
    main, measure = _parts(tmp_path / "c.exr")
    assert main[:5] == ("main", 48, 40, 48, 40)
    assert not any(c.startswith("M") for c in main[5])
    # The display window is part 0's, as OpenEXR requires of every part.
    assert measure[:5] == ("measure", 40, 30, 48, 40)
    assert sorted(measure[5]) == ["M00.Y", "M01.Y", "M02.Y", "M03.Y"]


def test_measuring_images_of_the_sensors_size_stay_one_part(tmp_path, small_capture):
    """Today's files are unchanged: one part, no part name."""
    write_capture(tmp_path / "c.exr", small_capture)
    ((name, w, h, *_, channels),) = _parts(tmp_path / "c.exr")
    assert (name, w, h) == ("", 96, 80) and "M00.R" in channels


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_cli_simulate_then_hdr_static_info_and_deblur(tmp_path, ext):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG_TOML)
    cap = tmp_path / f"cap.{ext}"
    r = run_cli("simulate", "builtin:chart", "--size", "48x40", "--motion", "translate:5,0",
                "--seed", "2", "--measure-bins", "8", "--rig-profile", rig, "-o", cap)  # fmt: skip
    assert r.exit_code == 0, r.output
    back = read_capture(cap)
    assert back.I.shape[:2] == (40, 48) and back.measure.shape == (8, 30, 40, 1)
    r = run_cli("hdr-static", cap, "-o", tmp_path / "h.exr")
    assert r.exit_code == 0, r.output
    from stages.formats import read_hdr
    from stages.hdr_static import hdr_static

    hdr = read_hdr(tmp_path / "h.exr")
    assert hdr.radiance.shape[:2] == (40, 48)
    # What the command made of the file is what the capture in memory gives.
    np.testing.assert_allclose(hdr.radiance, hdr_static(back).radiance, rtol=1e-6)
    r = run_cli("info", cap)
    assert r.exit_code == 0, r.output
    info = json.loads(r.stdout)
    assert info["size"] == {"width": 48, "height": 40}
    entry = info["layers"]["M00..M07"]
    assert entry["count"] == 8 and entry["size"] == {"width": 40, "height": 30}
    assert "size" not in info["layers"]["I"]
    r = run_cli("deblur", cap, "-o", tmp_path / "d.exr")
    assert r.exit_code == 0, r.output


def test_cli_simulate_the_whole_stream_and_evaluate(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG_TOML)
    cap = tmp_path / "cap.exr"
    r = run_cli("simulate", "builtin:chart", "--size", "48x40", "--rig-profile", rig, "-o", cap)
    assert r.exit_code == 0, r.output
    assert read_capture(cap).measure.shape == (131, 30, 40, 1)
    r = run_cli("evaluate", "builtin:chart", "--size", "48x40", "--motion", "none",
                "--methods", "vet-static,long", "--rig-profile", rig, "-o", tmp_path / "ev")  # fmt: skip
    assert r.exit_code == 0, r.output


def test_truncated_second_part_exits_1_with_one_line(tmp_path, captures):
    good = tmp_path / "c.exr"
    write_capture(good, captures[4])
    raw = good.read_bytes()
    for cut in (10, 600):
        bad = tmp_path / f"cut{cut}.exr"
        bad.write_bytes(raw[:-cut])
        for command in ("hdr-static", "info"):
            out = ["-o", tmp_path / "h.exr"] if command == "hdr-static" else []
            line = one_error_line(run_cli(command, bad, *out), command)
            assert "pixel data of part 1 unreadable" in line


def _second_part_window(raw: bytes, width: int) -> bytes:
    """The EXR with its last header's dataWindow xMax set so the part is ``width`` wide."""
    at = raw.rindex(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4 + 8
    return raw[:at] + (width - 1).to_bytes(4, "little", signed=True) + raw[at + 4 :]


@pytest.mark.parametrize(
    ("width", "message"),
    [
        (41, "rig.measure_size: 40x30 but measuring image 'M00' is 41x30 pixels"),
        (10**6, "declares 480038400 bytes of pixel data"),  # refused before allocating its pixels
    ],
)
def test_second_part_of_a_wrong_size_is_refused_in_one_line(tmp_path, captures, width, message):
    good = tmp_path / "c.exr"
    write_capture(good, captures[4])
    bad = tmp_path / "bad.exr"
    bad.write_bytes(_second_part_window(good.read_bytes(), width))
    assert message in one_error_line(
        run_cli("hdr-static", bad, "-o", tmp_path / "h.exr"), "hdr-static"
    )


def _layers(cap) -> Layered:
    data = cap.to_layered()
    data.meta = json.loads(json.dumps(data.meta))
    return data


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_layers_of_the_wrong_size_are_refused_before_their_pixels(tmp_path, captures, ext):
    """Only measuring images may have the camera's size; they share one size; a rig
    without a camera of its own size allows none."""
    cases = []
    data = _layers(captures[4])
    data.layers["truth"] = np.ascontiguousarray(data.layers["truth"][:30, :40])
    cases.append((data, "rig.sensor_size: 48x40 but layer 'truth' is 40x30 pixels"))
    data = _layers(captures[4])
    data.layers["M01"] = np.zeros((40, 48, 1), np.float32)  # the sensor's size: allowed alone
    cases.append((data, "measuring layers have different sizes 40x30, 48x40"))
    data = _layers(captures[4])
    data.layers["M01"] = np.zeros((24, 36, 1), np.float32)  # a third size: a third part
    data.layers["M03"] = np.zeros((24, 36, 1), np.float32)  # (named apart from "measure")
    cases.append((data, "measuring image 'M01' is 36x24 pixels; it must be that or the sensor"))
    data = _layers(captures[4])
    data.meta["rig"]["measure_size"] = []
    cases.append((data, "rig.sensor_size: 48x40 but layer 'M00' is 40x30 pixels"))
    for i, (data, message) in enumerate(cases):
        path = tmp_path / f"bad{i}.{ext}"
        write_layered(path, data)
        with pytest.raises(FormatError, match=message):
            read_capture(path)
        assert message in one_error_line(run_cli("info", path), "info")


@pytest.mark.parametrize("ext", ["exr", "npz"])
def test_non_finite_measuring_images_are_refused_in_one_line(tmp_path, captures, ext):
    """Found by the fuzzer on this path (and true of every rig): a NaN or infinite
    measuring pixel reached the fits as numpy warnings. It is refused, as in I."""
    for value in (np.nan, np.inf, -np.inf):
        data = _layers(captures[4])
        data.layers["M01"][3, 5, 0] = value
        path = tmp_path / f"nan.{ext}"
        write_unchecked(path, data)  # (write_layered refuses to write it)
        r = run_cli("hdr-static", path, "-o", tmp_path / "h.exr")
        assert "measuring images hold NaN or infinite values" in one_error_line(r, "hdr-static")
