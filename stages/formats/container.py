"""The in-memory form of a vet file and what its EXR and npz forms share.

:class:`Layered` holds named float32 layers plus one JSON metadata dictionary; the
container readers and writers live in :mod:`stages.formats.exr` (OpenEXR) and
:mod:`stages.formats.layered` (npz, and the dispatch between the two). Here: the layer
and channel naming, the compact layer types, the metadata parsing and the sizes that a
file's metadata declares for its layers.

Sizes. Every layer has the main size (a capture's VET sensor, an HDR image's), except
that a capture whose rig declares a measurement camera of its own size
(``rig.measure_size``) may hold its measuring images ``M00``, ``M01``... at that size.
EXR keeps such layers in a second part of the file, npz as arrays of their own shape.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from . import limits

META_ATTR = "vetMeta"
KIND_ATTR = "vetKind"
#: The names vet wrote before: ``prefix:name`` attributes read as ``channel:tag`` by some
#: tools (pfstools warns there is no channel ``vet``). Still read.
LEGACY_ATTRS = {META_ATTR: "vet:meta", KIND_ATTR: "vet:kind"}

#: Layer types kept compact in memory and on disk (:mod:`stages.formats.layered`).
COMPACT_DTYPES = (np.dtype(np.int16), np.dtype(np.float16))

#: Most layers (npz members or EXR channels) one file may hold.
MAX_CHANNELS = 4096

#: Names of a capture's measuring images, the layers that may have a size of their own.
MEASURING_LAYER = re.compile(r"M\d{2,}")


@dataclass
class Layered:
    """Named float32 layers plus metadata. Layers share the main size (the first
    layer's), except those added with ``own_size`` (module docstring)."""

    layers: dict[str, np.ndarray] = field(default_factory=dict)
    channels: dict[str, list[str]] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def add(
        self, name: str, array: np.ndarray, channels: list[str], own_size: bool = False
    ) -> None:
        a = np.asarray(array)
        if a.dtype not in COMPACT_DTYPES:
            a = a.astype(np.float32, copy=False)
        if a.ndim == 2:
            a = a[:, :, None]
        if a.ndim != 3 or a.shape[2] != len(channels):
            raise ValueError(f"layer {name!r}: shape {a.shape} does not match channels {channels}")
        if self.layers and not own_size:
            h, w = self.shape
            if a.shape[:2] != (h, w):
                raise ValueError(f"layer {name!r}: size {a.shape[:2]} differs from {(h, w)}")
        self.layers[name] = np.ascontiguousarray(a)
        self.channels[name] = list(channels)

    @property
    def shape(self) -> tuple[int, int]:
        """The main size: the first layer's."""
        if not self.layers:
            return (0, 0)
        return next(iter(self.layers.values())).shape[:2]

    def parts(self) -> list[list[str]]:
        """The layer names grouped by size: the main size first, then each other size in
        the order its first layer was added (an EXR file's parts)."""
        groups: dict[tuple[int, int], list[str]] = {}
        for name, arr in self.layers.items():
            groups.setdefault(arr.shape[:2], []).append(name)
        return list(groups.values())


def empty_layers(specs: dict[str, tuple[tuple[int, ...], np.dtype]]) -> dict[str, np.ndarray]:
    """Uninitialised arrays for a reader to fill, one per ``{layer: (shape, dtype)}``.

    The measuring images (:data:`MEASURING_LAYER`) that share one shape and type are views
    of one stack ``(B, *shape)`` in the order of their numbers, so a capture takes them as
    that array (:func:`stack_of`) and never holds a copy beside them: a stream of 131
    subframes is most of a capture's memory."""
    series = sorted(
        (name for name in specs if MEASURING_LAYER.fullmatch(name)), key=lambda n: int(n[1:])
    )
    out: dict[str, np.ndarray] = {}
    if len(series) >= 2 and len({specs[n] for n in series}) == 1:
        shape, dtype = specs[series[0]]
        stack = np.empty((len(series), *shape), dtype)
        out.update((name, stack[b]) for b, name in enumerate(series))
    for name, (shape, dtype) in specs.items():
        if name not in out:
            out[name] = np.empty(shape, dtype)
    return {name: out[name] for name in specs}


def stack_of(arrays: list[np.ndarray]) -> np.ndarray | None:
    """The array ``arrays`` are the consecutive first-axis slices of, in order, when they
    are exactly that (as :func:`empty_layers` makes them), else None."""
    base = arrays[0].base if arrays else None
    if (
        not isinstance(base, np.ndarray)
        or not base.flags.c_contiguous
        or base.shape != (len(arrays), *arrays[0].shape)
    ):
        return None
    start = base.__array_interface__["data"][0]
    for b, a in enumerate(arrays):
        if a.base is not base or a.__array_interface__["data"][0] != start + b * base.strides[0]:
            return None
    return base


def channel_name(layer: str, ch: str) -> str:
    return f"{layer}.{ch}" if layer else ch


def split_channel(name: str) -> tuple[str, str]:
    if "." in name:
        layer, ch = name.rsplit(".", 1)
        return layer, ch
    return "", name


def parse_meta(source: Any, what: str) -> dict[str, Any]:
    """The metadata object from JSON text (an EXR attribute) or parsed JSON (an npz
    member's, already read by :func:`stages.formats.layered.npz_table`)."""
    meta = limits.parse_json(source, what, "metadata") if isinstance(source, str) else source
    if not isinstance(meta, dict):
        raise FormatError(f"{what}: metadata is not a JSON object")
    return meta


def _size_pair(source: Any) -> tuple[int, int] | None:
    """``(height, width)`` of a ``[width, height]`` pair of positive ints, else None."""
    if (
        isinstance(source, list)
        and len(source) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in source)
    ):
        return int(source[1]), int(source[0])
    return None


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
        pair = _size_pair(source)
        if pair is not None:
            return (*pair, field_name)
    return None


