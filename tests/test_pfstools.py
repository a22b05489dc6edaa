"""Other tools read vet's HDR files: pfstools (Debian's ``pfstools``; ``make test-tools``
installs it). Skips cleanly where ``pfsin`` is absent."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from stages.formats.layered import LEGACY_ATTRS, META_ATTR, _oiio, read_layered
from tests.conftest import run_vet

needs_pfs = pytest.mark.skipif(
    shutil.which("pfsin") is None, reason="pfstools not installed (make test-tools installs it)"
)


def _through_pfstools(path, png):
    return subprocess.run(
        f"pfsin {path} | pfstmo_drago03 | pfsout {png}",
        shell=True,
        capture_output=True,
        text=True,
        timeout=120,
    )


@needs_pfs
def test_hdr_files_go_through_pfstools_without_a_word(tmp_path):
    cap, hdr, sharp = tmp_path / "c.exr", tmp_path / "h.exr", tmp_path / "d.exr"
    assert run_vet("simulate", "builtin:interior", "--size", "64x48", "--motion",
                   "translate:20,0", "-o", cap).returncode == 0  # fmt: skip
    assert run_vet("hdr-static", cap, "-o", hdr).returncode == 0
    assert run_vet("deblur", cap, "-o", sharp).returncode == 0
    for path in (hdr, sharp):
        res = _through_pfstools(path, tmp_path / f"{path.stem}.png")
        assert res.returncode == 0 and res.stderr == "", res.stderr
        assert (tmp_path / f"{path.stem}.png").stat().st_size > 0


def test_long_metadata_is_split_and_legacy_attribute_still_reads(tmp_path):
    """Metadata over 900 characters spans vetMeta, vetMeta0001...; a file written with
    the single vet:meta attribute of earlier versions reads the same."""
    hdr = tmp_path / "h.exr"
    assert (
        run_vet("simulate", "builtin:chart", "--size", "32x24", "-o", tmp_path / "c.exr").returncode
        == 0
    )
    assert run_vet("hdr-static", tmp_path / "c.exr", "-o", hdr).returncode == 0
    oiio = _oiio()
    spec = oiio.ImageInput.open(str(hdr)).spec()
    names = [a.name for a in spec.extra_attribs]
    assert META_ATTR in names and f"{META_ATTR}0001" in names
    assert all(
        len(spec.get_string_attribute(n, "")) <= 900 for n in names if n.startswith(META_ATTR)
    )
    meta = read_layered(hdr).meta
    # rewrite the file the old way: one vet:meta attribute
    inp = oiio.ImageInput.open(str(hdr))
    pixels = inp.read_image("float")
    old = oiio.ImageSpec(inp.spec())
    inp.close()
    for n in names:
        if n.startswith(META_ATTR):
            old.erase_attribute(n)
    import json

    old.attribute(LEGACY_ATTRS[META_ATTR], json.dumps(meta))
    legacy = tmp_path / "legacy.exr"
    out = oiio.ImageOutput.create(str(legacy))
    out.open(str(legacy), old)
    out.write_image(np.asarray(pixels, np.float32))
    out.close()
    assert read_layered(legacy).meta == meta


@needs_pfs
def test_mono_hdr_goes_through_pfstools(tmp_path):
    """builtin:chart is mono: its HDR file must still tone-map in pfstools (a lone Y
    channel gave 'Missing X, Y, Z channels in the PFS stream')."""
    cap, hdr, png = tmp_path / "c.exr", tmp_path / "h.exr", tmp_path / "h.png"
    assert run_vet("simulate", "builtin:chart", "--size", "32x24", "-o", cap).returncode == 0
    assert run_vet("hdr-static", cap, "-o", hdr).returncode == 0
    res = _through_pfstools(hdr, png)
    assert res.returncode == 0 and res.stderr == "", res.stderr
    assert png.stat().st_size > 0


def test_mono_hdr_reads_back_as_one_channel_and_old_y_files_still_read(tmp_path):
    from stages.formats.hdr import HDRImage, read_hdr, write_hdr
    from stages.formats.layered import write_layered

    rng = np.random.default_rng(3)
    rad = rng.random((6, 5, 1), dtype=np.float32) + 0.5
    mask = rng.integers(0, 4, (6, 5)).astype(np.uint8)
    image = HDRImage(rad, ["Y"], {"units": "scene"}, mask=mask)
    new = tmp_path / "new.exr"
    write_hdr(new, image)
    assert read_layered(new).channels[""] == ["R", "G", "B"]  # what other tools see
    back = read_hdr(new)
    assert back.channels == ["Y"] and back.radiance.shape == (6, 5, 1)
    np.testing.assert_array_equal(back.radiance, rad)
    np.testing.assert_array_equal(back.mask, mask)
    assert "mono" not in back.meta and back.meta["channels"] == ["Y"]
    # a file of an earlier version: the unnamed layer holds Y
    old_layers = image.to_layered()
    old_layers.layers[""], old_layers.channels[""] = rad, ["Y"]
    old_layers.meta["channels"] = ["Y"]
    del old_layers.meta["mono"]
    old = tmp_path / "old.exr"
    write_layered(old, old_layers)
    np.testing.assert_array_equal(read_hdr(old).radiance, rad)
    assert read_hdr(old).channels == ["Y"]


def test_a_mono_hdr_image_as_a_scene_stays_mono(tmp_path):
    """A vet mono HDR image (three equal channels on disk) read as a scene is one channel."""
    from stages.scenes import read_linear_image

    cap, hdr = tmp_path / "c.exr", tmp_path / "h.exr"
    assert run_vet("simulate", "builtin:chart", "--size", "32x24", "-o", cap).returncode == 0
    assert run_vet("hdr-static", cap, "-o", hdr).returncode == 0
    radiance, channels = read_linear_image(hdr)
    assert channels == ["Y"] and radiance.shape == (24, 32, 1)
