"""Finding the captures under a folder, cheaply.

A *capture unit* is either a capture file (``*.exr`` or ``*.npz`` whose metadata says
``kind = "capture"``) or a capture folder (a folder holding ``capture.exr`` or
``capture.npz``; see :data:`stages.formats.capture.CAPTURE_FILENAMES`). Files inside a
capture folder (its raw measuring stream, its log) are never units of their own.

Classifying a file reads only its header: the EXR attribute ``vetKind`` (``vet:kind`` in
older files; parsed here in pure Python, without OpenImageIO) or the ``__meta__`` member of an ``.npz``. A file
whose header is readable but says another kind (an HDR image, a motion field) or no vet
kind at all (a foreign EXR) is *ignored*; a file whose header cannot be read is kept as a
unit, so that the run reports it as a failure with its reason instead of silently
skipping a damaged capture.
"""

from __future__ import annotations

import os
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import FormatError
from ..formats.capture import CAPTURE_FILENAMES
from ..formats.io import EXR_MAGIC, ZIP_MAGIC
from ..formats.limits import parse_json

#: File extensions that may hold a capture (compared in lower case).
CAPTURE_EXTENSIONS = (".exr", ".npz")
#: Headers larger than this are not parsed when classifying (bytes).
MAX_HEADER_BYTES = 16 * 1024 * 1024
#: Result of :func:`probe_kind` for a file whose header cannot be read.
UNREADABLE = "unreadable"


@dataclass(frozen=True)
class CaptureUnit:
    """One capture found under the batch root.

    Attributes
    ----------
    rel : str
        Its path relative to the root, ``/``-separated (``day1/a.exr``, or ``x`` for
        the capture folder ``x/``; ``.`` when the root itself is a capture folder). This
        is the capture's name in the manifest and the summary.
    path : Path
        The capture file to read (for a folder, the capture file inside it).
    is_folder : bool
        Whether the unit is a capture folder.
    """

    rel: str
    path: Path
    is_folder: bool


@dataclass(frozen=True)
class IgnoredFile:
    """A ``.exr`` / ``.npz`` file under the root that is not a capture, and why."""

    rel: str
    reason: str


def read_exr_attributes(path: str | Path, names: set[str]) -> dict[str, bytes]:
    """Raw values of some header attributes of an OpenEXR file, without decoding pixels.

    Parameters
    ----------
    path : str or Path
        The file.
    names : set of str
        Attribute names wanted (others are skipped).

    Returns
    -------
    dict mapping name to the attribute's raw value bytes (for a ``string`` attribute, the
    text in UTF-8 without terminator).

    Raises
    ------
    ValueError
        When the file is not OpenEXR or its header is truncated or malformed.
    OSError
        When the file cannot be read.
    """
    wanted = {n.encode() for n in names}
    found: dict[str, bytes] = {}
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8 or head[:4] != EXR_MAGIC:
            raise ValueError("not an OpenEXR file")
        consumed = 8
        while True:
            name = _cstring(f)
            if not name:
                return found
            kind = _cstring(f)  # (the attribute's type)
            raw = f.read(4)
            if len(raw) < 4:
                raise ValueError("truncated EXR header")
            (size,) = struct.unpack("<i", raw)
            consumed += len(name) + len(kind) + 2 + 4 + max(size, 0)
            if size < 0 or consumed > MAX_HEADER_BYTES:
                raise ValueError("malformed EXR header (attribute size)")
            if name in wanted:
                value = f.read(size)
                if len(value) < size:
                    raise ValueError("truncated EXR header")
                found[name.decode()] = value
            else:
                f.seek(size, os.SEEK_CUR)


def _cstring(f) -> bytes:
    """A NUL-terminated name of at most 255 bytes from the header ``f`` (without the NUL)."""
    out = bytearray()
    while True:
        c = f.read(1)
        if not c:
            raise ValueError("truncated EXR header")
        if c == b"\0":
            return bytes(out)
        out += c
        if len(out) > 255:
            raise ValueError("malformed EXR header (attribute name too long)")


