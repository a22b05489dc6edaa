"""Running OpenCV's tone mappers on robustly normalised radiance.

OpenCV's ``Tonemap*`` classes take float32 3-channel images and stretch both their input
and their output with min-max normalisations; :func:`opencv_tonemap` wraps them so that
the result depends on the scene's luminance ratios only, is safe for tiny, flat and
invalid images, and is display-encoded like the other operators of :mod:`stages.tonemap`.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from .encoding import check_exposure_gamma, encode, fit_to_gamut
from .radiance import check_level, estimate_white, luminance, sanitize, warn_if_unlit

#: OpenCV's tone mappers take logs of luminance floored at this value (relative to white).
OPENCV_LOG_FLOOR = 1e-4


def pad_for_opencv(rgb: np.ndarray, min_size: int) -> np.ndarray:
    """Pad (H, W, 3) for OpenCV's tone mappers; the caller crops back to (H, W).

    Images smaller than ``min_size`` are edge-padded up to it. OpenCV begins by mapping
    ``x -> (x - min) / (max - min)``, which would shift the whole image by its darkest
    sample and send that sample to zero luminance (and to NaN, see :func:`stretch`);
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


def stretch(display: np.ndarray) -> np.ndarray:
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


@contextlib.contextmanager
def quiet_opencv() -> Iterator[None]:
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


def opencv_tonemap(
    radiance: np.ndarray,
    make: Callable[[], Any],
    *,
    exposure: float,
    gamma: float,
    white: float | None,
    min_size: int = 1,
    pre: Callable[[np.ndarray], np.ndarray] | None = None,
    post: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Run an OpenCV tone mapper on robustly normalised, sanitised RGB.

    OpenCV's operators take float32 3-channel images and, despite documenting BGR,
    compute luminance with ``COLOR_RGB2GRAY`` (channel 0 weighted as red), so RGB is
    passed in its own order. They stretch their input linearly so that its darkest
    sample is 0 (made a pure scaling here, see :func:`pad_for_opencv`) and their output
    to [0, 1] (redone here, see :func:`stretch`). ``pre``, if given, maps the radiance
    normalised to white (H, W, 3, in [0, 1]) before OpenCV sees it, and ``post`` maps
    OpenCV's stretched, display-linear (H, W, 3) result (an operator's own display
    normalisation).
    Their gamma is set to 1 and applied here, after the display-side exposure.
    """
    exposure, gamma = check_exposure_gamma(exposure, gamma)
    white = check_level("white", white)
    shape = np.shape(radiance)
    rgb = sanitize(radiance)
    channels = rgb.shape[2]
    lum = luminance(rgb)
    if white is None:
        white = estimate_white(lum)
    if warn_if_unlit(white, stacklevel=3):
        return np.zeros(shape, dtype=np.float32)
    if channels == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    scaled = fit_to_gamut(rgb * np.float32(1.0 / white))
    if pre is not None:
        scaled = pre(scaled)
    scaled = np.ascontiguousarray(scaled, dtype=np.float32)
    h, w = scaled.shape[:2]
    import cv2

    gray = cv2.cvtColor(scaled, cv2.COLOR_RGB2GRAY)  # what OpenCV's operators look at
    log_gray = np.log(np.maximum(gray, OPENCV_LOG_FLOOR))
    # Without luminance contrast that OpenCV can see (its logs floor at 1e-4) Reinhard
    # returns NaN and Mantiuk fails an assertion: show the scaled radiance then.
    display = scaled
    if float(np.ptp(log_gray)) >= 1e-6:
        padded = np.ascontiguousarray(pad_for_opencv(scaled, min_size), dtype=np.float32)
        try:
            with quiet_opencv():
                mapped = np.asarray(make().process(padded), dtype=np.float32)
        except cv2.error as exc:
            warnings.warn(
                f"OpenCV's tone mapper failed on this image ({str(exc).strip()[:120]}); "
                "showing the linearly scaled radiance instead.",
                RuntimeWarning,
                stacklevel=3,
            )
        else:
            display = stretch(mapped[:h, :w])
            if post is not None:
                display = post(display)
    if channels == 1:
        display = display.mean(axis=2, keepdims=True, dtype=np.float32)
    display = display * np.float32(2.0**exposure)
    return encode(display, gamma, shape)
