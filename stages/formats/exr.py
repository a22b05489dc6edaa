"""The OpenEXR form of a vet file (:class:`~stages.formats.container.Layered`).

Channel ``"{layer}.{channel}"`` (the unnamed layer ``""`` uses bare channel names such
as ``R, G, B`` so that viewers show it); metadata as the string attributes ``vetKind`` and
``vetMeta`` (JSON, continued in ``vetMeta0001``... past 900 characters, so that tools
reading attributes as lines of text take them whole), readable with ``oiiotool --info
-v`` (files written before use ``vet:kind`` and ``vet:meta``, still read). Compact layers
(``int16``, ``float16``) are stored as HALF channels, every other one as FLOAT.

Parts. A file whose layers all share one size is a single-part EXR. Layers of another
size (a capture's measuring images from a measurement camera of its own size) go in
further parts of a multi-part EXR, one per size (OpenImageIO subimages): part 0,
named ``main``, holds the main-size layers and the metadata; part 1, named ``measure``
for measuring images, holds the rest, its data window of their size at the origin and,
as OpenEXR requires of every part, the display window of part 0.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError, OutputError
from ..rig import MAX_SENSOR_SIDE
from . import limits, schema
from .container import (
    COMPACT_DTYPES,
    KIND_ATTR,
    LEGACY_ATTRS,
    MAX_CHANNELS,
    MEASURING_LAYER,
    META_ATTR,
    Layered,
    SizeCheck,
    channel_name,
    empty_layers,
    json_default,
    parse_meta,
    split_channel,
)

#: Rows per EXR write (bounds the float32 staging buffer).
EXR_WRITE_ROWS = 64
#: Rows per block of a scanline part's read (all its channels decoded once, a block at a
#: time: :meth:`_Part.layers`).
READ_ROWS = 32
#: Most parts (subimages) a vet EXR may hold.
MAX_PARTS = 16
#: Characters of metadata per EXR string attribute: tools that turn attributes into text
#: lines of at most 1024 bytes (pfstools' tags) read each one whole.
META_CHUNK_CHARS = 900


def _oiio():
    import OpenImageIO as oiio

    return oiio


def _part_spec(oiio: Any, data: Layered, names: list[str], compression: str) -> Any:
    """The header of one part: its layers' channels (HALF for compact layers)."""
    h, w = data.layers[names[0]].shape[:2]
    channels: list[str] = []
    formats: list[str] = []
    for layer in names:
        arr = data.layers[layer]
        channels += [channel_name(layer, c) for c in data.channels[layer]]
        formats += ["half" if arr.dtype in COMPACT_DTYPES else "float"] * arr.shape[2]
    # (OpenImageIO writes channel formats only where they differ: a part of HALF
    # channels alone is a HALF image.)
    spec = oiio.ImageSpec(w, h, len(channels), formats[0] if len(set(formats)) == 1 else "float")
    spec.channelnames = tuple(channels)
    if len(set(formats)) > 1:
        spec.channelformats = tuple(oiio.TypeDesc(f) for f in formats)
    spec.attribute("compression", compression)
    return spec


def _part_names(parts: list[list[str]]) -> list[str]:
    """Each part's name, unique as OpenEXR requires: ``main``, ``measure`` for the first
    further part of measuring images alone, ``part{k}`` for any other."""
    out = ["main"]
    for k, names in enumerate(parts[1:], start=1):
        measuring = all(MEASURING_LAYER.fullmatch(n) for n in names)
        out.append("measure" if measuring and "measure" not in out else f"part{k}")
    return out


