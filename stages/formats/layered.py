"""Layered float images with JSON metadata, stored as OpenEXR or NumPy ``.npz``.

This is the container under every vet file (captures, HDR images, motion fields,
calibrations). A file holds named *layers*, each an ``ndarray of shape (H, W, C)``
float32 with named channels, plus one JSON metadata dictionary.

The layers share one size, except a capture's measuring images from a measurement camera
of its own size (:mod:`stages.formats.container`, which holds :class:`Layered`).

EXR layout: :mod:`stages.formats.exr` (a second part for layers of their own size).

NPZ layout: array ``layer:{name}`` per layer (each of its own shape), plus 0-d unicode
arrays ``__channels__`` and ``__meta__`` holding JSON. Nothing is pickled; reading
refuses object arrays.

Compact layers. A layer held as ``int16`` or ``float16`` (whole digital numbers, such as
a capture's measuring stream) stays compact: EXR stores its channels as HALF (exact for
whole numbers up to 2048 in magnitude, the nearest even number up to 4096: below the
shot noise of such codes), npz as the array itself, deflated; both read back as
``float16`` (EXR) or the stored type (npz). Every other layer is float32.
"""

from __future__ import annotations

import json
import math
import threading
import tokenize
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..cluster import in_order, solve_threads
from ..errors import FormatError
from . import limits, schema
from .container import (
    COMPACT_DTYPES,
    KIND_ATTR,
    LEGACY_ATTRS,
    MAX_CHANNELS,
    META_ATTR,
    Layered,
    SizeCheck,
    declared_measure_size,
    declared_size,
    empty_layers,
    json_default,
    parse_meta,
    require_finite,
)
from .exr import EXR_WRITE_ROWS, MAX_PARTS, _oiio, meta_chunks, read_exr, read_oiio, write_exr
from .inflate import ERRORS as INFLATE_ERRORS
from .inflate import open_member
from .io import atomic_output, sniff, spooled_input
from .names import format_for_output

#: Re-exported: the container's parts live in :mod:`stages.formats.container` and
#: :mod:`stages.formats.exr`; readers of other kinds import them from here.
__all__ = [
    "COMPACT_DTYPES",
    "EXR_WRITE_ROWS",
    "KIND_ATTR",
    "LEGACY_ATTRS",
    "MAX_CHANNELS",
    "MAX_PARTS",
    "META_ATTR",
    "Layered",
    "_oiio",
    "_parse_meta",
    "declared_measure_size",
    "declared_size",
    "meta_chunks",
    "read_exr",
    "read_layered",
    "read_npz",
    "read_oiio",
    "write_exr",
    "write_layered",
    "write_npz",
]


# --- NPZ ---------------------------------------------------------------------------


def write_npz(path: Path, data: Layered) -> None:
    """Write ``data`` as npz: float32 layers stored, compact ones deflated (module
    docstring), one member at a time."""
    arrays = {f"layer:{k}": v for k, v in data.layers.items()}
    arrays["__channels__"] = np.array(json.dumps(data.channels))
    arrays["__meta__"] = np.array(json.dumps(data.meta, sort_keys=True, default=json_default))
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
    *INFLATE_ERRORS,
)


#: The .npy header is a Python literal that numpy parses with ``ast``, which CPython 3.11
#: cannot do on two threads at once ("SystemError: AST constructor recursion depth
#: mismatch"); members read on threads parse their headers one at a time.
_HEADER_LOCK = threading.Lock()


def _read_npy_header(fp) -> tuple[tuple[int, ...], bool, np.dtype]:
    """``(shape, fortran_order, dtype)`` of the .npy stream ``fp``, left at its data."""
    with _HEADER_LOCK:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            return np.lib.format.read_array_header_1_0(fp)
        if version == (2, 0):
            return np.lib.format.read_array_header_2_0(fp)
    raise ValueError(f"unsupported .npy version {version}")


def _npz_member_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str):
    """``(shape, dtype, header bytes)`` of one .npy member, read without inflating its data."""
    member = info.filename
    try:
        with zf.open(info) as fp:
            shape, _, dtype = _read_npy_header(fp)
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


