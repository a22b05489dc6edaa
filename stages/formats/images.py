"""Display images: 8-bit PNG / JPEG and 16-bit PNG / TIFF, written atomically.

These hold display-referred pictures (tone-mapped HDR images, false-colour maps), not
data: values are stored as given, with no transfer function applied here (the tone
mappers in :mod:`stages.tonemap` already applied their gamma). The output name's
extension decides the format; ``-`` writes a PNG to standard output.

=================  ============  ====================================
extension          format        bits per channel
=================  ============  ====================================
``.png``           PNG           8 or 16
``.jpg``, ``.jpeg``  JPEG        8 (quality :data:`JPEG_QUALITY`)
``.tif``, ``.tiff``  TIFF        8 or 16
``-``              PNG, stdout   8 or 16
=================  ============  ====================================
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .io import atomic_output
from .names import DISPLAY_FORMATS, display_format  # noqa: F401 - DISPLAY_FORMATS re-exported

#: Bits per channel each format can hold.
FORMAT_BITS: dict[str, tuple[int, ...]] = {"png": (8, 16), "jpeg": (8,), "tiff": (8, 16)}
#: JPEG quality (0-100) used for ``.jpg`` outputs.
JPEG_QUALITY = 95
_SUFFIX = {"png": ".png", "jpeg": ".jpg", "tiff": ".tif"}


def quantize_display(image: np.ndarray, bits: int = 8) -> np.ndarray:
    """Display values as unsigned integers of ``bits`` bits, shape (H, W, C).

    Parameters
    ----------
    image : ndarray of shape (H, W), (H, W, 1) or (H, W, 3)
        Floating point display values in [0, 1] (clipped there; NaN becomes 0), or
        integer code values: uint8 (scaled by 257 for 16 bits, exactly) or uint16
        (16 bits only).
    bits : {8, 16}
        Bits per channel.

    Returns
    -------
    ndarray of shape (H, W, C), uint8 or uint16
        ``round(v * (2**bits - 1))`` for floating point input.
    """
    if bits not in (8, 16):
        raise ValueError(f"Display images have 8 or 16 bits per channel; got {bits!r}.")
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3):
        raise ValueError(
            "A display image must have shape (H, W), (H, W, 1) or (H, W, 3); "
            f"got {np.shape(image)}."
        )
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"A display image cannot be empty (shape {np.shape(image)}).")
    if arr.dtype == np.uint8:
        return arr.copy() if bits == 8 else arr.astype(np.uint16) * np.uint16(257)
    if arr.dtype == np.uint16:
        if bits == 8:
            raise ValueError("A uint16 image cannot be written with 8 bits; convert it explicitly.")
        return arr.copy()
    if arr.dtype.kind != "f":
        raise ValueError(
            f"A display image must be floating point in [0, 1], uint8 or uint16; got {arr.dtype}."
        )
    top = float(2**bits - 1)
    scaled = np.nan_to_num(arr.astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    scaled = np.rint(np.clip(scaled, 0.0, 1.0) * top)
    return scaled.astype(np.uint8 if bits == 8 else np.uint16)


def encode_display_image(image: np.ndarray, fmt: str = "png", bits: int = 8) -> bytes:
    """Encode a display image as PNG, JPEG or TIFF bytes (see :func:`quantize_display`).

    Channels are taken as R, G, B (or grey) and reordered for OpenCV, which stores BGR.
    """
    if fmt not in FORMAT_BITS:
        raise ValueError(f"Unknown display image format {fmt!r}; use png, jpeg or tiff.")
    if bits not in FORMAT_BITS[fmt]:
        raise InputError(
            f"{fmt.upper()} holds only 8 bits per channel, not {bits}; "
            "write a .png or .tif file for 16 bits"
        )
    import cv2

    codes = quantize_display(image, bits)
    if codes.shape[2] == 3:
        codes = codes[:, :, ::-1]
    codes = np.ascontiguousarray(codes)
    params: list[int] = []
    if fmt == "jpeg":
        params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
    ok, buffer = cv2.imencode(_SUFFIX[fmt], codes, params)
    if not ok:
        raise InputError(f"OpenCV could not encode a {bits}-bit {fmt.upper()} image")
    return buffer.tobytes()


def write_display_image(path: str | Path, image: np.ndarray, bits: int = 8) -> None:
    """Write a display image atomically; the extension picks the format, ``-`` is stdout.

    Parameters
    ----------
    path : str or Path
        Output file (``.png``, ``.jpg``, ``.jpeg``, ``.tif``, ``.tiff``), or ``-`` for a
        PNG on standard output. An existing file is replaced only once the new one is
        complete.
    image : ndarray of shape (H, W), (H, W, 1) or (H, W, 3)
        R, G, B or grey display values: float in [0, 1], uint8, or uint16 (16 bits).
    bits : {8, 16}
        Bits per channel; JPEG allows only 8.

    Raises
    ------
    InputError
        Unknown extension, 16 bits asked of JPEG, or a missing output folder.
    ValueError
        An image of the wrong shape or type, or ``bits`` other than 8 or 16.
    """
    fmt = display_format(path)
    if bits not in (8, 16):
        raise ValueError(f"Display images have 8 or 16 bits per channel; got {bits!r}.")
    if bits not in FORMAT_BITS[fmt]:
        raise InputError(
            f"{path}: {fmt.upper()} holds only 8 bits per channel, not {bits}; "
            "write a .png or .tif file for 16 bits"
        )
    data = encode_display_image(image, fmt, bits)
    with atomic_output(path, suffix=_SUFFIX[fmt] if str(path) == "-" else None) as tmp:
        tmp.write_bytes(data)


def captioned(image: np.ndarray, caption: str, dark: bool = False) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with a 22-pixel caption bar above it.

    ``dark`` puts white text on black (for tone-mapped pictures), else black on white.
    """
    import cv2

    bg, fg = ((0, 0, 0), (255, 255, 255)) if dark else ((255, 255, 255), (0, 0, 0))
    bar = np.empty((22, image.shape[1], 3), np.uint8)
    bar[:] = bg
    cv2.putText(bar, caption, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, fg, 1, cv2.LINE_AA)
    return np.concatenate([bar, image], axis=0)
