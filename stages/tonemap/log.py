"""Global logarithmic tone mapping (the default operator of :mod:`stages.tonemap`)."""

from __future__ import annotations

import math

import numpy as np

from .encoding import check_exposure_gamma, encode, fit_to_gamut
from .radiance import (
    check_level,
    estimate_black,
    estimate_white,
    luminance,
    sanitize,
    warn_if_unlit,
)

#: Default colour saturation exponent of the log mapping: keeps the scene's colour ratios
#: in the light a gamma-2.2 display emits (see :func:`tonemap_log`).
LOG_SATURATION = 1.0 / 2.2
#: Largest white/black ratio the log mapping spans (120 dB); a darker black level is
#: raised to ``white / MAX_LOG_RANGE`` so that a few near-zero samples cannot flatten the
#: whole picture.
MAX_LOG_RANGE = 1e6


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
    exposure, gamma = check_exposure_gamma(exposure, gamma)
    black = check_level("black", black)
    white = check_level("white", white)
    if not 0.0 <= float(saturation) <= 4.0:
        raise ValueError(f"Log saturation must lie in [0, 4]; got {saturation}.")
    shape = np.shape(radiance)
    rgb = sanitize(radiance)
    lum = luminance(rgb)
    if white is None:
        white = estimate_white(lum)
    if black is None:
        black = estimate_black(lum)
    if warn_if_unlit(white, stacklevel=2):
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
        display = fit_to_gamut(ratios * mapped[:, :, None])
    return encode(display, gamma, shape)
