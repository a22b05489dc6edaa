"""Layered float images with JSON metadata, stored as OpenEXR or NumPy ``.npz``.

This is the container under every vet file (captures, HDR images, motion fields,
calibrations). A file holds named *layers*, each an ``ndarray of shape (H, W, C)``
float32 with named channels, plus one JSON metadata dictionary.

EXR layout: channel ``"{layer}.{channel}"`` (the unnamed layer ``""`` uses bare channel
names such as ``R, G, B`` so that viewers show it); metadata as the string attributes
``vetKind`` and ``vetMeta`` (JSON, continued in ``vetMeta0001``... past 900 characters, so
that tools reading attributes as lines of text take them whole), readable with ``oiiotool
--info -v`` (files written before use ``vet:kind`` and ``vet:meta``, still read).

NPZ layout: array ``layer:{name}`` per layer, plus 0-d unicode arrays ``__channels__``
and ``__meta__`` holding JSON. Nothing is pickled; reading refuses object arrays.

Compact layers. A layer held as ``int16`` or ``float16`` (whole digital numbers, such as
a capture's measuring stream) stays compact: EXR stores its channels as HALF (exact for
whole numbers up to 2048 in magnitude, the nearest even number up to 4096: below the
shot noise of such codes), npz as the array itself, deflated; both read back as
``float16`` (EXR) or the stored type (npz). Every other layer is float32.
"""

from __future__ import annotations

import json
import math
import tokenize
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, OutputError
from . import limits, schema
from .io import atomic_output, sniff, spooled_input
from .names import format_for_output

META_ATTR = "vetMeta"
KIND_ATTR = "vetKind"
#: The names vet wrote before: ``prefix:name`` attributes read as ``channel:tag`` by some
#: tools (pfstools warns there is no channel ``vet``). Still read.
LEGACY_ATTRS = {META_ATTR: "vet:meta", KIND_ATTR: "vet:kind"}


#: Layer types kept compact in memory and on disk (module docstring).
COMPACT_DTYPES = (np.dtype(np.int16), np.dtype(np.float16))

#: Rows per EXR write (bounds the float32 staging buffer).
EXR_WRITE_ROWS = 64


