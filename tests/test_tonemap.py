"""Tone mapping, false-colour pictures and display image files."""

from __future__ import annotations

import math
import os
import warnings

import cv2
import numpy as np
import pytest

from stages.errors import InputError
from stages.falsecolor import MASK_PALETTE, render_exposure_time_map, render_mask
from stages.formats.hdr import MASK_CODES
from stages.formats.images import (
    display_format,
    encode_display_image,
    quantize_display,
    write_display_image,
)
from stages.tonemap import (
    DEFAULT_GAMMA,
    OPERATORS,
    luminance,
    robust_levels,
    tonemap,
    tonemap_log,
)

FRAME_S = 0.99975
SUBFRAME_S = 0.00758


def ramp(decades: float = 4.0, width: int = 256, height: int = 24) -> np.ndarray:
    """(H, W, 1) luminance rising log-uniformly from 1 to 10**decades along x."""
    row = np.logspace(0.0, decades, width, dtype=np.float32)
    return np.tile(row, (height, 1))[:, :, None]


def scene(seed: int = 3) -> np.ndarray:
    """(32, 48, 3) colour HDR test image: smooth 4-decade ramp times a mild random tint.

    Seeded so that every run maps the same pixels; the values only need to be varied.
    """
    rng = np.random.default_rng(seed)
    tint = 0.6 + 0.4 * rng.random((32, 48, 3))
    return (ramp(4.0, 48, 32) * tint).astype(np.float32)


# ------------------------------------------------------------------ tone mapping


@pytest.mark.parametrize("operator", OPERATORS)
def test_output_is_display_range_float32_of_input_shape(operator):
    for image in (scene(), ramp(), ramp()[:, :, 0]):
        out = tonemap(image, operator)
        assert out.shape == image.shape
        assert out.dtype == np.float32
        assert np.isfinite(out).all()
        assert out.min() >= 0.0 and out.max() <= 1.0
        assert out.max() > 0.9  # the brightest pixels reach (near) white


@pytest.mark.parametrize("operator", ["log", "reinhard", "drago"])
def test_global_operators_are_monotonic_in_luminance(operator):
    out = tonemap(ramp(), operator)[:, :, 0]
    assert (np.diff(out, axis=1) > 0).all()


def test_mantiuk_is_monotonic_up_to_solver_noise():
    # Mantiuk's operator is local and solved iteratively: along a smooth ramp its
    # output may wobble by far less than one 8-bit code, and no more.
    out = tonemap(ramp(), "mantiuk")[:, :, 0]
    assert np.diff(out, axis=1).min() > -0.5 / 255
    assert out[:, -1].mean() - out[:, 0].mean() > 0.9


@pytest.mark.parametrize("operator", OPERATORS)
def test_every_operator_uses_the_display_range_and_keeps_the_darks(operator):
    # builtin:interior spans over five decades: a lamp, and a room 4-5 decades darker.
    # OpenCV's Mantiuk floors its logs at 1e-4 of white and only min-max stretches its
    # output, which gave a flat dark grey picture with no texture left in the room.
    from stages.scenes import builtin_interior

    radiance = builtin_interior(160, 128).radiance
    codes = np.round(tonemap(radiance, operator) * 255)
    p1, p99 = np.percentile(codes, [1, 99])
    assert p99 - p1 >= 110
    lum = luminance(radiance)
    dark = luminance(codes)[lum < np.median(lum)]
    lo, hi = np.percentile(dark, [5, 95])
    assert hi - lo >= 15  # the darker half of the scene keeps its texture


def test_mantiuk_maps_its_cut_log_luminance_onto_the_display_range():
    # As pfstmo_mantiuk06 does: the 0.1-99.9 percentiles of the output log luminance
    # become 10**-2.3 and 1 (display-linear), then the display gamma.
    from stages.tonemap.mantiuk06 import MANTIUK_DISPLAY_RANGE, fit_log_luminance

    lum = np.logspace(-3.0, 0.0, 1001, dtype=np.float32).reshape(1, -1)
    display = np.repeat(lum[:, :, None], 3, axis=2)
    out = luminance(fit_log_luminance(display, MANTIUK_DISPLAY_RANGE))[0]
    assert out[500] == pytest.approx(10 ** (-MANTIUK_DISPLAY_RANGE / 2), rel=1e-3)
    assert out[-1] == pytest.approx(1.0) and out[0] == pytest.approx(10**-MANTIUK_DISPLAY_RANGE)
    assert (np.diff(out) >= 0).all()


