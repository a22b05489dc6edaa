"""Gray-code patterns for the LCoS and their per-pixel decoding.

The LCoS shows the Gray-code patterns of ``cv2.structured_light.GrayCodePattern``
(columns then rows, most significant bit first), each followed by its inverse; the VET
camera images a flat bright field through them. A pixel's bit is 1 where it is brighter
under the pattern than under the inverse (the standard pattern/inverse comparison, which
needs no per-pixel threshold and cancels the scene, vignetting and leakage); the bits are
a Gray code of the cell index that covers the pixel. OpenCV's own ``decode`` targets
projector-camera stereo pairs and ``getProjPixel`` is a per-pixel call, so the bits are
decoded here, vectorised, from the same patterns.

References
----------
.. [1] Gray, F. (1953). Pulse code communication. US Patent 2,632,058.
.. [2] Inokuchi, S., Sato, K., Matsuda, F. (1984). Range imaging system for 3-D object
   recognition. Proc. ICPR, 806-808 (Gray-code structured light).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def gray_bit_counts(lcos_cells: tuple[int, int]) -> tuple[int, int]:
    """Number of Gray-code bits for columns and rows, ``ceil(log2(n))`` each.

    Parameters
    ----------
    lcos_cells : (int, int)
        LCoS grid (width, height) in cells.

    Returns
    -------
    (int, int)
        Bits along x (columns) and along y (rows).
    """
    w, h = lcos_cells
    return math.ceil(math.log2(w)), math.ceil(math.log2(h))


def gray_code_patterns(lcos_cells: tuple[int, int]) -> list[np.ndarray]:
    """The Gray-code patterns of ``cv2.structured_light.GrayCodePattern``, as open masks.

    Parameters
    ----------
    lcos_cells : (int, int)
        LCoS grid (width, height) in cells.

    Returns
    -------
    list of ndarray of shape (H_cells, W_cells), bool
        True where the cell is open (white). Order as OpenCV generates them: for each
        column bit (most significant first) the pattern then its inverse, then the
        same for the row bits; ``2 * (bits_x + bits_y)`` images.
    """
    import cv2

    w, h = lcos_cells
    gen = cv2.structured_light.GrayCodePattern_create(width=int(w), height=int(h))
    ok, patterns = gen.generate()
    if not ok:  # pragma: no cover - OpenCV refuses only absurd sizes
        raise ValueError(f"OpenCV could not generate Gray-code patterns for {w}x{h} cells.")
    nx, ny = gray_bit_counts(lcos_cells)
    if len(patterns) != 2 * (nx + ny):  # pragma: no cover - guards an OpenCV change
        raise RuntimeError(
            f"unexpected Gray-code pattern count {len(patterns)} (expected {2 * (nx + ny)})"
        )
    return [np.asarray(p) > 127 for p in patterns]


def decode_gray(
    diffs: Sequence[np.ndarray],
    lcos_cells: tuple[int, int],
    min_contrast_dn: float = 8.0,
    rel_contrast: float = 0.25,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode per-pixel Gray-code bits into the LCoS cell seen by each pixel.

    Parameters
    ----------
    diffs : sequence of ndarray of shape (H, W)
        ``image(pattern) - image(inverse)`` for each bit, in the order of
        :func:`gray_code_patterns` (column bits MSB first, then row bits), DN.
    lcos_cells : (int, int)
        LCoS grid (width, height) in cells.
    min_contrast_dn : float
        A pixel whose strongest pattern/inverse difference is below this (DN) is not
        modulated by the LCoS (outside its footprint, or dark) and stays undecoded.
    rel_contrast : float
        A bit is trusted when ``|diff|`` is at least this fraction of the pixel's
        strongest difference; pixels with an untrusted bit (on a cell edge, blurred)
        stay undecoded.

    Returns
    -------
    cell_x, cell_y : ndarray of shape (H, W), int32
        Decoded cell column and row (-1 where undecoded).
    valid : ndarray of shape (H, W), bool
    """
    nx, ny = gray_bit_counts(lcos_cells)
    if len(diffs) != nx + ny:
        raise ValueError(
            f"need {nx + ny} pattern/inverse differences for {lcos_cells[0]}x{lcos_cells[1]} "
            f"cells, got {len(diffs)}."
        )
    stack = [np.asarray(d, dtype=np.float32) for d in diffs]
    shape = stack[0].shape
    if any(d.shape != shape for d in stack):
        raise ValueError("all pattern differences must have the same shape.")
    amp = np.zeros(shape, np.float32)
    for d in stack:
        np.maximum(amp, np.abs(d), out=amp)
    valid = amp >= min_contrast_dn
    floor = rel_contrast * amp
    for d in stack:
        valid &= np.abs(d) >= floor

    def _to_binary(bits: list[np.ndarray]) -> np.ndarray:
        value = np.zeros(shape, np.int32)
        b = np.zeros(shape, bool)
        for g in bits:  # MSB first: b_i = b_{i-1} xor g_i
            b = b ^ g
            value = (value << 1) | b
        return value

    cx = _to_binary([d > 0 for d in stack[:nx]])
    cy = _to_binary([d > 0 for d in stack[nx:]])
    valid &= (cx < lcos_cells[0]) & (cy < lcos_cells[1])
    cx = np.where(valid, cx, -1).astype(np.int32)
    cy = np.where(valid, cy, -1).astype(np.int32)
    return cx, cy, valid