@dataclass
class Layered:
    """Named float32 layers of one size plus metadata."""

    layers: dict[str, np.ndarray] = field(default_factory=dict)
    channels: dict[str, list[str]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def add(self, name: str, array: np.ndarray, channels: list[str]) -> None:
        a = np.asarray(array)
        if a.dtype not in COMPACT_DTYPES:
            a = a.astype(np.float32, copy=False)
        if a.ndim == 2:
            a = a[:, :, None]
        if a.ndim != 3 or a.shape[2] != len(channels):
            raise ValueError(f"layer {name!r}: shape {a.shape} does not match channels {channels}")
        if self.layers:
            h, w = next(iter(self.layers.values())).shape[:2]
            if a.shape[:2] != (h, w):
                raise ValueError(f"layer {name!r}: size {a.shape[:2]} differs from {(h, w)}")
        self.layers[name] = np.ascontiguousarray(a)
        self.channels[name] = list(channels)

    @property
    def shape(self) -> tuple[int, int]:
        if not self.layers:
            return (0, 0)
        return next(iter(self.layers.values())).shape[:2]


def _channel_name(layer: str, ch: str) -> str:
    return f"{layer}.{ch}" if layer else ch


def _split_channel(name: str) -> tuple[str, str]:
    if "." in name:
        layer, ch = name.rsplit(".", 1)
        return layer, ch
    return "", name


# --- EXR ---------------------------------------------------------------------------


def _oiio():
    import OpenImageIO as oiio

    return oiio


def write_exr(path: Path, data: Layered, compression: str = "zip", what: str | None = None) -> None:
    """Write ``data`` as a multi-layer float32 EXR at ``path`` (``what``: its name in
    messages, when ``path`` is a temporary file). Raises OutputError on failure."""
    what = what or str(path)
    oiio = _oiio()
    h, w = data.shape
    names: list[str] = []
    arrays: list[np.ndarray] = []
    formats: list[str] = []
    for layer, arr in data.layers.items():
        names += [_channel_name(layer, c) for c in data.channels[layer]]
        arrays.append(arr)
        formats += ["half" if arr.dtype in COMPACT_DTYPES else "float"] * arr.shape[2]
    spec = oiio.ImageSpec(w, h, len(names), "float")
    spec.channelnames = tuple(names)
    if "half" in formats:
        spec.channelformats = tuple(oiio.TypeDesc(f) for f in formats)
    spec.attribute("compression", compression)
    spec.attribute(KIND_ATTR, str(data.meta.get("kind", "")))
    text = json.dumps(data.meta, sort_keys=True, default=_json_default)
    for name, part in meta_chunks(text):
        spec.attribute(name, part)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OutputError(f"{what}: cannot write EXR ({_last_error(oiio.geterror, '?')})")
    try:
        # A band of rows at a time: the float32 staging copy stays small.
        for y0 in range(0, h, EXR_WRITE_ROWS):
            y1 = min(h, y0 + EXR_WRITE_ROWS)
            band = np.concatenate([a[y0:y1].astype(np.float32) for a in arrays], axis=2)
            if not out.write_scanlines(y0, y1, 0, np.ascontiguousarray(band)):
                raise OutputError(f"{what}: cannot write EXR ({_last_error(out.geterror, '?')})")
    finally:
        out.close()


#: Characters of metadata per EXR string attribute: tools that turn attributes into text
#: lines of at most 1024 bytes (pfstools' tags) read each one whole.
META_CHUNK_CHARS = 900


def meta_chunks(text: str) -> list[tuple[str, str]]:
    """The metadata JSON as EXR attributes: ``vetMeta`` holds the first
    :data:`META_CHUNK_CHARS` characters, ``vetMeta0001``, ``vetMeta0002``... the rest."""
    parts = [text[i : i + META_CHUNK_CHARS] for i in range(0, len(text), META_CHUNK_CHARS)]
    return [
        (META_ATTR if i == 0 else f"{META_ATTR}{i:04d}", p) for i, p in enumerate(parts or [""])
    ]


def _joined_meta(spec: Any) -> str:
    """The metadata JSON of an EXR header: ``vetMeta`` and its continuations, or the
    single ``vet:meta`` attribute of files written before."""
    text = spec.get_string_attribute(META_ATTR, "")
    if not text:
        return spec.get_string_attribute(LEGACY_ATTRS[META_ATTR], "")
    parts = [text]
    for i in range(1, 10**4):
        part = spec.get_string_attribute(f"{META_ATTR}{i:04d}", "")
        if not part:
            break
        parts.append(part)
    return "".join(parts)


def _last_error(geterror: Callable[[], str], default: str) -> str:
    """The last line of an OpenImageIO error (which may quote undecodable header bytes)."""
    try:
        lines = geterror().strip().splitlines()
    except UnicodeDecodeError:
        return "the header holds bytes that are not text"
    return lines[-1] if lines else default


def read_oiio(
    path: str | Path,
    what: str,
    attrs: tuple[str, ...] = (),
    before_pixels: Callable[[dict[str, str], int, int], None] | None = None,
    keep_half: bool = False,
) -> tuple[np.ndarray | list[np.ndarray], list[str], dict[str, str]]:
    """Read any image OpenImageIO reads at full resolution (subimage 0, MIP level 0;
    tiles handled by OIIO), checking the header before allocating.

    The header's data window and channel count are checked against
    :data:`MAX_CHANNELS` and the limits of :mod:`stages.formats.limits` (the
    pixel bytes it declares against the file's size on disk), and ``before_pixels(attrs,
    height, width)`` may refuse the file (by raising) before any pixel is read.

    Returns ``(pixels (H, W, C) float32, channel names, {attr: string value})``; with
    ``keep_half``, ``pixels`` is a list of (H, W) planes, float16 for HALF channels.
    """
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = _last_error(oiio.geterror, "unknown format")
        raise FormatError(f"{what}: not a readable image ({msg})")
    try:
        return _read_oiio_pixels(inp, path, what, attrs, before_pixels, keep_half)
    except UnicodeDecodeError:
        raise FormatError(f"{what}: header holds names or text that are not UTF-8") from None
    finally:
        inp.close()


def _read_oiio_pixels(
    inp: Any,
    path: str | Path,
    what: str,
    attrs: tuple[str, ...],
    before_pixels: Callable[[dict[str, str], int, int], None] | None,
    keep_half: bool = False,
) -> tuple[np.ndarray | list[np.ndarray], list[str], dict[str, str]]:
    spec = inp.spec()
    w, h, nch = int(spec.width), int(spec.height), int(spec.nchannels)
    if w <= 0 or h <= 0 or nch <= 0:
        raise FormatError(f"{what}: image has no pixels")
    if nch > MAX_CHANNELS:
        raise FormatError(f"{what}: image has {nch} channels, over the limit of {MAX_CHANNELS}")
    kinds = [str(t) for t in spec.channelformats] or [str(spec.format)] * nch
    half = [keep_half and k == "half" for k in kinds]
    declared = w * h * sum(2 if hf else 4 for hf in half)
    limits.check_declared(declared, Path(path).stat().st_size, what)
    values = {
        a: _joined_meta(spec) if a == META_ATTR else spec.get_string_attribute(a, "") for a in attrs
    }
    if before_pixels is not None:
        before_pixels(values, h, w)
    names = list(spec.channelnames)
    if not any(half):
        pixels = inp.read_image(0, 0, 0, nch, "float")
        if pixels is None:
            msg = _last_error(inp.geterror, "truncated?")
            raise FormatError(f"{what}: pixel data unreadable ({msg})")
        return np.asarray(pixels, dtype=np.float32).reshape(h, w, nch), names, values
    planes: list[np.ndarray] = []
    c0 = 0
    while c0 < nch:  # runs of channels of one kind, each read in its own type
        c1 = c0 + 1
        while c1 < nch and half[c1] == half[c0]:
            c1 += 1
        fmt = "half" if half[c0] else "float"
        run = inp.read_image(0, 0, c0, c1, fmt)
        if run is None:
            msg = _last_error(inp.geterror, "truncated?")
            raise FormatError(f"{what}: pixel data unreadable ({msg})")
        run = np.asarray(run, dtype=np.float16 if half[c0] else np.float32).reshape(h, w, c1 - c0)
        planes += [run[:, :, i] for i in range(c1 - c0)]
        c0 = c1
    return planes, names, values


def read_exr(path: Path, what: str | None = None) -> Layered:
    """Read a vet EXR; its metadata (size- and depth-limited JSON) and the image size it
    declares are checked before the pixels are read."""
    what = what or str(path)
    meta: dict[str, Any] = {}

    def check(values: dict[str, str], h: int, w: int) -> None:
        text = values[META_ATTR]
        if text:
            meta.update(_parse_meta(text, what))
            schema.check_meta(meta, what)
        _check_declared_size(declared_size(meta), (h, w), "", what)

    pixels, names, _ = read_oiio(path, what, (META_ATTR,), check, keep_half=True)
    data = Layered(meta=meta)
    grouped: dict[str, list[tuple[str, int]]] = {}
    for i, name in enumerate(names):
        layer, ch = _split_channel(name)
        grouped.setdefault(layer, []).append((ch, i))
    order = meta.get("channel_order", {}) if isinstance(meta.get("channel_order"), dict) else {}
    for layer, chans in grouped.items():
        wanted = order.get(layer)
        if (
            isinstance(wanted, list)
            and all(isinstance(c, str) for c in wanted)
            and sorted(wanted) == sorted(c for c, _ in chans)
        ):
            idx = dict(chans)
            chans = [(c, idx[c]) for c in wanted]
        if isinstance(pixels, list):
            data.layers[layer] = np.stack([pixels[i] for _, i in chans], axis=2)
        else:
            data.layers[layer] = np.ascontiguousarray(pixels[:, :, [i for _, i in chans]])
        data.channels[layer] = [c for c, _ in chans]
    return data


# --- NPZ ---------------------------------------------------------------------------


def write_npz(path: Path, data: Layered) -> None:
    """Write ``data`` as npz: float32 layers stored, compact ones deflated (module
    docstring), one member at a time."""
    arrays = {f"layer:{k}": v for k, v in data.layers.items()}
    arrays["__channels__"] = np.array(json.dumps(data.channels))
    arrays["__meta__"] = np.array(json.dumps(data.meta, sort_keys=True, default=_json_default))
    with zipfile.ZipFile(path, "w", allowZip64=True, compresslevel=1) as zf:
        for name, arr in arrays.items():
            method = zipfile.ZIP_DEFLATED if arr.dtype in COMPACT_DTYPES else zipfile.ZIP_STORED
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info._compresslevel = 1  # (the attribute zipfile reads; fast deflate)
            with zf.open(info, "w", force_zip64=True) as fp:
                np.lib.format.write_array(fp, np.asanyarray(arr), allow_pickle=False)


#: The tables every vet npz holds besides its ``layer:{name}.npy`` members.
_NPZ_TABLES = ("__meta__.npy", "__channels__.npy")
#: Zip methods numpy writes (stored, deflate); others (bzip2, lzma) are refused.
_NPZ_METHODS = (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED)
#: Most layers (npz members or EXR channels) one file may hold.
MAX_CHANNELS = 4096


#: What numpy's .npy reader and zipfile raise on damaged input (the header is parsed with
#: tokenize and ast, which have exceptions of their own).
_NPY_ERRORS = (
    ValueError,
    TypeError,
    NotImplementedError,  # zipfile: a member needing a zip version or feature it lacks
    SyntaxError,
    tokenize.TokenError,
    EOFError,
    OSError,
    zipfile.BadZipFile,
    zlib.error,
)


def _npz_member_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str):
    """``(shape, dtype, header bytes)`` of one .npy member, read without inflating its data."""
    member = info.filename
    try:
        with zf.open(info) as fp:
            version = np.lib.format.read_magic(fp)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
            else:
                raise ValueError(f"unsupported .npy version {version}")
            header = fp.tell()
    except _NPY_ERRORS as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise FormatError(f"{what}: member {member!r} is not a NumPy array ({first})") from None
    if any(int(n) < 0 for n in shape):
        raise FormatError(f"{what}: member {member!r} declares a negative shape {shape}")
    if dtype.hasobject:
        raise FormatError(
            f"{what}: member {member[:-4]!r} holds Python objects (pickle); refusing to load"
        )
    nbytes = math.prod(int(n) for n in shape) * dtype.itemsize
    if header + nbytes != info.file_size:
        raise FormatError(
            f"{what}: member {member[:-4]!r} declares {nbytes} bytes of data but the zip "
            f"holds {info.file_size - header}"
        )
    return tuple(int(n) for n in shape), dtype, header


