"""Output names: which file format an output path's extension asks for.

Both the data writers (:mod:`stages.formats.layered`, through :mod:`stages.formats.io`)
and the display-image writer (:mod:`stages.formats.images`) choose their format here, and
:func:`stages.formats.io.check_output` refuses a bad name with the same rules before a
command does any work. ``-`` (standard output) takes each kind's default format.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError

#: Data formats (captures, HDR images, motion fields, calibrations) by extension.
DATA_FORMATS: dict[str, str] = {".exr": "exr", ".npz": "npz"}

#: Display image formats by extension.
DISPLAY_FORMATS: dict[str, str] = {
    ".png": "png",
    ".jpg": "jpeg",
    ".jpeg": "jpeg",
    ".tif": "tiff",
    ".tiff": "tiff",
}


def format_for_output(path: str | Path, default: str = "exr") -> str:
    """Data format (``"exr"`` or ``"npz"``) for an output name; ``-`` gives ``default``.

    Raises
    ------
    InputError
        When the extension is neither ``.exr`` nor ``.npz``.
    """
    if str(path) == "-":
        return default
    ext = Path(path).suffix.lower()
    fmt = DATA_FORMATS.get(ext)
    if fmt is None:
        raise InputError(
            f"{path}: unsupported output extension {ext or '(none)'!r}; use .exr or .npz"
        )
    return fmt


def display_format(path: str | Path) -> str:
    """Format (``"png"``, ``"jpeg"`` or ``"tiff"``) for an output name; ``-`` gives PNG.

    Raises
    ------
    InputError
        When the extension is not one of :data:`DISPLAY_FORMATS`.
    """
    if str(path) == "-":
        return "png"
    ext = Path(path).suffix.lower()
    fmt = DISPLAY_FORMATS.get(ext)
    if fmt is None:
        raise InputError(
            f"{path}: unsupported image extension {ext or '(none)'!r}; "
            "use .png, .jpg, .jpeg, .tif or .tiff"
        )
    return fmt