def probe_kind(path: str | Path) -> str | None:
    """The vet ``kind`` a file declares, read from its header only.

    Returns
    -------
    str or None
        ``"capture"``, ``"hdr"``, ... as written by vet; ``None`` for a readable EXR or
        ``.npz`` that is not a vet file; :data:`UNREADABLE` when the header cannot be
        read (wrong magic bytes, truncated, permissions).
    """
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
        if magic == EXR_MAGIC:
            attrs = read_exr_attributes(path, {"vetKind", "vet:kind"})
            kind = (attrs.get("vetKind") or attrs.get("vet:kind", b"")).decode("utf-8", "replace")
            return kind or None
        if magic == ZIP_MAGIC:
            return _npz_kind(path)
    except Exception:  # noqa: BLE001 - whatever stops the header (an encrypted member's
        # RuntimeError, a malformed zip, a bad npy header) is the run's to report for this
        # capture alone, never a reason to stop the batch
        return UNREADABLE
    return UNREADABLE


def _npz_kind(path: str | Path) -> str | None:
    from ..formats.layered import read_npy

    with zipfile.ZipFile(path) as zf:
        if "__meta__.npy" not in zf.namelist():
            return None
        info = zf.getinfo("__meta__.npy")
        if info.flag_bits & 0x1:  # (encrypted: the reader refuses it, naming the member)
            return UNREADABLE
        if info.file_size > MAX_HEADER_BYTES:
            raise ValueError("metadata too large")
        with zf.open(info) as fp:
            text = str(read_npy(fp, info.file_size))
    try:
        meta = parse_json(text, str(path))
    except FormatError:
        return UNREADABLE
    kind = meta.get("kind") if isinstance(meta, dict) else None
    return str(kind) if kind else None


def _rel(path: Path, root: Path) -> str:
    rel = path.relative_to(root).as_posix()
    return rel or "."


def discover_captures(
    root: str | Path, exclude: list[str | Path] | tuple[str | Path, ...] = ()
) -> tuple[list[CaptureUnit], list[IgnoredFile]]:
    """Find the capture files and capture folders under ``root``.

    Parameters
    ----------
    root : str or Path
        Folder to search, recursively. Symbolic links to folders are not followed;
        hidden files and folders (names starting with ``.``) are skipped.
    exclude : sequence of paths
        Folders not to search (the batch's output folder when it lies inside ``root``).

    Returns
    -------
    units : list of CaptureUnit
        Sorted by ``rel``.
    ignored : list of IgnoredFile
        ``.exr`` / ``.npz`` files that are readable but not captures.
    """
    root = Path(root).absolute()
    excluded = {os.path.normcase(str(Path(p).absolute())) for p in exclude}
    units: list[CaptureUnit] = []
    ignored: list[IgnoredFile] = []
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        capture_file = next((here / n for n in CAPTURE_FILENAMES if n in filenames), None)
        if capture_file is not None and capture_file.is_file():
            units.append(CaptureUnit(_rel(here, root), capture_file, True))
            dirnames[:] = []
            continue
        dirnames[:] = sorted(
            d
            for d in dirnames
            if not d.startswith(".") and os.path.normcase(str(here / d)) not in excluded
        )
        for name in sorted(filenames):
            if name.startswith(".") or not name.lower().endswith(CAPTURE_EXTENSIONS):
                continue
            path = here / name
            if not path.is_file():
                continue
            kind = probe_kind(path)
            if kind == "capture" or kind == UNREADABLE:
                units.append(CaptureUnit(_rel(path, root), path, False))
            else:
                ignored.append(
                    IgnoredFile(
                        _rel(path, root), f"not a capture (kind: {kind or 'not a vet file'})"
                    )
                )
    units.sort(key=lambda u: u.rel)
    return units, ignored


def output_stems(units: list[CaptureUnit], root_name: str) -> dict[str, str]:
    """Each unit's output name without suffix, relative to the output folder.

    ``day1/a.exr`` gives ``day1/a``; the capture folder ``x`` gives ``x``; the root as a
    capture folder gives ``root_name``. When two units would share a stem (``a.exr`` and
    ``a.npz``, or ``x.exr`` and the folder ``x``), the *files* among them keep their
    extension in the stem (``a.exr``, ``a.npz``), which is unique within a folder.
    """

    def plain(u: CaptureUnit) -> str:
        if u.rel == ".":
            return root_name
        if u.is_folder:
            return u.rel
        return u.rel[: -len(Path(u.rel).suffix)]

    counts: dict[str, int] = {}
    for u in units:
        counts[plain(u)] = counts.get(plain(u), 0) + 1
    return {u.rel: (u.rel if counts[plain(u)] > 1 and not u.is_folder else plain(u)) for u in units}
