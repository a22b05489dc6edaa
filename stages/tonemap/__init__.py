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

Modules, one per operator named after its source as in pfstools and colour-hdri:

- :mod:`.log`: the global logarithmic mapping;
- :mod:`.reinhard05`: Reinhard and Devlin 2005;
- :mod:`.drago03`: Drago et al. 2003;
- :mod:`.mantiuk06`: Mantiuk et al. 2006;

and the parts they share: :mod:`.radiance` (input checks, sanitising, luminance, robust
levels), :mod:`.encoding` (gamut fitting, clipping, display gamma) and :mod:`.opencv`
(running OpenCV's tone mappers on normalised radiance).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any

import numpy as np

from .drago03 import tonemap_drago
from .log import LOG_SATURATION, MAX_LOG_RANGE, tonemap_log
from .mantiuk06 import tonemap_mantiuk
from .radiance import BLACK_PERCENTILE, REC709_LUMA, luminance, robust_levels
from .reinhard05 import tonemap_reinhard

__all__ = [
    "BLACK_PERCENTILE",
    "DEFAULT_GAMMA",
    "LOG_SATURATION",
    "MAX_LOG_RANGE",
    "OPERATORS",
    "REC709_LUMA",
    "luminance",
    "robust_levels",
    "tonemap",
    "tonemap_drago",
    "tonemap_log",
    "tonemap_mantiuk",
    "tonemap_reinhard",
]

#: Names accepted by :func:`tonemap`, default first.
OPERATORS: tuple[str, ...] = ("log", "reinhard", "drago", "mantiuk")

#: Display gamma each operator uses when :func:`tonemap` is given ``gamma=None``. The
#: log mapping already spaces its output roughly perceptually, so it gets none; the
#: OpenCV operators produce display-linear values and get the usual 2.2.
DEFAULT_GAMMA: dict[str, float] = {"log": 1.0, "reinhard": 2.2, "drago": 2.2, "mantiuk": 2.2}


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