@pytest.mark.parametrize("operator", OPERATORS)
def test_shuffled_patches_keep_their_brightness_order(operator):
    levels = np.logspace(0, 3, 8).astype(np.float32)
    order = np.array([5, 2, 7, 0, 3, 6, 1, 4])  # a fixed shuffle, so neighbours differ
    image = np.repeat(np.repeat(levels[order][None, :], 48, axis=0), 16, axis=1)[:, :, None]
    out = tonemap(image, operator)[:, :, 0]
    means = out.reshape(48, 8, 16).mean(axis=(0, 2))
    assert np.array_equal(np.argsort(means), np.argsort(levels[order]))


@pytest.mark.parametrize("operator", OPERATORS)
def test_grey_rgb_equals_replicated_mono(operator):
    mono = ramp(3.0, 64, 16)
    grey = tonemap(np.repeat(mono, 3, axis=2), operator)
    single = tonemap(mono, operator)
    np.testing.assert_allclose(grey, np.repeat(single, 3, axis=2), atol=1e-5)


@pytest.mark.parametrize("operator", OPERATORS)
def test_colour_order_is_kept(operator):
    # A reddish and a bluish patch inside a grey ramp: OpenCV must see R as R (it
    # documents BGR but weights channel 0 as red), so the dominant channel survives.
    image = np.repeat(ramp(2.0, 64, 16), 3, axis=2)
    image[4:8, 20:24] = [40.0, 8.0, 4.0]
    image[10:14, 40:44] = [4.0, 8.0, 40.0]
    out = tonemap(image, operator)
    red, blue = out[5, 21], out[11, 41]
    assert red[0] > red[1] > red[2]
    assert blue[2] > blue[1] > blue[0]


def test_log_is_invariant_to_the_units_of_the_radiance():
    image = scene()
    reference = tonemap(image, "log")
    for scale in (1e-6, 3.7, 1e5):
        np.testing.assert_allclose(tonemap(image * scale, "log"), reference, atol=1e-5)


@pytest.mark.parametrize("operator", ["reinhard", "drago", "mantiuk"])
def test_opencv_operators_are_invariant_to_the_units(operator):
    image = scene()
    reference = tonemap(image, operator)
    np.testing.assert_allclose(tonemap(image * 1e4, operator), reference, atol=1e-3)


def test_log_known_answer():
    # black = 1, white = e**2 - 1: L_d = ln(1 + L) / 2, so L = e - 1 maps to 1/2.
    white = math.e**2 - 1
    y = np.array([[[0.0], [math.e - 1], [white], [10 * white]]], dtype=np.float32)
    out = tonemap_log(y, black=1.0, white=white)
    np.testing.assert_allclose(out[0, :, 0], [0.0, 0.5, 1.0, 1.0], atol=1e-6)
    # One stop more exposure: ln(1 + 2 (e - 1)) / 2.
    brighter = tonemap_log(y, black=1.0, white=white, exposure=1.0)
    assert brighter[0, 1, 0] == pytest.approx(math.log(2 * math.e - 1) / 2, abs=1e-6)
    # Gamma acts on the result.
    assert tonemap_log(y, black=1.0, white=white, gamma=2.0)[0, 1, 0] == pytest.approx(
        math.sqrt(0.5), abs=1e-6
    )


def test_log_colour_ratios_follow_the_saturation_exponent():
    rgb = np.array([[[3.0, 2.0, 1.0], [300.0, 10.0, 10.0], [0.5, 0.5, 0.5]]], dtype=np.float32)
    exact = tonemap_log(rgb, black=0.5, white=50.0, saturation=1.0)
    np.testing.assert_allclose(exact[0, 0] / exact[0, 0, 2], [3.0, 2.0, 1.0], rtol=1e-5)
    # Above white the pixel is scaled down as a whole: still red, ratios kept.
    assert exact[0, 1, 0] == pytest.approx(1.0)
    np.testing.assert_allclose(exact[0, 1, 1:], [10 / 300, 10 / 300], rtol=1e-5)
    # The default keeps the ratios in displayed light (code ** 2.2), not in code values.
    shown = tonemap_log(rgb, black=0.5, white=50.0) ** 2.2
    np.testing.assert_allclose(shown[0, 0] / shown[0, 0, 2], [3.0, 2.0, 1.0], rtol=1e-4)
    # Grey stays grey, and its level does not depend on the saturation.
    np.testing.assert_allclose(exact[0, 2], tonemap_log(rgb, black=0.5, white=50.0)[0, 2])
    assert np.ptp(exact[0, 2]) == 0


@pytest.mark.parametrize("operator", OPERATORS)
def test_exposure_shifts_brightness(operator):
    image = scene()
    means = [tonemap(image, operator, exposure=e).mean() for e in (-1.0, 0.0, 1.0)]
    assert means[0] < means[1] < means[2]