def read_npy(fp, max_bytes: int) -> np.ndarray:
    """The array of the .npy stream ``fp`` (a file or zip member), read into place; safe
    on threads, unlike ``np.lib.format.read_array`` (:data:`_HEADER_LOCK`). ``max_bytes``
    bounds the data its header may declare (the member's size), checked before anything
    is allocated. ValueError on Python objects (no pickle) or a declared size over the
    bound, EOFError on truncated data."""
    shape, fortran, dtype = _read_npy_header(fp)
    if dtype.hasobject:
        raise ValueError("it holds Python objects (pickle); refusing to load")
    declared = math.prod(shape) * dtype.itemsize
    if declared > max_bytes:
        raise ValueError(f"its header declares {declared} bytes of data, more than its {max_bytes}")
    arr = np.empty(shape, dtype, order="F" if fortran else "C")
    view = memoryview(arr.reshape(-1, order="A").view(np.uint8))
    got = 0
    while got < view.nbytes:
        n = fp.readinto(view[got:])
        if not n:
            raise EOFError(f"{got} of {view.nbytes} bytes of data")
        got += n
    return arr


def _npz_array(zf: zipfile.ZipFile, info: zipfile.ZipInfo, what: str) -> np.ndarray:
    """One .npy member's array (its header checked by :func:`_npz_member_header`)."""
    try:
        with open_member(zf, info) as fp:
            return read_npy(fp, info.file_size)
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


