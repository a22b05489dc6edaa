"""Scenes for the simulator: any linear image OpenImageIO reads, or a builtin procedural one.

A scene is an ``ndarray of shape (H, W, C)`` float32 of linear, non-negative radiance in
the file's own units, with ``C = 1`` (channel ``Y``) or ``C = 3`` (``R, G, B``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

log = logging.getLogger(__name__)

LUMA_709 = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


@dataclass
class Scene:
    radiance: np.ndarray  # (H, W, C) float32
    channels: list[str]
    source: str


def luminance(img: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of an (H, W, 3) image, or the single channel of (H, W, 1)."""
    if img.shape[-1] == 1:
        return img[..., 0]
    return img[..., :3] @ LUMA_709


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"640x512"`` -> (640, 512) (width, height)."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"invalid size {text!r}: expected WIDTHxHEIGHT, e.g. 640x512") from None
    if not (8 <= w <= 16384 and 8 <= h <= 16384):
        raise InputError(f"invalid size {text!r}: each side must be 8 to 16384 pixels")
    return w, h


# --- builtin procedural scenes ------------------------------------------------------


def _value_noise(h: int, w: int, cell: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth random field in [0, 1] with features of about ``cell`` pixels."""
    import cv2

    gh, gw = max(2, int(math.ceil(h / cell)) + 2), max(2, int(math.ceil(w / cell)) + 2)
    grid = rng.random((gh, gw)).astype(np.float32)
    big = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
    return np.clip(big[:h, :w], 0, 1)


def _fbm(h: int, w: int, rng: np.random.Generator, base: float, octaves: int = 4) -> np.ndarray:
    acc = np.zeros((h, w), np.float32)
    amp, total = 1.0, 0.0
    for o in range(octaves):
        acc += amp * _value_noise(h, w, max(1.5, base / 2**o), rng)
        total += amp
        amp *= 0.55
    return acc / total


def builtin_interior(w: int = 640, h: int = 512) -> Scene:
    """A lamp-lit interior: textured walls, floor, shelf and a bright bulb (DR > 1e4).

    Radiance in arbitrary linear units: the bulb is about 2e3, the lamp shade about 40,
    lit wall about 1, the shadowed corners about 1e-2.
    """
    rng = np.random.default_rng(20261121)  # fixed: the scene must be the same everywhere
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    sx, sy = w / 640.0, h / 512.0
    lamp = np.array([0.30 * w, 0.36 * h], np.float32)
    # Illumination from the lamp: inverse-square with a soft core, plus weak ambient.
    d2 = ((xx - lamp[0]) / sx) ** 2 + ((yy - lamp[1]) / sy) ** 2
    illum = 1.6e4 / (d2 + 2.0e3) + 0.01
    floor_y = 0.72 * h
    albedo = 0.35 + 0.3 * _fbm(h, w, rng, 24 * sx)
    # Brick wall texture: mortar lines and per-brick variation.
    bh, bw = 18 * sy, 44 * sx
    row = np.floor(yy / bh)
    shift = (row % 2) * bw / 2
    col = np.floor((xx + shift) / bw)
    brick_var = (np.sin(row * 12.9898 + col * 78.233) * 43758.5453) % 1.0
    mortar = (((yy % bh) < 2 * sy) | (((xx + shift) % bw) < 2 * sx)).astype(np.float32)
    wall = albedo * (0.75 + 0.35 * brick_var) * (1 - 0.6 * mortar)
    # Floor: wood planks with fine grain.
    grain = 0.5 + 0.5 * np.sin(xx / (3.0 * sx) + 6 * _fbm(h, w, rng, 40 * sx, 3))
    plank = ((yy - floor_y) % (22 * sy)) < 1.5 * sy
    floor = (0.25 + 0.2 * grain) * (1 - 0.5 * plank)
    refl = np.where(yy < floor_y, wall, floor).astype(np.float32)
    # A bookshelf on the right: coloured spines with gaps.
    shelf = (xx > 0.62 * w) & (xx < 0.92 * w) & (yy > 0.18 * h) & (yy < 0.68 * h)
    spine = np.floor((xx - 0.62 * w) / (9 * sx))
    spine_v = (np.sin(spine * 91.7) * 1e4) % 1.0
    board = ((yy - 0.18 * h) % (0.125 * h)) < 4 * sy
    books = np.where(board, 0.15, 0.1 + 0.6 * spine_v * (((xx - 0.62 * w) % (9 * sx)) > 1.2 * sx))
    refl = np.where(shelf, books, refl).astype(np.float32)
    # A dark doorway in the left corner (deep shadow, still textured).
    door = (xx < 0.1 * w) & (yy > 0.2 * h) & (yy < floor_y)
    refl = np.where(door, 0.02 + 0.03 * _fbm(h, w, rng, 6 * sx, 3), refl)
    rad = refl * illum
    # Lamp: a glowing shade (trapezoid) above a very bright bulb.
    ry = (yy - lamp[1]) / sy
    rx = np.abs(xx - lamp[0]) / sx
    shade = (ry > -55) & (ry < -12) & (rx < 28 + (ry + 55) * 0.5)
    rad = np.where(shade, 40.0 * (0.8 + 0.4 * _fbm(h, w, rng, 5 * sx, 2)), rad)
    bulb_r2 = rx**2 + ((ry - 2) * 1.2) ** 2
    rad = np.where(bulb_r2 < 14**2, 2000.0 * np.exp(-bulb_r2 / 300.0) + 200.0, rad)
    # Warm lamp light on the wall, cooler ambient in the shadows.
    warm = np.clip(illum / illum.max(), 0, 1)
    tint = np.stack([1.0 + 0.25 * warm, 1.0 + 0.0 * warm, 1.0 - 0.35 * warm], axis=-1)
    out = (rad[..., None] * tint).astype(np.float32)
    return Scene(np.ascontiguousarray(out), ["R", "G", "B"], "builtin:interior")


def builtin_chart(w: int = 640, h: int = 512) -> Scene:
    """A test chart: 24 grey patches spanning 5 decades (1e-3 .. 1e2), a Siemens star
    and bar groups, on a mid-grey surround. Monochrome (channel ``Y``)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.full((h, w), 0.05, np.float32)
    # Patch grid: 6 x 4 in the left 60% of the frame, log-spaced radiances.
    cols, rows = 6, 4
    levels = np.logspace(-3, 2, cols * rows).astype(np.float32)
    pw, ph = 0.6 * w / cols, 0.7 * h / rows
    for i, lev in enumerate(levels):
        r, c = divmod(i, cols)
        x0, y0 = c * pw + 0.1 * pw, 0.05 * h + r * ph + 0.1 * ph
        img[int(y0) : int(y0 + 0.8 * ph), int(x0) : int(x0 + 0.8 * pw)] = lev
    # Siemens star: 36 spokes, bright and dark, on the right.
    cx, cy, rad = 0.8 * w, 0.3 * h, 0.17 * min(w, h) * 1.4
    ang = np.arctan2(yy - cy, xx - cx)
    r = np.hypot(xx - cx, yy - cy)
    star = (np.sin(36 * ang) > 0).astype(np.float32)
    img = np.where(r < rad, 0.02 + 20.0 * star, img)
    # Bar groups of decreasing period along the bottom, high contrast.
    y0, y1 = int(0.82 * h), int(0.95 * h)
    x = 0.05 * w
    for period in (16, 12, 8, 6, 4, 3, 2):
        pw_ = period * max(1.0, w / 640) * 5
        seg = (xx >= x) & (xx < x + pw_) & (yy >= y0) & (yy < y1)
        bars = ((xx - x) // max(1, period // 2 * max(1.0, w / 640))) % 2 == 0
        img = np.where(seg, np.where(bars, 5.0, 0.01), img)
        x += pw_ + 0.02 * w
    return Scene(img[..., None].astype(np.float32), ["Y"], "builtin:chart")


BUILTIN_SCENES = {
    "interior": builtin_interior,
    "chart": builtin_chart,
}


# --- loading ----------------------------------------------------------------------------


#: vet file kinds that are not radiance: refused as scenes.
NOT_SCENES = {
    "capture": "a capture records DN, not radiance; vet hdr-static or vet deblur make one "
    "into an HDR image",
    "motion": "a motion file holds velocities (give it to --motion field:PATH)",
    "calibration": "a calibration holds rig maps (give it to vet capture --calibration)",
}


def scene_file_kind(path: str | Path) -> tuple[str | None, str | None]:
    """What a scene file is, from its header: ``(vet kind, display encoding)``.

    The vet kind is the file's ``vetKind`` (or ``vet:kind``) (``None`` for a file vet did not write).
    The encoding is ``None`` for a linear image, else why it is display-referred
    (``"8-bit"``, ``"sRGB-encoded"``, or both).
    """
    from .formats.io import ZIP_MAGIC
    from .formats.layered import KIND_ATTR, LEGACY_ATTRS, _oiio, read_layered

    p = Path(path)
    with open(p, "rb") as f:
        if f.read(4) == ZIP_MAGIC:
            return str(read_layered(p).meta.get("kind") or "") or None, None
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(p))
    if inp is None:  # read_linear_image reports the unreadable file
        return None, None
    try:
        spec = inp.spec()
        kind = (
            spec.get_string_attribute(KIND_ATTR, "")
            or spec.get_string_attribute(LEGACY_ATTRS[KIND_ATTR], "")
            or None
        )
        colorspace = spec.get_string_attribute("oiio:ColorSpace", "").lower()
        basetype = spec.format.basetype
        eight_bit = basetype in (oiio.UINT8, oiio.INT8)
        fmt = inp.format_name().lower()
    finally:
        inp.close()
    linear = "linear" in colorspace or colorspace.startswith("lin_")
    srgb = "srgb" in colorspace or (fmt in ("png", "jpeg", "bmp", "gif", "webp") and not linear)
    parts = [w for w, on in (("8-bit", eight_bit), ("sRGB-encoded", srgb)) if on]
    return kind, (", ".join(parts) if parts else None)


def read_linear_image(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Read any linear image OpenImageIO reads at full resolution (level 0 of mip-maps,
    tiles handled by OIIO), choosing colour channels by name and ignoring alpha."""
    from .formats.layered import META_ATTR, _parse_meta, read_oiio

    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not an image")
    pixels, names, attrs = read_oiio(p, str(p), (META_ATTR,))
    names = [n.split(".")[-1].upper() for n in names]
    nch = pixels.shape[2]
    mono = bool(attrs.get(META_ATTR)) and _parse_meta(attrs[META_ATTR], str(p)).get("mono") is True
    if mono and "R" in names:  # a vet mono HDR image: three equal channels on disk
        return np.ascontiguousarray(pixels[:, :, [names.index("R")]]), ["Y"]
    if all(c in names for c in ("R", "G", "B")):
        idx = [names.index(c) for c in ("R", "G", "B")]
        return np.ascontiguousarray(pixels[:, :, idx]), ["R", "G", "B"]
    if "Y" in names:
        return np.ascontiguousarray(pixels[:, :, [names.index("Y")]]), ["Y"]
    if nch >= 3:
        return np.ascontiguousarray(pixels[:, :, :3]), ["R", "G", "B"]
    return np.ascontiguousarray(pixels[:, :, :1]), ["Y"]


def sanitise(radiance: np.ndarray, source: str) -> np.ndarray:
    """Replace NaN/inf with 0 and clip negatives to 0, warning how many were changed."""
    bad = ~np.isfinite(radiance)
    neg = radiance < 0
    nbad, nneg = int(bad.sum()), int(neg.sum())
    if nbad or nneg:
        log.warning(
            "%s: %d non-finite and %d negative values set to 0 (scene radiance must be "
            "finite and non-negative)",
            source,
            nbad,
            nneg,
        )
        radiance = np.where(bad | neg, 0.0, radiance).astype(np.float32)
    return radiance


def resample(radiance: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize to (width, height), area-averaging when shrinking (keeps radiance units)."""
    import cv2

    w, h = size
    if (radiance.shape[1], radiance.shape[0]) == (w, h):
        return radiance
    shrink = w < radiance.shape[1] and h < radiance.shape[0]
    interp = cv2.INTER_AREA if shrink else cv2.INTER_CUBIC
    out = cv2.resize(radiance, (w, h), interpolation=interp)
    if out.ndim == 2:
        out = out[:, :, None]
    return np.maximum(out, 0).astype(np.float32)


def load_scene(spec: str, size: tuple[int, int] | None = None) -> Scene:
    """Load ``spec`` (a path, or ``builtin:NAME``), sanitised and optionally resampled."""
    if spec.startswith("builtin:"):
        name = spec.split(":", 1)[1]
        if name not in BUILTIN_SCENES:
            raise InputError(
                f"unknown builtin scene {name!r}; choose from {', '.join(sorted(BUILTIN_SCENES))}"
            )
        w, h = size or (640, 512)
        scene = BUILTIN_SCENES[name](w, h)
        return scene
    if Path(spec).is_file():
        kind, display = scene_file_kind(spec)
        if kind in NOT_SCENES:
            raise InputError(
                f"{spec}: is a vet {kind} file, but a scene must be an HDR image of linear "
                f"radiance (EXR, HDR, TIFF, PFM, or a vet HDR image): {NOT_SCENES[kind]}"
            )
        if kind not in (None, "hdr"):
            raise InputError(f"{spec}: is a vet {kind} file, not an HDR image of radiance")
        if kind == "hdr" and Path(spec).suffix.lower() == ".npz":
            from .formats.hdr import read_hdr

            img = read_hdr(spec)
            return _scene_from(img.radiance, list(img.channels), spec, size)
        if display:
            log.warning(
                "%s: an %s image is display-referred, not linear radiance; its values are "
                "taken as radiance as they are (convert it to a linear EXR or HDR first)",
                spec,
                display,
            )
    radiance, channels = read_linear_image(spec)
    return _scene_from(radiance, channels, spec, size)


def _scene_from(
    radiance: np.ndarray, channels: list[str], spec: str, size: tuple[int, int] | None
) -> Scene:
    radiance = sanitise(radiance, spec)
    if size is not None:
        radiance = resample(radiance, size)
    if not np.any(radiance > 0):
        raise InputError(f"{spec}: scene is black (no positive radiance)")
    return Scene(radiance, channels, str(spec))