def write_exr(path: Path, data: Layered, compression: str = "zip", what: str | None = None) -> None:
    """Write ``data`` as a multi-layer float32 EXR at ``path`` (``what``: its name in
    messages, when ``path`` is a temporary file); layers of other sizes than the first's
    in further parts (module docstring). Raises OutputError on failure."""
    what = what or str(path)
    oiio = _oiio()
    parts = _exr_parts(data)
    specs = [_part_spec(oiio, data, names, compression) for names in parts]
    main = specs[0]
    main.attribute(KIND_ATTR, str(data.meta.get("kind", "")))
    text = json.dumps(data.meta, sort_keys=True, default=json_default)
    for name, chunk in meta_chunks(text):
        main.attribute(name, chunk)
    if len(specs) > 1:
        for spec, name in zip(specs, _part_names(parts), strict=True):
            spec.attribute("oiio:subimagename", name)
            # OpenEXR: every part of a file shares the display window.
            spec.full_x, spec.full_y = main.full_x, main.full_y
            spec.full_width, spec.full_height = main.full_width, main.full_height
    out = oiio.ImageOutput.create(str(path))
    opened = out is not None and (
        out.open(str(path), specs) if len(specs) > 1 else out.open(str(path), main)
    )
    if not opened:
        raise OutputError(f"{what}: cannot write EXR ({_last_error(oiio.geterror, '?')})")
    try:
        for k, (spec, names) in enumerate(zip(specs, parts, strict=True)):
            if k and not out.open(str(path), spec, "AppendSubimage"):
                raise OutputError(f"{what}: cannot write EXR ({_last_error(out.geterror, '?')})")
            _write_part(out, [data.layers[n] for n in names], what)
    finally:
        out.close()


def _exr_parts(data: Layered) -> list[list[str]]:
    """The layer names of each part: :meth:`Layered.parts`, with measuring images of
    the main size that are all compact moved to a part of their own after the first (so
    that every part of a capture with a stream is of one kind: its HALF channels are
    written as they are, with no conversion of mixed channel formats)."""
    parts = data.parts()
    main = parts[0]
    measuring = [n for n in main if MEASURING_LAYER.fullmatch(n)]
    if (
        measuring
        and len(measuring) < len(main)
        and all(data.layers[n].dtype in COMPACT_DTYPES for n in measuring)
    ):
        moved = set(measuring)
        parts = [[n for n in main if n not in moved], measuring, *parts[1:]]
    return parts


#: float16 of each int16, indexed by its bits as uint16 (exact: numpy's own conversion).
_HALF_OF_INT16 = (
    np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.int16).astype(np.float16)
)


def _as_half(a: np.ndarray) -> np.ndarray:
    """A compact layer's rows as float16 (int16 through :data:`_HALF_OF_INT16`)."""
    if a.dtype == np.int16:
        return _HALF_OF_INT16[a.view(np.uint16)]
    return a.astype(np.float16, copy=False)


def _write_part(out: Any, arrays: list[np.ndarray], what: str) -> None:
    """A band of rows at a time: the staging copy stays small. A part of compact layers
    alone (a HALF part) is staged as float16, any other as float32."""
    h = arrays[0].shape[0]
    half = all(a.dtype in COMPACT_DTYPES for a in arrays)
    for y0 in range(0, h, EXR_WRITE_ROWS):
        y1 = min(h, y0 + EXR_WRITE_ROWS)
        if half:
            band = np.concatenate([_as_half(a[y0:y1]) for a in arrays], axis=2)
        else:
            band = np.concatenate([a[y0:y1].astype(np.float32) for a in arrays], axis=2)
        if not out.write_scanlines(y0, y1, 0, np.ascontiguousarray(band)):
            raise OutputError(f"{what}: cannot write EXR ({_last_error(out.geterror, '?')})")


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


def _open(path: str | Path, what: str) -> Any:
    oiio = _oiio()
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = _last_error(oiio.geterror, "unknown format")
        raise FormatError(f"{what}: not a readable image ({msg})")
    return inp


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
    inp = _open(path, what)
    try:
        head = _Part(inp, 0, what, keep_half)
        limits.check_declared(head.nbytes, Path(path).stat().st_size, what)
        values = {a: _attribute(head.spec, a) for a in attrs}
        if before_pixels is not None:
            before_pixels(values, head.h, head.w)
        return head.pixels(inp), head.names, values
    except UnicodeDecodeError:
        raise FormatError(f"{what}: header holds names or text that are not UTF-8") from None
    finally:
        inp.close()


def _attribute(spec: Any, name: str) -> str:
    return _joined_meta(spec) if name == META_ATTR else spec.get_string_attribute(name, "")