def read_npz(path: Path, what: str | None = None, skip: frozenset[str] = frozenset()) -> Layered:
    """Read a vet npz, checking every member's declared shape before inflating any.

    Order: member names (each once), zip methods and flags (no encryption); each member's
    .npy header (no pickles; declared bytes equal to the zip's uncompressed size); the
    metadata and channel tables (size- and depth-limited JSON); each layer's shape against
    its channels and the sizes the metadata declares
    (:class:`~stages.formats.container.SizeCheck`); the total against the input and
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
        tables, members = _npz_members(zf, what)
        meta = _parse_meta(tables["__meta__.npy"], what, zf)
        schema.check_meta(meta, what)
        channels = _npz_table(zf, tables["__channels__.npy"], what)
        if not isinstance(channels, dict):
            raise FormatError(f"{what}: corrupt channel table (not a JSON object)")
        _check_npz_layers(members, channels, meta, on_disk, what)
        kept = {name: member for name, member in members.items() if name not in skip}
        return _inflate_npz(path, zf, kept, channels, meta, what)


#: One layer member of an npz: its zip entry, declared shape and type.
_Member = tuple[zipfile.ZipInfo, tuple, np.dtype]


def _npz_members(
    zf: zipfile.ZipFile, what: str
) -> tuple[dict[str, zipfile.ZipInfo], dict[str, _Member]]:
    """The zip's tables and layer members (headers read, not their data), each name once,
    stored or deflated, not encrypted."""
    infos = zf.infolist()
    if len(infos) > MAX_CHANNELS:
        raise FormatError(f"{what}: .npz holds {len(infos)} members, over {MAX_CHANNELS}")
    tables: dict[str, zipfile.ZipInfo] = {}
    layers: dict[str, _Member] = {}
    seen: set[str] = set()
    for info in infos:
        m = info.filename
        if not m.endswith(".npy") or not (m in _NPZ_TABLES or m.startswith("layer:")):
            raise FormatError(f"{what}: unexpected member {m!r} in .npz")
        if m in seen:
            raise FormatError(
                f"{what}: member {m!r} is in the .npz twice; refusing to choose one of them"
            )
        seen.add(m)
        if info.flag_bits & 0x1:
            raise FormatError(f"{what}: member {m!r} is encrypted; vet reads no encrypted files")
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
    return tables, layers


def _check_npz_layers(
    layers: dict[str, _Member], channels: dict, meta: dict[str, Any], on_disk: int, what: str
) -> None:
    """Each layer's shape against its channels and the declared sizes; the pixel bytes
    of all against the limits."""
    sizes = SizeCheck(meta, what)
    total = 0
    for name, (_, shape, dtype) in layers.items():
        chans = channels.get(name)
        if len(shape) != 3 or not isinstance(chans, list) or len(chans) != shape[2]:
            raise FormatError(f"{what}: layer {name!r} has shape {shape} but channels {chans}")
        if dtype.kind not in "fiu" or dtype.itemsize > 8:
            raise FormatError(f"{what}: layer {name!r} is not real numbers ({dtype})")
        sizes(name, shape[:2])
        kept = dtype in COMPACT_DTYPES
        total += math.prod(shape) * (dtype.itemsize if kept else max(dtype.itemsize, 4))
    limits.check_declared(total, on_disk, what)


def _inflate_npz(
    path: Path,
    zf: zipfile.ZipFile,
    layers: dict[str, _Member],
    channels: dict,
    meta: dict[str, Any],
    what: str,
) -> Layered:
    """The checked layers read, each member inflated into its place (the stream's into
    one stack: :func:`~stages.formats.container.empty_layers`)."""
    data = Layered(meta=meta)
    data.layers = empty_layers(
        {
            name: (shape, dtype if dtype in COMPACT_DTYPES else np.dtype(np.float32))
            for name, (_, shape, dtype) in layers.items()
        }
    )
    infos_in_order = [info for info, _, _ in layers.values()]
    for name, arr in zip(layers, _npz_arrays(path, zf, infos_in_order, what), strict=True):
        if arr.shape != data.layers[name].shape:
            raise FormatError(f"{what}: member {name!r} does not hold the shape it declares")
        np.copyto(data.layers[name], arr, casting="unsafe")
        data.channels[name] = [str(c) for c in channels[name]]
    return data


def _npz_arrays(
    path: Path, zf: zipfile.ZipFile, infos: list[zipfile.ZipInfo], what: str
) -> Iterator[np.ndarray]:
    """The members ``infos`` of the npz at ``path`` (open as ``zf``) read as arrays, in
    order. On :func:`~stages.cluster.solve_threads` threads, each with a zip handle of its
    own (zlib inflates without holding the GIL), at most two members per thread ahead of
    the one handed out, so a file of many layers (a capture's stream) is inflated on every
    core the process may use with a few layers in flight."""
    if min(solve_threads(), len(infos)) <= 1:
        for info in infos:
            yield _npz_array(zf, info, what)
        return
    local = threading.local()
    handles: list[zipfile.ZipFile] = []
    lock = threading.Lock()

    def one(info: zipfile.ZipInfo) -> np.ndarray:
        z = getattr(local, "zf", None)
        if z is None:
            try:
                z = zipfile.ZipFile(path)
            except (zipfile.BadZipFile, OSError, ValueError) as exc:
                raise FormatError(f"{what}: cannot reopen the .npz ({exc})") from None
            local.zf = z
            with lock:
                handles.append(z)
        return _npz_array(z, info, what)

    try:
        yield from in_order(lambda k: one(infos[k]), len(infos), ahead=2)
    finally:
        for z in handles:
            z.close()


# --- dispatch ------------------------------------------------------------------------


def _parse_meta(source: Any, what: str, zf: zipfile.ZipFile | None = None) -> dict[str, Any]:
    """The metadata object from JSON text (EXR attribute) or an npz member."""
    return parse_meta(_npz_table(zf, source, what) if zf is not None else source, what)


def read_layered(path: str | Path, skip: frozenset[str] = frozenset()) -> Layered:
    """Read a vet file (EXR or npz, sniffed by magic bytes); ``-`` reads stdin. Layers
    named in ``skip`` are checked but not kept (an npz does not inflate them).

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
        data = read_exr(real, what, skip) if kind == "exr" else read_npz(real, what, skip)
    schema.check_layers(data.meta, data.layers, data.channels, what)
    return data


def write_layered(path: str | Path, data: Layered, fmt: str | None = None) -> None:
    """Write atomically as EXR or npz (by extension, or ``fmt``); ``-`` writes stdout.

    A capture, HDR image or motion field with a NaN or infinite value anywhere is not
    written (:func:`~stages.formats.container.require_finite`, OutputError)."""
    fmt = fmt or format_for_output(str(path))
    require_finite(data, "standard output" if str(path) == "-" else str(path))
    data.meta["channel_order"] = {k: list(v) for k, v in data.channels.items()}
    with atomic_output(path, suffix="." + fmt) as tmp:
        if fmt == "exr":
            write_exr(tmp, data, what="standard output" if str(path) == "-" else str(path))
        else:
            write_npz(tmp, data)
