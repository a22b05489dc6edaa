"""Tone mapping: linear HDR radiance to display-referred images in [0, 1].

Every operator takes scene-referred linear radiance of shape ``(H, W, C)`` with ``C`` = 1
(``Y``) or 3 (``R, G, B``), or a 2-D ``(H, W)`` luminance map, in any units (scene units,
DN/s, ...), and returns display-referred float32 values in [0, 1] of the same shape, with
the display transfer function (``gamma``) already applied: the result is what an 8- or
16-bit image file stores, see :func:`stages.formats.images.write_display_image`.

Results do not depend on the absolute scale of the input: each operator normalises the
luminance by levels estimated robustly from the image itself (:func:`robust_levels`), or
by levels the caller passes (``black`` / ``white``, in the input's units), which lets
several images (the methods of an evaluation, say) share one normalisation.

Invalid samples are made safe before mapping: NaN and negative values (noise in
reconstructed dark pixels) become 0 and ``+inf`` becomes the brightest finite level. A
:class:`RuntimeWarning` reports non-finite samples.

Operators (:data:`OPERATORS`):

``log``
    Global logarithmic mapping of luminance with colour ratios preserved
    (:func:`tonemap_log`); the default.
``reinhard``, ``drago``, ``mantiuk``
    OpenCV's implementations (:func:`tonemap_reinhard`, :func:`tonemap_drago`,
    :func:`tonemap_mantiuk`).
"""

from __future__ import annotations

import contextlib
import inspect
import math
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

#: Names accepted by :func:`tonemap`, default first.
OPERATORS: tuple[str, ...] = ("log", "reinhard", "drago", "mantiuk")

#: Display gamma each operator uses when :func:`tonemap` is given ``gamma=None``. The
#: log mapping already spaces its output roughly perceptually, so it gets none; the
#: OpenCV operators produce display-linear values and get the usual 2.2.
DEFAULT_GAMMA: dict[str, float] = {"log": 1.0, "reinhard": 2.2, "drago": 2.2, "mantiuk": 2.2}

#: Relative luminance weights of linear Rec. ITU-R BT.709 / sRGB primaries.
REC709_LUMA: tuple[float, float, float] = (0.2126, 0.7152, 0.0722)

#: Percentile of the positive luminance taken as the black level of the log mapping.
BLACK_PERCENTILE = 1.0
#: Default colour saturation exponent of the log mapping: keeps the scene's colour ratios
#: in the light a gamma-2.2 display emits (see :func:`tonemap_log`).
LOG_SATURATION = 1.0 / 2.2
#: Percentile of the output luminance of Mantiuk's operator taken as white.
MANTIUK_WHITE_PERCENTILE = 99.9
#: Largest white/black ratio the log mapping spans (120 dB); a darker black level is
#: raised to ``white / MAX_LOG_RANGE`` so that a few near-zero samples cannot flatten the
#: whole picture.
MAX_LOG_RANGE = 1e6
#: OpenCV's tone mappers take logs of luminance floored at this value.
_OPENCV_LOG_FLOOR = 1e-4


# --------------------------------------------------------------------------- helpers


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
    arr = _check_radiance(radiance)
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
    lum = _clean_luminance(luminance(radiance))
    return _estimate_black(lum), _estimate_white(lum)


def _check_radiance(radiance: np.ndarray) -> np.ndarray:
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


def _sanitize(radiance: np.ndarray) -> np.ndarray:
    """(H, W, C) float32 copy with NaN and negatives set to 0 and +inf to the top finite level."""
    arr = _check_radiance(radiance).astype(np.float32, copy=True)
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


def _clean_luminance(lum: np.ndarray) -> np.ndarray:
    lum = np.where(np.isfinite(lum), lum, 0.0).astype(np.float32, copy=False)
    return np.maximum(lum, 0.0)


def _estimate_white(lum: np.ndarray) -> float:
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


