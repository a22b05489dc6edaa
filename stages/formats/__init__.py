"""File formats: layered EXR/npz container, captures, HDR images, atomic I/O."""

from .capture import Capture, provenance_entry, read_capture, resolve_capture_path, write_capture
from .hdr import MASK_CODES, HDRImage, read_hdr, write_hdr
from .layered import Layered, read_layered, write_layered

__all__ = [
    "Capture",
    "HDRImage",
    "Layered",
    "MASK_CODES",
    "provenance_entry",
    "read_capture",
    "read_hdr",
    "read_layered",
    "resolve_capture_path",
    "write_capture",
    "write_hdr",
    "write_layered",
]