@pytest.mark.parametrize("operator", OPERATORS)
def test_nan_inf_and_negative_samples_are_made_safe(operator):
    image = scene()
    image[3, 4] = np.nan
    image[5, 6] = -20.0
    image[7, 8, 1] = np.inf
    with pytest.warns(RuntimeWarning, match="NaN or infinite"):
        out = tonemap(image, operator)
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    if operator != "mantiuk":  # a local operator need not map zero to exactly zero
        assert out[3, 4].max() < 1e-3 and out[5, 6].max() < 1e-3
    # Negative noise alone is routine in dark pixels: no warning for it.
    clean = scene()
    clean[0, 0] = -1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tonemap(clean, operator)


@pytest.mark.parametrize("operator", OPERATORS)
def test_degenerate_images_do_not_fail(operator):
    flat = np.full((8, 8, 3), 5.0, dtype=np.float32)
    out = tonemap(flat, operator)
    assert np.isfinite(out).all() and np.ptp(out) == 0
    tiny = np.array([[[2.0, 1.0, 0.5]]], dtype=np.float32)
    assert tonemap(tiny, operator).shape == (1, 1, 3)
    with pytest.warns(RuntimeWarning, match="no positive samples"):
        black = tonemap(np.zeros((4, 4, 1), np.float32), operator)
    assert not black.any()


def test_robust_white_ignores_a_hot_pixel_but_not_a_small_highlight():
    image = np.ones((32, 32, 1), dtype=np.float32)
    image[10, 10] = 1e6  # a hot pixel
    assert robust_levels(image)[1] == pytest.approx(1.0)
    image[20:23, 20:23] = 500.0  # a 3x3 lamp
    black, white = robust_levels(image)
    assert white == pytest.approx(500.0) and black == pytest.approx(1.0)


def test_luminance_uses_rec709_weights():
    rgb = np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]], np.float32)
    np.testing.assert_allclose(luminance(rgb)[0], [0.2126, 0.7152, 0.0722], rtol=1e-6)


def test_dispatcher_defaults_and_refusals():
    image = scene()
    assert set(DEFAULT_GAMMA) == set(OPERATORS)
    np.testing.assert_array_equal(tonemap(image), tonemap_log(image, gamma=DEFAULT_GAMMA["log"]))
    with pytest.raises(ValueError, match="Unknown tone-mapping operator 'durand'"):
        tonemap(image, "durand")
    with pytest.raises(ValueError, match="does not take the parameter"):
        tonemap(image, "drago", scale=0.5)
    with pytest.raises(ValueError, match="Gamma must be"):
        tonemap(image, gamma=0.0)
    with pytest.raises(ValueError, match="Exposure must be"):
        tonemap(image, exposure=float("nan"))
    with pytest.raises(ValueError, match="1 \\(Y\\) or 3"):
        tonemap(np.ones((4, 4, 2), np.float32))
    with pytest.raises(ValueError, match="white level"):
        tonemap(image, white=-1.0)
    with pytest.raises(ValueError, match="bias"):
        tonemap(image, "drago", bias=1.5)


# ------------------------------------------------------------- display images


@pytest.mark.parametrize(("name", "bits"), [("a.png", 16), ("a.tif", 16), ("a.png", 8)])
def test_display_image_round_trip_is_exact(tmp_path, name, bits):
    # Seeded so the round trip covers many arbitrary code values reproducibly.
    rng = np.random.default_rng(7)
    image = rng.random((9, 13, 3)).astype(np.float32)
    path = tmp_path / name
    write_display_image(path, image, bits=bits)
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back.dtype == (np.uint16 if bits == 16 else np.uint8)
    expected = np.rint(image.astype(np.float64) * (2**bits - 1)).astype(back.dtype)
    np.testing.assert_array_equal(back[:, :, ::-1], expected)  # cv2 reads BGR
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".vet-tmp")]


def test_grey_and_uint8_inputs(tmp_path):
    grey = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    write_display_image(tmp_path / "g.png", grey, bits=16)
    back = cv2.imread(str(tmp_path / "g.png"), cv2.IMREAD_UNCHANGED)
    assert back.shape == (3, 4)
    np.testing.assert_array_equal(back, np.rint(grey * 65535).astype(np.uint16))
    codes = np.arange(12, dtype=np.uint8).reshape(3, 4)
    np.testing.assert_array_equal(quantize_display(codes, 16)[:, :, 0], codes.astype(int) * 257)


