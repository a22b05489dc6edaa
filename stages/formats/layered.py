"""Layered float images with JSON metadata, stored as OpenEXR or NumPy ``.npz``.

This is the container under every vet file (captures, HDR images, motion fields,
calibrations). A file holds named *layers*, each an ``ndarray of shape (H, W, C)``
float32 with named channels, plus one JSON metadata dictionary.

EXR layout: channel ``"{layer}.{channel}"`` (the unnamed layer ``""`` uses bare channel
names such as ``R, G, B`` so that viewers show it); metadata as the string attributes
``vet:kind`` and ``vet:meta`` (JSON), readable with ``oiiotool --info -v``.

NPZ layout: array ``layer:{name}`` per layer, plus 0-d unicode arrays ``__channels__``
and ``__meta__`` holding JSON. Nothing is pickled; reading refuses object arrays.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, InputError
from .io import atomic_output, check_size, sniff, spooled_input
from .names import format_for_output

META_ATTR = "vet:meta"
KIND_ATTR = "vet:kind"


@dataclass
class Layered:
    """Named float32 layers of one size plus metadata."""

    layers: dict[str, np.ndarray] = field(default_factory=dict)
    channels: dict[str, list[str]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def add(self, name: str, array: np.ndarray, channels: list[str]) -> None:
        a = np.asarray(array, dtype=np.float32)
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


def write_exr(path: Path, data: Layered, compression: str = "zip") -> None:
    oiio = _oiio()
    h, w = data.shape
    names: list[str] = []
    arrays: list[np.ndarray] = []
    for layer, arr in data.layers.items():
        names += [_channel_name(layer, c) for c in data.channels[layer]]
        arrays.append(arr)
    pixels = np.ascontiguousarray(np.concatenate(arrays, axis=2), dtype=np.float32)
    spec = oiio.ImageSpec(w, h, len(names), "float")
    spec.channelnames = tuple(names)
    spec.attribute("compression", compression)
    spec.attribute(KIND_ATTR, str(data.meta.get("kind", "")))
    spec.attribute(META_ATTR, json.dumps(data.meta, sort_keys=True, default=_json_default))
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise InputError(f"{path}: cannot write EXR ({oiio.geterror()})")
    try:
        if not out.write_image(pixels):
            raise InputError(f"{path}: cannot write EXR ({out.geterror()})")
    finally:
        out.close()


def read_oiio(
    path: str | Path, what: str, attrs: tuple[str, ...] = ()
) -> tuple[np.ndarray, list[str], dict[str, str]]:
    """Read any image OpenImageIO reads at full resolution (subimage 0, MIP level 0;
    tiles handled by OIIO), checking the declared size before allocating.

    Returns ``(pixels (H, W, C) float32, channel names, {attr: string value})``.
    """
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = oiio.geterror().strip().splitlines()
        raise FormatError(f"{what}: not a readable image ({msg[-1] if msg else 'unknown format'})")
    try:
        spec = inp.spec()
        w, h, nch = spec.width, spec.height, spec.nchannels
        if w <= 0 or h <= 0 or nch <= 0:
            raise FormatError(f"{what}: image has no pixels")
        check_size(int(w) * int(h) * int(nch) * 4, what)
        pixels = inp.read_image(0, 0, 0, nch, "float")
        if pixels is None:
            msg = inp.geterror().strip().splitlines()
            raise FormatError(f"{what}: pixel data unreadable ({msg[-1] if msg else 'truncated?'})")
        values = {a: spec.get_string_attribute(a, "") for a in attrs}
        names = list(spec.channelnames)
    finally:
        inp.close()
    return np.asarray(pixels, dtype=np.float32).reshape(h, w, nch), names, values


def read_exr(path: Path, what: str | None = None) -> Layered:
    what = what or str(path)
    pixels, names, attrs = read_oiio(path, what, (META_ATTR,))
    meta_json = attrs[META_ATTR]
    meta = _parse_meta(meta_json, what) if meta_json else {}
    data = Layered(meta=meta)
    grouped: dict[str, list[tuple[str, int]]] = {}
    for i, name in enumerate(names):
        layer, ch = _split_channel(name)
        grouped.setdefault(layer, []).append((ch, i))
    order = meta.get("channel_order", {}) if isinstance(meta.get("channel_order"), dict) else {}
    for layer, chans in grouped.items():
        wanted = order.get(layer)
        if wanted and sorted(wanted) == sorted(c for c, _ in chans):
            idx = dict(chans)
            chans = [(c, idx[c]) for c in wanted]
        data.layers[layer] = np.ascontiguousarray(pixels[:, :, [i for _, i in chans]])
        data.channels[layer] = [c for c, _ in chans]
    return data


# --- NPZ ---------------------------------------------------------------------------


def write_npz(path: Path, data: Layered) -> None:
    arrays = {f"layer:{k}": v for k, v in data.layers.items()}
    arrays["__channels__"] = np.array(json.dumps(data.channels))
    arrays["__meta__"] = np.array(json.dumps(data.meta, sort_keys=True, default=_json_default))
    with open(path, "wb") as f:
        np.savez(f, **arrays)


def _npz_member_header(zf: zipfile.ZipFile, member: str, what: str) -> tuple[tuple, np.dtype]:
    with zf.open(member) as fp:
        try:
            version = np.lib.format.read_magic(fp)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fp)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(fp)
        except ValueError as exc:
            raise FormatError(f"{what}: member {member!r} is not a NumPy array ({exc})") from None
    return shape, dtype


def read_npz(path: Path, what: str | None = None) -> Layered:
    what = what or str(path)
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise FormatError(f"{what}: not a valid .npz file ({exc})") from None
    with zf:
        members = zf.namelist()
        total = 0
        for m in members:
            if not m.endswith(".npy"):
                raise FormatError(f"{what}: unexpected member {m!r} in .npz")
            shape, dtype = _npz_member_header(zf, m, what)
            if dtype.hasobject:
                raise FormatError(
                    f"{what}: member {m[:-4]!r} holds Python objects (pickle); refusing to load"
                )
            total += int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        check_size(total, what)
        try:
            npz = np.load(path, allow_pickle=False)
            arrays = {k: npz[k] for k in npz.files}
        except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
            raise FormatError(f"{what}: corrupt .npz ({exc})") from None
    if "__meta__" not in arrays or "__channels__" not in arrays:
        raise FormatError(f"{what}: .npz is not a vet file (no __meta__ / __channels__)")
    meta = _parse_meta(str(arrays.pop("__meta__")), what)
    try:
        channels = json.loads(str(arrays.pop("__channels__")))
    except json.JSONDecodeError:
        raise FormatError(f"{what}: corrupt channel table") from None
    data = Layered(meta=meta)
    for key, arr in arrays.items():
        if not key.startswith("layer:"):
            continue
        name = key[len("layer:") :]
        chans = channels.get(name)
        if arr.ndim != 3 or not isinstance(chans, list) or len(chans) != arr.shape[2]:
            raise FormatError(f"{what}: layer {name!r} has shape {arr.shape} but channels {chans}")
        if not np.issubdtype(arr.dtype, np.number):
            raise FormatError(f"{what}: layer {name!r} is not numeric")
        data.layers[name] = np.ascontiguousarray(arr, dtype=np.float32)
        data.channels[name] = [str(c) for c in chans]
    shapes = {a.shape[:2] for a in data.layers.values()}
    if len(shapes) > 1:
        raise FormatError(f"{what}: layers have different sizes {sorted(shapes)}")
    return data


# --- dispatch ------------------------------------------------------------------------


def _parse_meta(text: str, what: str) -> dict[str, Any]:
    try:
        meta = json.loads(text)
    except json.JSONDecodeError:
        raise FormatError(f"{what}: metadata is not valid JSON") from None
    if not isinstance(meta, dict):
        raise FormatError(f"{what}: metadata is not a JSON object")
    return meta


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_layered(path: str | Path) -> Layered:
    """Read a vet file (EXR or npz, sniffed by magic bytes); ``-`` reads stdin."""
    what = "standard input" if str(path) == "-" else str(path)
    with spooled_input(path) as real:
        kind = sniff(real)
        return read_exr(real, what) if kind == "exr" else read_npz(real, what)


def write_layered(path: str | Path, data: Layered, fmt: str | None = None) -> None:
    """Write atomically as EXR or npz (by extension, or ``fmt``); ``-`` writes stdout."""
    fmt = fmt or format_for_output(str(path))
    data.meta["channel_order"] = {k: list(v) for k, v in data.channels.items()}
    with atomic_output(path, suffix="." + fmt) as tmp:
        if fmt == "exr":
            write_exr(tmp, data)
        else:
            write_npz(tmp, data)