def declared_measure_size(meta: dict[str, Any]) -> tuple[int, int, str] | None:
    """The measurement camera's size a capture's metadata declares (``rig.measure_size``),
    ``(height, width, field)``; None when it has none (the sensor's size)."""
    rig = meta.get("rig")
    if meta.get("kind") != "capture" or not isinstance(rig, dict):
        return None
    pair = _size_pair(rig.get("measure_size"))
    return None if pair is None else (*pair, "rig.measure_size")


class SizeCheck:
    """Checks each layer's size against the metadata, before any pixel is read: the
    declared main size (or, where none is declared, the first layer's) for every layer,
    or the measurement camera's for a capture's measuring images (module docstring)."""

    def __init__(self, meta: dict[str, Any], what: str) -> None:
        self.main = declared_size(meta)
        self.measure = declared_measure_size(meta)
        self.what = what
        self.first: tuple[int, int] | None = None

    def __call__(self, layer: str, size: tuple[int, int]) -> None:
        size = (int(size[0]), int(size[1]))
        main = self.main[:2] if self.main is not None else self.first
        if main is None:
            self.first = main = size
        if size == main:
            return
        name, what = layer or "image", self.what
        if self.measure is not None and MEASURING_LAYER.fullmatch(layer):
            if size == self.measure[:2]:
                return
            m = self.measure
            raise FormatError(
                f"{what}: {m[2]}: {m[1]}x{m[0]} but measuring image {name!r} is "
                f"{size[1]}x{size[0]} pixels; it must be that or the sensor's size"
            )
        if self.main is None:
            raise FormatError(
                f"{what}: layers have different sizes {sorted({main, size})} (layer {name!r})"
            )
        e = self.main
        raise FormatError(
            f"{what}: {e[2]}: {e[1]}x{e[0]} but layer {name!r} is {size[1]}x{size[0]} "
            "pixels; they must match"
        )


#: Kinds of file whose every pixel must be finite (calibrations mark unmeasured cells NaN).
FINITE_KINDS = ("capture", "hdr", "motion")


def count_nonfinite(a: np.ndarray, block: int = 1 << 22) -> int:
    """How many values of ``a`` are NaN or infinite (0 for integers), counted a block of
    rows at a time (no boolean copy of a large image)."""
    if a.dtype.kind not in "fc" or a.size == 0:
        return 0
    rows = a.reshape(a.shape[0], -1) if a.ndim > 1 else a.reshape(-1, 1)
    step = max(1, block // max(rows.shape[1], 1))
    return sum(
        int(rows.shape[1] * len(part) - np.count_nonzero(np.isfinite(part)))
        for part in (rows[i : i + step] for i in range(0, rows.shape[0], step))
    )


def require_finite(data: Layered, what: str) -> None:
    """Refuse a file of :data:`FINITE_KINDS` any of whose layers holds a NaN or an
    infinity: :class:`~stages.errors.OutputError` naming the layer and the count (the
    one check of every data output, made before anything is written)."""
    from ..errors import OutputError

    if data.meta.get("kind") not in FINITE_KINDS:
        return
    for name, layer in data.layers.items():
        bad = count_nonfinite(layer)
        if bad:
            raise OutputError(
                f"{what}: layer {name or 'image'!r} holds {bad} NaN or infinite values of "
                f"{layer.size}; every value of an output must be finite (nothing written)"
            )


def json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
