"""Linear radiance in: checking, sanitising, luminance and robust black/white levels.

The shared first steps of every tone-mapping operator of :mod:`stages.tonemap`: the
input is refused unless it is a real (H, W, C) or (H, W) array with ``C`` = 1 or 3,
made safe (NaN and negatives to 0, ``+inf`` to the brightest finite level, with a
:class:`RuntimeWarning`), and measured (luminance, black and white levels that scale
exactly with the input).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

#: Relative luminance weights of linear Rec. ITU-R BT.709 / sRGB primaries.
REC709_LUMA: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)

#: Percentile of the positive luminance taken as the black level of the log mapping.
BLACK_PERCENTILE = 1.0


def luminance(radiance: np.ndarray) -> np.ndarray:
    """Relative luminance of linear radiance.

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance; ``C`` = 3 is taken as linear Rec. 709 ``R, G, B``, ``C`` = 1 (or
        a 2-D array) as luminance already.

    Returns
    -------
    ndarray of shape (H, W), float32
        ``0.2126 R + 0.7152 G + 0.0722 B``, or the single channel. NaN stays NaN.

    References
    ----------
    .. [1] Recommendation ITU-R BT.709-6, "Parameter values for the HDTV standards for
       production and international programme exchange", 2015, item 3.2.
    """
    arr = check_radiance(radiance)
    if arr.shape[2] == 1:
        return arr[:, :, 0].astype(np.float32, copy=True)
    weights = np.asarray(REC709_LUMA, dtype=np.float32)
    return np.tensordot(arr.astype(np.float32, copy=False), weights, axes=([2], [0])).astype(
        np.float32, copy=False
    )


def robust_levels(radiance: np.ndarray) -> tuple[float, float]:
    """Black and white luminance levels of an image, robust to hot pixels and noise.

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, any units; NaN, infinite and negative samples are ignored.

    Returns
    -------
    black : float
        The :data:`BLACK_PERCENTILE`-th percentile of the positive luminance, in the
        input's units.
    white : float
        The maximum of the 3x3 median-filtered luminance: the brightest level that at
        least a few neighbouring pixels reach, so isolated hot pixels do not set it but
        small real highlights (a lamp, a specular spot) do. 0 when no sample is positive.

    Both scale exactly with the input, which makes every operator here independent of
    the units of the radiance.
    """
    lum = clean_luminance(luminance(radiance))
    return estimate_black(lum), estimate_white(lum)


def check_radiance(radiance: np.ndarray) -> np.ndarray:
    """Return ``radiance`` as an (H, W, C) view, refusing shapes and types we cannot map."""
    arr = np.asarray(radiance)
    if arr.dtype.kind not in "fiu" or arr.dtype == np.bool_:
        raise ValueError(f"Radiance must be a real numeric array, not an array of {arr.dtype}.")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise ValueError(
            f"Radiance must have shape (H, W, C) or (H, W); got an array of shape {arr.shape}."
        )
    if arr.shape[2] not in (1, 3):
        raise ValueError(
            f"Radiance must have 1 (Y) or 3 (R, G, B) channels; got {arr.shape[2]} channels."
        )
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"Radiance is empty (shape {np.asarray(radiance).shape}).")
    return arr


def sanitize(radiance: np.ndarray) -> np.ndarray:
    """(H, W, C) float32 copy with NaN and negatives set to 0 and +inf to the top finite level."""
    arr = check_radiance(radiance).astype(np.float32, copy=True)
    finite = np.isfinite(arr)
    if not finite.all():
        bad = int(arr.size - np.count_nonzero(finite))
        warnings.warn(
            f"{bad} of {arr.size} radiance samples are NaN or infinite; NaN and -inf are "
            "shown as black, +inf as the brightest finite level.",
            RuntimeWarning,
            stacklevel=3,
        )
        top = float(arr[finite].max()) if finite.any() else 0.0
        arr[np.isposinf(arr)] = max(top, 0.0)
        arr[~np.isfinite(arr)] = 0.0
    np.maximum(arr, 0.0, out=arr)
    return arr


def clean_luminance(lum: np.ndarray) -> np.ndarray:
    lum = np.where(np.isfinite(lum), lum, 0.0).astype(np.float32, copy=False)
    return np.maximum(lum, 0.0)


def warn_if_unlit(white: float, stacklevel: int) -> bool:
    """True (after a :class:`RuntimeWarning` at ``stacklevel`` above the caller) when the
    white level is not positive: the radiance has no positive samples and the
    tone-mapped image is black."""
    import warnings

    if white > 0.0:
        return False
    warnings.warn(
        "The radiance has no positive samples; the tone-mapped image is black.",
        RuntimeWarning,
        stacklevel=stacklevel + 1,
    )
    return True


def estimate_white(lum: np.ndarray) -> float:
    import cv2

    if lum.shape[0] >= 3 and lum.shape[1] >= 3:
        smoothed = cv2.medianBlur(np.ascontiguousarray(lum, dtype=np.float32), 3)
    else:
        smoothed = lum
    white = float(smoothed.max())
    if white <= 0.0:
        # Only isolated pixels are lit: the median removed them all; use them anyway.
        white = float(lum.max())
    return max(white, 0.0)


def estimate_black(lum: np.ndarray) -> float:
    positive = lum[lum > 0]
    if positive.size == 0:
        return 0.0
    return float(np.percentile(positive, BLACK_PERCENTILE))


def check_level(name: str, value: float | None) -> float | None:
    if value is None:
        return None
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"The {name} level must be a positive finite radiance; got {value}.")
    return value