def _npz_array(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str) -> np.ndarray:
    try:
        with zf.open(info) as fp:
            return np.lib.format.read_array(fp, allow_pickle=False)
    except _NPY_ERRORS as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise FormatError(f"{what}: corrupt .npz member {info.filename!r} ({first})") from None


def _npz_table(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str) -> Any:
    shape, dtype, _ = _npz_member_header(zf, info, what)
    if shape != () or dtype.kind != "U":
        raise FormatError(f"{what}: {info.filename[:-4]} is not a JSON string")
    if dtype.itemsize > 4 * limits.MAX_META_BYTES:
        raise FormatError(
            f"{what}: {info.filename[:-4]} is over the limit of {limits.MAX_META_BYTES} bytes"
        )
    kind = "metadata" if info.filename == "__meta__.npy" else "channel table"
    return limits.parse_json(str(_npz_array(zf, info, what)), what, kind)


def read_npz(path: Path, what: str | None = None) -> Layered:
    """Read a vet npz, checking every member's declared shape before inflating any.

    Order: member names and zip methods; each member's .npy header (no pickles; declared
    bytes equal to the zip's uncompressed size); the metadata and channel tables
    (size- and depth-limited JSON); each layer's shape against its channels, the other
    layers and the image size the metadata declares; the total against the input and
    compression-ratio limits of :mod:`stages.formats.limits`. Only then are layers read.

    Raises
    ------
    FormatError
        Any of the above fails (one line naming the file and what is wrong).
    """
    what = what or str(path)
    try:
        on_disk = Path(path).stat().st_size
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:
        raise FormatError(f"{what}: not a valid .npz file ({exc})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_CHANNELS:
            raise FormatError(f"{what}: .npz holds {len(infos)} members, over {MAX_CHANNELS}")
        tables: dict[str, zipfile.ZipInfo] = {}
        layers: dict[str, tuple[zipfile.ZipInfo, tuple, np.dtype]] = {}
        for info in infos:
            m = info.filename
            if not m.endswith(".npy") or not (m in _NPZ_TABLES or m.startswith("layer:")):
                raise FormatError(f"{what}: unexpected member {m!r} in .npz")
            if info.compress_type not in _NPZ_METHODS:
                raise FormatError(
                    f"{what}: member {m!r} uses zip method {info.compress_type}; "
                    "only stored and deflate are read"
                )
            if m in _NPZ_TABLES:
                tables[m] = info
            else:
                shape, dtype, _ = _npz_member_header(zf, info, what)
                layers[m[len("layer:") : -len(".npy")]] = (info, shape, dtype)
        if len(tables) != len(_NPZ_TABLES):
            raise FormatError(f"{what}: .npz is not a vet file (no __meta__ / __channels__)")
        meta = _parse_meta(tables["__meta__.npy"], what, zf)
        schema.check_meta(meta, what)
        channels = _npz_table(zf, tables["__channels__.npy"], what)
        if not isinstance(channels, dict):
            raise FormatError(f"{what}: corrupt channel table (not a JSON object)")
        expected = declared_size(meta)
        total = 0
        size: tuple[int, int] | None = None
        for name, (_, shape, dtype) in layers.items():
            chans = channels.get(name)
            if len(shape) != 3 or not isinstance(chans, list) or len(chans) != shape[2]:
                raise FormatError(f"{what}: layer {name!r} has shape {shape} but channels {chans}")
            if dtype.kind not in "fiu" or dtype.itemsize > 8:
                raise FormatError(f"{what}: layer {name!r} is not real numbers ({dtype})")
            if size is not None and shape[:2] != size:
                raise FormatError(
                    f"{what}: layers have different sizes {sorted({size, shape[:2]})}"
                )
            size = shape[:2]
            _check_declared_size(expected, size, name, what)
            kept = dtype in COMPACT_DTYPES
            total += math.prod(shape) * (dtype.itemsize if kept else max(dtype.itemsize, 4))
        limits.check_declared(total, on_disk, what)
        data = Layered(meta=meta)
        for name, (info, _, _) in layers.items():
            arr = _npz_array(zf, info, what)
            keep = arr.dtype if arr.dtype in COMPACT_DTYPES else np.float32
            data.layers[name] = np.ascontiguousarray(arr, dtype=keep)
            data.channels[name] = [str(c) for c in channels[name]]
    return data


# --- dispatch ------------------------------------------------------------------------


def _parse_meta(source: Any, what: str, zf: zipfile.ZipFile | None = None) -> dict[str, Any]:
    """The metadata object from JSON text (EXR attribute) or an npz member."""
    if zf is not None:
        meta = _npz_table(zf, source, what)
    else:
        meta = limits.parse_json(source, what, "metadata")
    if not isinstance(meta, dict):
        raise FormatError(f"{what}: metadata is not a JSON object")
    return meta


def declared_size(meta: dict[str, Any]) -> tuple[int, int, str] | None:
    """The image size that a file's metadata declares, if any: ``(height, width, field)``.

    From ``sensor_size`` ``[width, height]`` (calibrations) or ``rig.sensor_size``
    (captures, HDR images made from them); None when neither is a pair of positive ints
    (the schema reports malformed ones by name).
    """
    rig = meta.get("rig")
    for field_name, source in (
        ("sensor_size", meta.get("sensor_size")),
        ("rig.sensor_size", rig.get("sensor_size") if isinstance(rig, dict) else None),
    ):
        if (
            isinstance(source, list)
            and len(source) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in source)
        ):
            return int(source[1]), int(source[0]), field_name
    return None