class _Part:
    """One part's header (the current subimage of ``inp``), checked before its pixels."""

    def __init__(self, inp: Any, index: int, what: str, keep_half: bool) -> None:
        spec = inp.spec()
        self.index, self.what, self.spec = index, what, spec
        self.w, self.h, self.nch = int(spec.width), int(spec.height), int(spec.nchannels)
        where = f" (part {index})" if index else ""
        if self.w <= 0 or self.h <= 0 or self.nch <= 0:
            raise FormatError(f"{what}: image{where} has no pixels")
        if self.nch > MAX_CHANNELS:
            raise FormatError(
                f"{what}: image{where} has {self.nch} channels, over the limit of {MAX_CHANNELS}"
            )
        self.origin = (int(spec.x), int(spec.y))
        _check_window(spec, self.origin, f"{what}: image{where}")
        kinds = [str(t) for t in spec.channelformats] or [str(spec.format)] * self.nch
        self.half = [keep_half and k == "half" for k in kinds]
        self.nbytes = self.w * self.h * sum(2 if hf else 4 for hf in self.half)
        self.names = list(spec.channelnames)

    def pixels(self, inp: Any) -> np.ndarray | list[np.ndarray]:
        """``(H, W, C)`` float32, or (any HALF channel kept) a list of ``(H, W)`` planes."""
        h, w, nch, half = self.h, self.w, self.nch, self.half
        if not any(half):
            return self._read(inp, 0, nch, "float").reshape(h, w, nch)
        planes: list[np.ndarray] = []
        c0 = 0
        while c0 < nch:  # runs of channels of one kind, each read in its own type
            c1 = c0 + 1
            while c1 < nch and half[c1] == half[c0]:
                c1 += 1
            run = self._read(inp, c0, c1, "half" if half[c0] else "float")
            run = run.reshape(h, w, c1 - c0)
            planes += [run[:, :, i] for i in range(c1 - c0)]
            c0 = c1
        return planes

    def layers(self, inp: Any, groups: dict[str, list[tuple[str, int]]]) -> dict[str, np.ndarray]:
        """Each layer of ``groups`` (``{layer: [(channel, index in the part), ...]}``) as
        ``(H, W, C)``: float16 where every one of its channels is a kept HALF channel,
        else float32.

        A scanline part is decoded once, :data:`READ_ROWS` rows of all its channels at a
        time, each block copied into the layers: no array of all the part's channels is
        made (a capture's stream is most of the file). A tiled part is read whole.
        """
        kept = {lay: all(self.half[i] for _, i in chans) for lay, chans in groups.items()}
        if self.spec.tile_width:
            pixels = self.pixels(inp)
            if isinstance(pixels, list):
                return {
                    lay: np.stack([pixels[i] for _, i in chans], axis=2)
                    for lay, chans in groups.items()
                }
            return {
                lay: np.ascontiguousarray(pixels[:, :, [i for _, i in chans]])
                for lay, chans in groups.items()
            }
        out = empty_layers(
            {
                lay: (
                    (self.h, self.w, len(chans)),
                    np.dtype(np.float16 if kept[lay] else np.float32),
                )
                for lay, chans in groups.items()
            }
        )
        fmt = "half" if all(self.half) else "float"  # (HALF values are exact as float)
        y, z = int(self.spec.y), int(self.spec.z)
        for r0 in range(0, self.h, READ_ROWS):
            r1 = min(self.h, r0 + READ_ROWS)
            block = inp.read_scanlines(self.index, 0, y + r0, y + r1, z, 0, self.nch, fmt)
            if block is None:
                self._unreadable(inp)
            # Channel planes first (one transposing copy): copying a few channels at a
            # time straight out of the interleaved block is several times slower.
            planes = np.asarray(block).reshape(-1, self.nch).T.copy()
            del block
            for lay, chans in groups.items():
                dest = out[lay][r0:r1].reshape(-1, len(chans))
                for j, (_, i) in enumerate(chans):
                    dest[:, j] = planes[i]
        return out

    def _unreadable(self, inp: Any) -> None:
        msg = _last_error(inp.geterror, "truncated?")
        where = f" of part {self.index}" if self.index else ""
        raise FormatError(f"{self.what}: pixel data{where} unreadable ({msg})")

    def _read(self, inp: Any, c0: int, c1: int, fmt: str) -> np.ndarray:
        pixels = inp.read_image(self.index, 0, c0, c1, fmt)
        if pixels is None:
            self._unreadable(inp)
        return np.asarray(pixels, dtype=np.float16 if fmt == "half" else np.float32)