def test_jpeg_writes_8_bits_and_refuses_16(tmp_path):
    image = np.full((8, 8, 3), 0.5, np.float32)
    write_display_image(tmp_path / "a.jpg", image, bits=8)
    back = cv2.imread(str(tmp_path / "a.jpg"))
    assert back.shape == (8, 8, 3) and abs(int(back.mean()) - 128) <= 1
    with pytest.raises(InputError, match="JPEG holds only 8 bits"):
        write_display_image(tmp_path / "b.jpeg", image, bits=16)
    assert not (tmp_path / "b.jpeg").exists()


def test_unknown_extension_and_bad_images_are_refused(tmp_path):
    with pytest.raises(InputError, match="unsupported image extension '.bmp'"):
        write_display_image(tmp_path / "a.bmp", np.zeros((2, 2)))
    with pytest.raises(InputError, match="unsupported image extension"):
        display_format(tmp_path / "noext")
    with pytest.raises(ValueError, match="8 or 16 bits"):
        write_display_image(tmp_path / "a.png", np.zeros((2, 2)), bits=12)
    target = tmp_path / "keep.png"
    target.write_bytes(b"old")
    with pytest.raises(ValueError, match="shape"):
        write_display_image(target, np.zeros((2, 2, 4)))
    assert target.read_bytes() == b"old"


def test_dash_writes_png_to_stdout(capsysbinary):
    write_display_image("-", np.ones((2, 3, 3), np.float32), bits=16)
    data = capsysbinary.readouterr().out
    assert data.startswith(b"\x89PNG\r\n\x1a\n")
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.shape == (2, 3, 3) and (back == 65535).all()


def test_encode_matches_file_bytes(tmp_path):
    image = np.eye(4, dtype=np.float32)
    write_display_image(tmp_path / "e.png", image)
    assert (tmp_path / "e.png").read_bytes() == encode_display_image(image, "png", 8)


# ------------------------------------------------------------ false colour


def exposure_times() -> np.ndarray:
    """(60, 80) T: a bright disc closing early (longer towards its rim), the rest never."""
    yy, xx = np.mgrid[:60, :80]
    r = np.hypot(yy - 30, xx - 40)
    steps = np.ceil(2 + r / 25 * 60)
    return np.where(r < 25, SUBFRAME_S * steps, FRAME_S).astype(np.float32)


def test_exposure_time_map_size_and_content():
    picture = render_exposure_time_map(exposure_times(), FRAME_S, SUBFRAME_S)
    assert picture.dtype == np.uint8 and picture.ndim == 3 and picture.shape[2] == 3
    # 60x80 is enlarged 4x (short side to >= 256): the map alone is 240x320.
    assert picture.shape[0] >= 240 and picture.shape[1] >= 320
    assert picture.shape[0] < 240 + 120 and picture.shape[1] < 320 + 250
    assert len(np.unique(picture.reshape(-1, 3), axis=0)) > 50
    # The never-closed pixels wear the top colour of the scale (viridis yellow).
    import matplotlib

    top = np.round(np.asarray(matplotlib.colormaps["viridis"](1.0)[:3]) * 255)
    assert (np.abs(picture.astype(int) - top).sum(axis=2) <= 3).sum() > 240 * 320 // 3


def test_exposure_time_map_native_resolution_and_refusals():
    t = np.full((300, 400), FRAME_S, np.float32)
    t[:, :200] = 0.05
    picture = render_exposure_time_map(t[:, :, None], FRAME_S, SUBFRAME_S)
    assert 300 <= picture.shape[0] < 420 and 400 <= picture.shape[1] < 600
    with pytest.raises(ValueError, match="longer than the subframe"):
        render_exposure_time_map(t, SUBFRAME_S, FRAME_S)
    with pytest.raises(ValueError, match="shape"):
        render_exposure_time_map(np.ones(5), FRAME_S, SUBFRAME_S)


def test_mask_legend_names_every_code():
    mask = np.zeros((40, 60), np.uint8)
    mask[5:10, 5:10] = 1
    mask[20:30, 30:40] = 3
    mask[0, 0] = 9  # not in MASK_CODES: still gets a legend entry
    picture = render_mask(mask, MASK_CODES)
    assert picture.dtype == np.uint8 and picture.shape[2] == 3
    assert picture.shape[0] > 40 * 6 and picture.shape[1] >= 60 * 6
    flat = picture.reshape(-1, 3).astype(int)
    # One legend swatch per code (0, 1, 2, 3 listed, 9 found): each palette colour shows.
    for colour in MASK_PALETTE[:5]:
        rgb = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])
        assert (np.abs(flat - rgb).sum(axis=1) <= 3).any(), colour
    with pytest.raises(ValueError, match="integer codes"):
        render_mask(np.full((4, 4), 0.5), MASK_CODES)