def _check_declared_size(
    expected: tuple[int, int, str] | None, size: tuple[int, int], layer: str, what: str
) -> None:
    if expected is not None and tuple(size) != expected[:2]:
        raise FormatError(
            f"{what}: {expected[2]}: {expected[1]}x{expected[0]} but layer "
            f"{layer or 'image'!r} is {size[1]}x{size[0]} pixels; they must match"
        )


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_layered(path: str | Path) -> Layered:
    """Read a vet file (EXR or npz, sniffed by magic bytes); ``-`` reads stdin.

    The metadata is validated against :mod:`stages.formats.schema` before the pixels are
    read, and the layers against the metadata after.

    Raises
    ------
    InputError
        Missing or unreadable file.
    FormatError
        Not a vet or image file, over a limit of :mod:`stages.formats.limits`, or
        metadata outside the schema (one line naming the field and the allowed range).
    """
    what = "standard input" if str(path) == "-" else str(path)
    with spooled_input(path) as real:
        kind = sniff(real)
        data = read_exr(real, what) if kind == "exr" else read_npz(real, what)
    schema.check_layers(data.meta, data.layers, data.channels, what)
    return data


def write_layered(path: str | Path, data: Layered, fmt: str | None = None) -> None:
    """Write atomically as EXR or npz (by extension, or ``fmt``); ``-`` writes stdout."""
    fmt = fmt or format_for_output(str(path))
    data.meta["channel_order"] = {k: list(v) for k, v in data.channels.items()}
    with atomic_output(path, suffix="." + fmt) as tmp:
        if fmt == "exr":
            write_exr(tmp, data, what="standard output" if str(path) == "-" else str(path))
        else:
            write_npz(tmp, data)