def _estimate_black(lum: np.ndarray) -> float:
    positive = lum[lum > 0]
    if positive.size == 0:
        return 0.0
    return float(np.percentile(positive, BLACK_PERCENTILE))


def _check_level(name: str, value: float | None) -> float | None:
    if value is None:
        return None
    value = float(value)
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"The {name} level must be a positive finite radiance; got {value}.")
    return value


def _check_exposure_gamma(exposure: float, gamma: float) -> tuple[float, float]:
    exposure = float(exposure)
    gamma = float(gamma)
    if not math.isfinite(exposure) or abs(exposure) > 64:
        raise ValueError(f"Exposure must be a finite number of stops within +/-64; got {exposure}.")
    if not math.isfinite(gamma) or gamma <= 0.0:
        raise ValueError(f"Gamma must be a positive finite number; got {gamma}.")
    return exposure, gamma


def _pad_for_opencv(rgb: np.ndarray, min_size: int) -> np.ndarray:
    """Pad (H, W, 3) for OpenCV's tone mappers; the caller crops back to (H, W).

    Images smaller than ``min_size`` are edge-padded up to it. OpenCV begins by mapping
    ``x -> (x - min) / (max - min)``, which would shift the whole image by its darkest
    sample and send that sample to zero luminance (and to NaN, see :func:`_stretch`);
    when no sample is 0, one edge-replicated row or column (the shorter) is appended
    with a black pixel in its last place, so that the stretch is a pure scaling and the
    operator sees the luminance ratios of the scene.
    """
    h, w = rgb.shape[:2]
    pad_h, pad_w = max(0, min_size - h), max(0, min_size - w)
    anchor = float(rgb.min()) > 0.0
    if anchor:
        if h <= w:
            pad_w += 1
        else:
            pad_h += 1
    if not (pad_h or pad_w):
        return rgb
    out = np.pad(rgb, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    if anchor:
        out[-1, -1] = 0.0
    return out


def _stretch(display: np.ndarray) -> np.ndarray:
    """Redo OpenCV's final min-max stretch to [0, 1], with NaN taken as the minimum.

    OpenCV's operators divide each channel by the luminance, which gives 0/0 = NaN for
    pixels whose (stretched) luminance is exactly 0, the darkest ones; a NaN then makes
    OpenCV skip its final normalisation altogether. Those pixels belong at black, and
    the stretch, being affine, is the same whether or not OpenCV already applied it.
    """
    finite = np.isfinite(display)
    if not finite.any():
        return np.zeros_like(display)
    lo = float(display[finite].min())
    hi = float(display[finite].max())
    out = np.where(finite, display, lo)
    if hi - lo > 1e-12:
        out = (out - lo) / (hi - lo)
    return out.astype(np.float32, copy=False)


def _encode(display: np.ndarray, gamma: float, shape: tuple[int, ...]) -> np.ndarray:
    """Clip display-linear (H, W, C) to [0, 1], apply 1/gamma, restore the input's shape."""
    out = np.clip(display, 0.0, 1.0).astype(np.float32, copy=False)
    if gamma != 1.0:
        out = np.power(out, np.float32(1.0 / gamma), dtype=np.float32)
    return out.reshape(shape)


def _fit_to_gamut(rgb: np.ndarray) -> np.ndarray:
    """Scale each pixel down so that its largest channel is at most 1 (keeps hue)."""
    peak = rgb.max(axis=2, keepdims=True)
    scale = np.where(peak > 1.0, 1.0 / np.maximum(peak, 1e-30), 1.0).astype(np.float32)
    return rgb * scale


# ------------------------------------------------------------------------ operators


def tonemap_log(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 1.0,
    black: float | None = None,
    white: float | None = None,
    saturation: float = LOG_SATURATION,
) -> np.ndarray:
    """Global logarithmic tone mapping of luminance, colour ratios preserved.

    With ``L`` the luminance (Rec. 709 weights, or the single channel), ``L_b`` the black
    and ``L_w`` the white level, ``k = 2**exposure`` and ``s`` the saturation:

    .. math::

        L_d = \\min\\left(1,\\ \\frac{\\ln(1 + k L / L_b)}{\\ln(1 + L_w / L_b)}\\right),
        \\qquad
        C_d = \\left(L_d \\left(\\frac{C}{L}\\right)^{s}\\right)^{1/\\gamma}
        \\quad (C = R, G, B)

    i.e. the classic logarithmic mapping ``log(1 + L) / log(1 + L_max)`` of [1]_ with the
    luminance measured in units of the black level, so that ``L_w`` maps to 1, ``L_b`` to
    ``ln 2 / ln(1 + L_w / L_b)`` and every stop in between gets about the same share of
    the display range. ``L_d`` is a display code value (the log curve is already close
    to perceptually uniform, so no further gamma is applied by default). Colour is
    carried by the ratios ``C / L`` [2]_: ``s = 1`` scales ``R, G, B`` by ``L_d / L``,
    keeping the ratios in code values, which a display (light = code ** 2.2) shows
    over-saturated; the default ``s = 1 / 2.2`` keeps them in the displayed light
    instead. A pixel whose largest channel would exceed 1 is scaled down as a whole,
    keeping its hue. Levels estimated from the image scale with it, so the result does
    not depend on the units of the radiance.

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units. NaN and negative
        samples are shown as black, ``+inf`` as white.
    exposure : float, optional
        Scene-side exposure in stops: the radiance is multiplied by ``2**exposure``
        before mapping while the levels stay those of the unscaled image (positive is
        brighter; what exceeds white clips).
    gamma : float, optional
        Display gamma applied to the result (1 = none, the default).
    black, white : float, optional
        Black and white luminance levels in the radiance's units; estimated by
        :func:`robust_levels` when not given. A black level darker than
        ``white / MAX_LOG_RANGE`` is raised to it.
    saturation : float, optional
        Exponent ``s`` of the colour ratios, in [0, 4]: 0 gives grey, 1 keeps the
        ratios in code values, ``1 / 2.2`` (default) in displayed light.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] E. Reinhard, G. Ward, S. Pattanaik, P. Debevec, W. Heidrich and K. Myszkowski,
       "High Dynamic Range Imaging: Acquisition, Display, and Image-Based Lighting",
       2nd ed., Morgan Kaufmann, 2010, section 8.1.1 "Logarithmic and exponential
       mappings".
    .. [2] C. Schlick, "Quantization techniques for visualization of high dynamic range
       pictures", Photorealistic Rendering Techniques (EGWR), Springer, 1994, pp. 7-20.
    """
    exposure, gamma = _check_exposure_gamma(exposure, gamma)
    black = _check_level("black", black)
    white = _check_level("white", white)
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Log saturation must lie in [0, 4]; got {saturation}.")
    shape = np.shape(radiance)
    rgb = _sanitize(radiance)
    lum = luminance(rgb)
    if white is None:
        white = _estimate_white(lum)
    if black is None:
        black = _estimate_black(lum)
    if white <= 0.0:
        warnings.warn(
            "The radiance has no positive samples; the tone-mapped image is black.",
            RuntimeWarning,
            stacklevel=2,
        )
        return np.zeros(shape, dtype=np.float32)
    black = max(black, white / MAX_LOG_RANGE)
    gain = 2.0**exposure
    lum64 = lum.astype(np.float64)
    mapped = np.log1p(gain * lum64 / black) / math.log1p(white / black)
    mapped = np.minimum(mapped, 1.0).astype(np.float32)
    if rgb.shape[2] == 1:
        display = mapped[:, :, None]
    else:
        positive = lum64 > 0
        inverse = np.divide(1.0, lum64, out=np.zeros_like(lum64), where=positive)
        ratios = rgb * inverse[:, :, None].astype(np.float32)
        if float(saturation) != 1.0:
            ratios = np.power(ratios, np.float32(saturation), dtype=np.float32)
            ratios[~positive] = 0.0
        display = _fit_to_gamut(ratios * mapped[:, :, None])
    return _encode(display, gamma, shape)


def tonemap_reinhard(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    intensity: float = 0.0,
    light_adapt: float = 0.0,
    color_adapt: float = 0.0,
) -> np.ndarray:
    """Reinhard and Devlin's photoreceptor tone mapping (OpenCV's ``TonemapReinhard``).

    Each channel is compressed as ``c / (c + (e^{-f} a)^m)`` where the adaptation level
    ``a`` blends the pixel's own and the image's mean luminance and colour, and the
    contrast ``m`` follows from the image's log-luminance key [1]_. The radiance is first
    divided by the white level and clipped there (so the result does not depend on its
    units), then OpenCV maps it and stretches the result to [0, 1].

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units. Mono input is mapped
        as grey RGB.
    exposure : float, optional
        Display-side exposure in stops: the operator's display-linear output is
        multiplied by ``2**exposure`` and clipped to 1 before the gamma is applied.
    gamma : float, optional
        Display gamma applied to the result.
    white : float, optional
        Luminance level (radiance units) taken as white; brighter pixels are clipped.
        Estimated by :func:`robust_levels` when not given.
    intensity : float, optional
        Overall intensity ``f``, in [-8, 8] (OpenCV's ``intensity``).
    light_adapt : float, optional
        Light adaptation in [0, 1]: 0 (default, as in OpenCV's HDR tutorial) adapts to
        the image's mean luminance, 1 (OpenCV's default) to each pixel's own, which
        flattens dark-keyed scenes to a uniform grey.
    color_adapt : float, optional
        Chromatic adaptation in [0, 1]: 1 adapts each channel separately, 0 does not.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] E. Reinhard and K. Devlin, "Dynamic range reduction inspired by photoreceptor
       physiology", IEEE Transactions on Visualization and Computer Graphics 11(1),
       2005, pp. 13-24.
    """
    if not -8.0 <= float(intensity) <= 8.0:
        raise ValueError(f"Reinhard intensity must lie in [-8, 8]; got {intensity}.")
    for name, value in (("light_adapt", light_adapt), ("color_adapt", color_adapt)):
        if not 0.0 <= float(value) <= 1.0:
            raise ValueError(f"Reinhard {name} must lie in [0, 1]; got {value}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapReinhard(
            1.0, float(intensity), float(light_adapt), float(color_adapt)
        )

    return _opencv_tonemap(radiance, make, exposure=exposure, gamma=gamma, white=white)


def tonemap_drago(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    saturation: float = 1.0,
    bias: float = 0.85,
) -> np.ndarray:
    """Drago et al.'s adaptive logarithmic mapping (OpenCV's ``TonemapDrago``).

    Luminance is mapped by a logarithm whose base varies from 2 in the darks to 10 in
    the highlights, interpolated by a bias power function [1]_. The radiance is first
    divided by the white level and clipped there, then OpenCV maps it and stretches
    the result to [0, 1].

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units. Mono input is mapped
        as grey RGB.
    exposure : float, optional
        Display-side exposure in stops (see :func:`tonemap_reinhard`).
    gamma : float, optional
        Display gamma applied to the result.
    white : float, optional
        Luminance level (radiance units) taken as white; estimated by
        :func:`robust_levels` when not given.
    saturation : float, optional
        Colour saturation exponent: 1 keeps the colour ratios, 0 gives grey.
    bias : float, optional
        Bias of the base interpolation, in (0, 1); 0.7 to 0.9 give the best results [1]_.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] F. Drago, K. Myszkowski, T. Annen and N. Chiba, "Adaptive logarithmic mapping
       for displaying high contrast scenes", Computer Graphics Forum 22(3)
       (Eurographics), 2003, pp. 419-426.
    """
    if not 0.0 < float(bias) < 1.0:
        raise ValueError(f"Drago bias must lie strictly between 0 and 1; got {bias}.")
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Drago saturation must lie in [0, 4]; got {saturation}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapDrago(1.0, float(saturation), float(bias))

    return _opencv_tonemap(radiance, make, exposure=exposure, gamma=gamma, white=white)


def tonemap_mantiuk(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    scale: float = 0.7,
    saturation: float = 1.0,
    white_percentile: float = MANTIUK_WHITE_PERCENTILE,
) -> np.ndarray:
    """Mantiuk et al.'s contrast-domain tone mapping (OpenCV's ``TonemapMantiuk``).

    Log-luminance gradients on a Gaussian pyramid are converted to contrast, scaled by
    ``scale`` and the image is rebuilt by solving the resulting optimisation with
    conjugate gradients [1]_. This is a local operator: it keeps the order of
    luminances within smooth regions but not necessarily across the image. The radiance
    is first divided by the white level and clipped there. The result keeps far more
    range than a display shows (``scale`` times the input's, in log units), so rather
    than stretching its extremes to [0, 1] as OpenCV does, the ``white_percentile``-th
    percentile of its luminance is taken as white and brighter pixels clip. Images
    smaller than 2x2 are edge-padded for OpenCV and cropped back.

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units. Mono input is mapped
        as grey RGB.
    exposure : float, optional
        Display-side exposure in stops (see :func:`tonemap_reinhard`).
    gamma : float, optional
        Display gamma applied to the result.
    white : float, optional
        Luminance level (radiance units) taken as white; estimated by
        :func:`robust_levels` when not given.
    scale : float, optional
        Contrast scale factor, in (0, 1]; 0.6 to 0.9 are typical.
    saturation : float, optional
        Colour saturation exponent: 1 keeps the colour ratios, 0 gives grey.
    white_percentile : float, optional
        Percentile (in (50, 100]) of the output luminance shown as white; 100 keeps
        OpenCV's own stretch.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] R. Mantiuk, K. Myszkowski and H.-P. Seidel, "A perceptual framework for
       contrast processing of high dynamic range images", ACM Transactions on Applied
       Perception 3(3), 2006, pp. 286-308.
    """
    if not 0.0 < float(scale) <= 1.0:
        raise ValueError(f"Mantiuk scale must lie in (0, 1]; got {scale}.")
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Mantiuk saturation must lie in [0, 4]; got {saturation}.")
    if not 50.0 < float(white_percentile) <= 100.0:
        raise ValueError(f"Mantiuk white_percentile must lie in (50, 100]; got {white_percentile}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapMantiuk(1.0, float(scale), float(saturation))

    return _opencv_tonemap(
        radiance,
        make,
        exposure=exposure,
        gamma=gamma,
        white=white,
        min_size=2,
        output_percentile=float(white_percentile),
    )


@contextlib.contextmanager
def _quiet_opencv() -> Iterator[None]:
    """Silence OpenCV's C++ warnings (Mantiuk's MatExpr notice) for the duration."""
    import cv2

    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is None:
        yield
        return
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        logging.setLogLevel(level)


def _opencv_tonemap(
    radiance: np.ndarray,
    make: Callable[[], Any],
    *,
    exposure: float,
    gamma: float,
    white: float | None,
    min_size: int = 1,
    output_percentile: float = 100.0,
) -> np.ndarray:
    """Run an OpenCV tone mapper on robustly normalised, sanitised RGB.

    OpenCV's operators take float32 3-channel images and, despite documenting BGR,
    compute luminance with ``COLOR_RGB2GRAY`` (channel 0 weighted as red), so RGB is
    passed in its own order. They stretch their input linearly so that its darkest
    sample is 0 (made a pure scaling here, see :func:`_pad_for_opencv`) and their output
    to [0, 1] (redone here, see :func:`_stretch`). Their gamma is set to 1 and applied
    here, after the display-side exposure.
    """
    exposure, gamma = _check_exposure_gamma(exposure, gamma)
    white = _check_level("white", white)
    shape = np.shape(radiance)
    rgb = _sanitize(radiance)
    channels = rgb.shape[2]
    lum = luminance(rgb)
    if white is None:
        white = _estimate_white(lum)
    if white <= 0.0:
        warnings.warn(
            "The radiance has no positive samples; the tone-mapped image is black.",
            RuntimeWarning,
            stacklevel=3,
        )
        return np.zeros(shape, dtype=np.float32)
    if channels == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    scaled = np.ascontiguousarray(_fit_to_gamut(rgb * np.float32(1.0 / white)))
    h, w = scaled.shape[:2]
    import cv2

    gray = cv2.cvtColor(scaled, cv2.COLOR_RGB2GRAY)  # what OpenCV's operators look at
    log_gray = np.log(np.maximum(gray, _OPENCV_LOG_FLOOR))
    # Without luminance contrast that OpenCV can see (its logs floor at 1e-4) Reinhard
    # returns NaN and Mantiuk fails an assertion: show the scaled radiance then.
    display = scaled
    if float(np.ptp(log_gray)) >= 1e-6:
        padded = np.ascontiguousarray(_pad_for_opencv(scaled, min_size), dtype=np.float32)
        try:
            with _quiet_opencv():
                mapped = np.asarray(make().process(padded), dtype=np.float32)
        except cv2.error as exc:
            warnings.warn(
                f"OpenCV's tone mapper failed on this image ({str(exc).strip()[:120]}); "
                "showing the linearly scaled radiance instead.",
                RuntimeWarning,
                stacklevel=3,
            )
        else:
            display = _stretch(mapped[:h, :w])
            if output_percentile < 100.0:
                level = float(np.percentile(luminance(display), output_percentile))
                if level > 0.0:
                    display = display * np.float32(1.0 / level)
    if channels == 1:
        display = display.mean(axis=2, keepdims=True, dtype=np.float32)
    display = display * np.float32(2.0**exposure)
    return _encode(display, gamma, shape)


_OPERATOR_FUNCTIONS: dict[str, Callable[..., np.ndarray]] = {
    "log": tonemap_log,
    "reinhard": tonemap_reinhard,
    "drago": tonemap_drago,
    "mantiuk": tonemap_mantiuk,
}


def tonemap(
    radiance: np.ndarray,
    operator: str = "log",
    exposure: float = 0.0,
    gamma: float | None = None,
    **params: Any,
) -> np.ndarray:
    """Tone-map linear radiance with one of :data:`OPERATORS`.

    Parameters
    ----------
    radiance : ndarray of shape (H, W, C) or (H, W)
        Linear radiance, ``C`` = 1 (Y) or 3 (R, G, B), any units.
    operator : str, optional
        ``"log"`` (default), ``"reinhard"``, ``"drago"`` or ``"mantiuk"``.
    exposure : float, optional
        Exposure compensation in stops (positive is brighter). Scene-side for ``log``,
        display-side for the OpenCV operators, which renormalise their input.
    gamma : float, optional
        Display gamma; ``None`` takes the operator's default from
        :data:`DEFAULT_GAMMA` (1 for ``log``, 2.2 for the others).
    **params
        Further keyword arguments of the operator's function (``white``, ``black``,
        ``bias``, ``scale``, ...).

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1], gamma applied.

    References
    ----------
    See :func:`tonemap_log`, :func:`tonemap_reinhard`, :func:`tonemap_drago` and
    :func:`tonemap_mantiuk`.
    """
    function = _OPERATOR_FUNCTIONS.get(operator)
    if function is None:
        raise ValueError(
            f"Unknown tone-mapping operator {operator!r}; choose one of {', '.join(OPERATORS)}."
        )
    unknown = sorted(set(params) - set(inspect.signature(function).parameters) - {"radiance"})
    if unknown:
        raise ValueError(
            f"The {operator} operator does not take the parameter(s) {', '.join(unknown)}."
        )
    if gamma is None:
        gamma = DEFAULT_GAMMA[operator]
    return function(radiance, exposure=exposure, gamma=gamma, **params)