def _check_window(spec: Any, origin: tuple[int, int], what: str) -> None:
    """A flat image (no depth, not deep) whose data window starts within
    :data:`~stages.rig.MAX_SENSOR_SIDE` pixels of the origin (its size is the limits')."""
    if getattr(spec, "deep", False) or int(spec.depth) != 1 or int(spec.z) != 0:
        raise FormatError(f"{what}: is a deep or volume image; vet reads flat images only")
    if max(abs(origin[0]), abs(origin[1])) > MAX_SENSOR_SIDE:
        raise FormatError(
            f"{what}: data window at ({origin[0]}, {origin[1]}); allowed within "
            f"{MAX_SENSOR_SIDE} pixels of the origin"
        )


def _parts(inp: Any, what: str) -> list[_Part]:
    """Every part's header, at most :data:`MAX_PARTS`."""
    heads = [_Part(inp, 0, what, True)]
    while inp.seek_subimage(len(heads), 0):
        if len(heads) == MAX_PARTS:
            raise FormatError(f"{what}: EXR holds more than {MAX_PARTS} parts")
        heads.append(_Part(inp, len(heads), what, True))
    inp.geterror()  # (the failed seek past the last part leaves a message)
    return heads


def read_exr(path: Path, what: str | None = None, skip: frozenset[str] = frozenset()) -> Layered:
    """Read a vet EXR, every part of it but the layers named in ``skip``. Its metadata
    (size- and depth-limited JSON), the layer sizes it declares
    (:class:`~stages.formats.container.SizeCheck`) and the pixel bytes of all parts
    together (:mod:`stages.formats.limits`) are checked before any pixel is read."""
    what = what or str(path)
    inp = _open(path, what)
    try:
        return _read_exr(inp, path, what, skip)
    except UnicodeDecodeError:
        raise FormatError(f"{what}: header holds names or text that are not UTF-8") from None
    finally:
        inp.close()


def _read_exr(inp: Any, path: str | Path, what: str, skip: frozenset[str] = frozenset()) -> Layered:
    heads = _parts(inp, what)
    nch = sum(p.nch for p in heads)
    if nch > MAX_CHANNELS:
        raise FormatError(f"{what}: EXR holds {nch} channels, over the limit of {MAX_CHANNELS}")
    limits.check_declared(sum(p.nbytes for p in heads), Path(path).stat().st_size, what)
    meta: dict[str, Any] = {}
    text = _joined_meta(heads[0].spec)
    if text:
        meta.update(parse_meta(text, what))
        schema.check_meta(meta, what)
    for head in heads if meta.get("kind") else ():
        if head.origin != (0, 0):
            where = f" (part {head.index})" if head.index else ""
            raise FormatError(
                f"{what}: data window{where} at {head.origin}; a vet file's layers lie at (0, 0)"
            )
    check = SizeCheck(meta, what)
    grouped: list[dict[str, list[tuple[str, int]]]] = []
    seen: set[str] = set()
    for head in heads:
        groups: dict[str, list[tuple[str, int]]] = {}
        for i, name in enumerate(head.names):
            layer, ch = split_channel(name)
            if layer in seen:
                raise FormatError(f"{what}: layer {layer or 'image'!r} is in two parts of the EXR")
            groups.setdefault(layer, []).append((ch, i))
        for layer in groups:
            check(layer, (head.h, head.w))
        seen.update(groups)
        grouped.append(groups)
    data = Layered(meta=meta)
    order = meta.get("channel_order", {}) if isinstance(meta.get("channel_order"), dict) else {}
    for head, groups in zip(heads, grouped, strict=True):
        ordered: dict[str, list[tuple[str, int]]] = {}
        for layer, chans in groups.items():
            if layer in skip:
                continue
            wanted = order.get(layer)
            if (
                isinstance(wanted, list)
                and all(isinstance(c, str) for c in wanted)
                and sorted(wanted) == sorted(c for c, _ in chans)
            ):
                idx = dict(chans)
                chans = [(c, idx[c]) for c in wanted]
            ordered[layer] = chans
        if not ordered:
            continue
        for layer, array in head.layers(inp, ordered).items():
            data.layers[layer] = array
            data.channels[layer] = [c for c, _ in ordered[layer]]
    return data
