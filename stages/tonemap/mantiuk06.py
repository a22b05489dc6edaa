"""Mantiuk et al.'s contrast-domain tone mapping (2006), through OpenCV."""

from __future__ import annotations

from typing import Any

import numpy as np

from .encoding import fit_to_gamut
from .opencv import OPENCV_LOG_FLOOR, opencv_tonemap
from .radiance import estimate_black, luminance

#: Percentile of the output log luminance cut at either end before it is mapped onto the
#: display's range (pfstmo_mantiuk06's ``CUT_MARGIN``).
MANTIUK_CUT_PERCENT = 0.1
#: Dynamic range of the display, log10 units: the cut log luminance is mapped linearly
#: onto ``[-MANTIUK_DISPLAY_RANGE, 0]`` (pfstmo_mantiuk06's ``disp_dyn_range``).
MANTIUK_DISPLAY_RANGE = 2.3
#: The input's black level (relative to white) is brought up to at least this before
#: OpenCV takes logs floored at :data:`~stages.tonemap.opencv.OPENCV_LOG_FLOOR`, so
#: that the darks keep their contrasts (:func:`fit_log_range`).
MANTIUK_INPUT_BLACK = 10.0 * OPENCV_LOG_FLOOR


def tonemap_mantiuk(
    radiance: np.ndarray,
    *,
    exposure: float = 0.0,
    gamma: float = 2.2,
    white: float | None = None,
    scale: float = 0.7,
    saturation: float = 1.0,
    display_range: float = MANTIUK_DISPLAY_RANGE,
) -> np.ndarray:
    """Mantiuk et al.'s contrast-domain tone mapping (OpenCV's ``TonemapMantiuk``).

    Log-luminance gradients on a Gaussian pyramid are converted to contrast, scaled by
    ``scale`` and the image is rebuilt by solving the resulting optimisation with
    conjugate gradients [1]_. This is a local operator: it keeps the order of
    luminances within smooth regions but not necessarily across the image. The radiance
    is first divided by the white level and clipped there; OpenCV takes logs of
    luminance floored at :data:`~stages.tonemap.opencv.OPENCV_LOG_FLOOR` of white, which
    would flatten the darks of a scene spanning more, so a wider input has its log
    luminance scaled to fit first (:func:`fit_log_range`). The result keeps far more
    range than a display shows (``scale`` times the input's, in log units) and OpenCV
    only stretches its extremes to [0, 1], which leaves most pixels dark and flat; so,
    as the authors' implementation in pfstools does (``pfstmo_mantiuk06`` [2]_), its log
    luminance between the :data:`MANTIUK_CUT_PERCENT` and ``100 - MANTIUK_CUT_PERCENT``
    percentiles is mapped linearly onto ``display_range`` decades below white (darker and
    brighter pixels clip), colour ratios kept, before the display gamma. Images smaller
    than 2x2 are edge-padded for OpenCV and cropped back.

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
    display_range : float, optional
        Display dynamic range in log10 units, in (0, 6]: the output luminance spans
        ``10**-display_range`` to 1 before the gamma.

    Returns
    -------
    ndarray of the input's shape, float32
        Display-referred values in [0, 1].

    References
    ----------
    .. [1] R. Mantiuk, K. Myszkowski and H.-P. Seidel, "A perceptual framework for
       contrast processing of high dynamic range images", ACM Transactions on Applied
       Perception 3(3), 2006, pp. 286-308.
    .. [2] R. Mantiuk, G. Krawczyk et al., pfstools, ``src/tmo/mantiuk06/tmo_mantiuk06.cpp``
       (the luminance normalisation that ends ``tmo_mantiuk06_contmap``),
       https://pfstools.sourceforge.net/.
    """
    if not 0.0 < float(scale) <= 1.0:
        raise ValueError(f"Mantiuk scale must lie in (0, 1]; got {scale}.")
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Mantiuk saturation must lie in [0, 4]; got {saturation}.")
    if not 0.0 < float(display_range) <= 6.0:
        raise ValueError(f"Mantiuk display_range must lie in (0, 6]; got {display_range}.")

    def make() -> Any:
        import cv2

        return cv2.createTonemapMantiuk(1.0, float(scale), float(saturation))

    return opencv_tonemap(
        radiance,
        make,
        exposure=exposure,
        gamma=gamma,
        white=white,
        min_size=2,
        pre=fit_log_range,
        post=lambda display: fit_log_luminance(display, float(display_range)),
    )


def fit_log_luminance(display: np.ndarray, decades: float) -> np.ndarray:
    """Map the log luminance of display-linear (H, W, 3) onto ``decades`` below white.

    With ``L`` the luminance and ``l_lo``, ``l_hi`` the :data:`MANTIUK_CUT_PERCENT` and
    ``100 - MANTIUK_CUT_PERCENT`` percentiles of ``log10 L`` over the positive pixels,
    each pixel is scaled by ``L_d / L`` with
    ``log10 L_d = decades (clip((log10 L - l_hi) / (l_hi - l_lo), -1, 0))``: ``l_hi``
    becomes white (1), ``l_lo`` ``10**-decades``; colour ratios are kept (a pixel whose
    largest channel would exceed 1 is scaled down whole) and pixels of zero luminance
    stay black. Returns float32 (H, W, 3), display-linear, in [0, 1].
    """
    lum = luminance(display).astype(np.float64)
    positive = lum > 0
    if not positive.any():
        return display
    log_lum = np.log10(lum[positive])
    lo, hi = np.percentile(log_lum, [MANTIUK_CUT_PERCENT, 100.0 - MANTIUK_CUT_PERCENT])
    span = max(float(hi - lo), 1e-6)
    target = np.zeros_like(lum)
    target[positive] = 10.0 ** (decades * np.clip((log_lum - hi) / span, -1.0, 0.0))
    gain = np.divide(target, lum, out=np.zeros_like(lum), where=positive)
    return fit_to_gamut((display * gain[:, :, None]).astype(np.float32))


def fit_log_range(rgb: np.ndarray) -> np.ndarray:
    """Scale the log luminance of (H, W, 3) radiance in [0, 1] so its black level fits.

    With ``b`` the black level of the luminance ``L`` (:func:`stages.tonemap.robust_levels`'
    percentile) and ``m`` = :data:`MANTIUK_INPUT_BLACK`: when ``b < m``, each pixel is
    scaled by ``L' / L`` with ``L' = L ** k``, ``k = log(m) / log(b)``, which maps ``b`` to
    ``m`` and keeps white at 1, colour ratios and the order of luminances; otherwise the
    input is returned as it is. Returns float32 (H, W, 3).
    """
    lum = luminance(rgb).astype(np.float64)
    black = estimate_black(lum)
    if not 0.0 < black < MANTIUK_INPUT_BLACK:
        return rgb
    k = np.log(MANTIUK_INPUT_BLACK) / np.log(black)
    positive = lum > 0
    gain = np.ones_like(lum)
    gain[positive] = lum[positive] ** (k - 1.0)
    return fit_to_gamut((rgb * gain[:, :, None]).astype(np.float32))
