"""Scene loading: real-data quirks (tiles, mip-maps, alpha, negatives, NaN, mono)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from stages.errors import FormatError, InputError
from stages.scenes import BUILTIN_SCENES, load_scene, luminance


def _write(path, pixels, names, tile=None, mip=False):
    import OpenImageIO as oiio

    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, "float")
    spec.channelnames = tuple(names)
    if tile:
        spec.tile_width = spec.tile_height = tile
    buf = oiio.ImageBuf(spec)
    buf.set_pixels(oiio.ROI(), pixels)
    if mip:
        oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, buf, str(path), spec)
    else:
        assert buf.write(str(path)), oiio.geterror()


@pytest.fixture
def rgba(rng):
    img = rng.random((40, 52, 4)).astype(np.float32) * 100
    img[..., 3] = 0.25  # alpha: must be ignored
    return img


def test_tiled_exr_reads_at_full_resolution(tmp_path, rgba):
    _write(tmp_path / "t.exr", rgba, ["R", "G", "B", "A"], tile=16)
    sc = load_scene(str(tmp_path / "t.exr"))
    assert sc.channels == ["R", "G", "B"]
    np.testing.assert_allclose(sc.radiance, rgba[..., :3], rtol=1e-6)


def test_mipmapped_exr_reads_level_zero(tmp_path, rgba):
    _write(tmp_path / "m.exr", rgba, ["R", "G", "B", "A"], tile=16, mip=True)
    sc = load_scene(str(tmp_path / "m.exr"))
    assert sc.radiance.shape == (40, 52, 3)
    np.testing.assert_allclose(sc.radiance, rgba[..., :3], rtol=1e-3)


def test_channels_picked_by_name_not_position(tmp_path, rgba):
    # A file storing A, B, G, R: the scene must come back as R, G, B.
    _write(tmp_path / "abgr.exr", rgba[..., ::-1].copy(), ["A", "B", "G", "R"])
    sc = load_scene(str(tmp_path / "abgr.exr"))
    np.testing.assert_allclose(sc.radiance, rgba[..., :3], rtol=1e-6)


def test_negative_and_nan_pixels_become_zero_with_a_warning(tmp_path, rgba, caplog):
    img = rgba.copy()
    img[0, 0, 0] = -5.0
    img[1, 1, 1] = np.nan
    _write(tmp_path / "bad.exr", img, ["R", "G", "B", "A"])
    with caplog.at_level(logging.WARNING):
        sc = load_scene(str(tmp_path / "bad.exr"))
    assert sc.radiance[0, 0, 0] == 0 and sc.radiance[1, 1, 1] == 0
    assert "1 non-finite and 1 negative" in caplog.text


def test_mono_scene(tmp_path, rng):
    img = rng.random((20, 30, 1)).astype(np.float32)
    _write(tmp_path / "y.exr", img, ["Y"])
    sc = load_scene(str(tmp_path / "y.exr"))
    assert sc.channels == ["Y"] and sc.radiance.shape == (20, 30, 1)


def test_resample_preserves_mean_radiance(tmp_path, rgba):
    _write(tmp_path / "s.exr", rgba, ["R", "G", "B", "A"])
    sc = load_scene(str(tmp_path / "s.exr"), size=(26, 20))
    assert sc.radiance.shape == (20, 26, 3)
    assert sc.radiance.mean() == pytest.approx(rgba[..., :3].mean(), rel=0.01)


def test_black_and_missing_scenes_are_refused(tmp_path):
    _write(tmp_path / "black.exr", np.zeros((8, 8, 3), np.float32), ["R", "G", "B"])
    with pytest.raises(InputError, match="black"):
        load_scene(str(tmp_path / "black.exr"))
    with pytest.raises(InputError, match="no such file"):
        load_scene(str(tmp_path / "nope.exr"))
    (tmp_path / "junk.exr").write_bytes(b"junk" * 100)
    with pytest.raises(FormatError):
        load_scene(str(tmp_path / "junk.exr"))


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENES))
def test_builtins_are_deterministic_and_high_dynamic_range(name):
    a = load_scene(f"builtin:{name}", (160, 128))
    b = load_scene(f"builtin:{name}", (160, 128))
    np.testing.assert_array_equal(a.radiance, b.radiance)
    lum = luminance(a.radiance)
    assert np.percentile(lum, 99.9) / np.percentile(lum, 1) > 1e4
    assert np.all(np.isfinite(lum)) and lum.min() > 0
