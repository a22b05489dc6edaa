"""The measuring bins of a capture as log luminance rates at a working scale."""

from __future__ import annotations

import numpy as np

from ...cluster import in_order
from ...formats.capture import Capture
from ...physics import channel_mean
from .alignment import median0


def rate_frames(cap: Capture) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Luminance rate of each measuring bin (B, H, W), its noise, and validity (a stream
    as :func:`stages.flow.motion_bins` bins it). One bin at a time: the per-channel rates
    and noise (:func:`stages.flow.measure_rates`) of a single bin are the only
    full-resolution colour arrays made."""
    # A stream's bins are summed each as it is read (no stack of them is made).
    nb = _motion_bin_count(cap)
    if nb < cap.measure_shape[0]:
        one = lambda b: _bin_rate(cap.time_bin(nb, b), 0)  # noqa: E731
    else:
        one = lambda b: _bin_rate(cap, b)  # noqa: E731
    h, w = cap.measure_shape[1:3]
    lum = np.empty((nb, h, w), np.float32)
    noise = np.empty((nb, h, w), np.float32)
    valid = np.empty((nb, h, w), bool)
    for b, parts in enumerate(in_order(one, nb)):
        lum[b], noise[b], valid[b] = (a[0] for a in parts)
    return lum, noise, valid


def rate_frame_centres(cap: Capture) -> np.ndarray:
    """Centre times (B,) s of the bins :func:`rate_frames` reads."""
    return cap.bin_times(_motion_bin_count(cap)).mean(axis=1)


def _motion_bin_count(cap: Capture) -> int:
    """How many bins :func:`stages.flow.motion_bins` makes of ``cap``: a stream's
    :data:`~stages.formats.capture.MOTION_BINS` (or fewer subframes), else its images."""
    from ...formats.capture import MOTION_BINS

    n = cap.measure_shape[0]
    return min(n, MOTION_BINS) if cap.keeps_stream else n


#: Rows of a bin whose colour rates are made at once (:func:`_bin_rate`).
RATE_ROWS = 128


def _bin_rate(cap: Capture, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`rate_frames` of bin ``b`` of ``cap`` (time bins) alone, each (1, H, W),
    made :data:`RATE_ROWS` rows at a time (the colour rates and noise of a strip are the
    only colour arrays made: every value is a pixel's own)."""
    from dataclasses import replace

    from ...flow import measure_rates

    meta = {**cap.meta, "measure_subframes": [int(cap.measure_counts()[b])]}
    h, w, n_ch = cap.measure.shape[1:]
    lum = np.empty((1, h, w), np.float32)
    noise = np.empty((1, h, w), np.float32)
    valid = np.empty((1, h, w), bool)
    for r0 in range(0, h, RATE_ROWS):
        r1 = min(h, r0 + RATE_ROWS)
        strip = replace(
            cap,
            measure=cap.measure[b : b + 1, r0:r1],
            measure_times=cap.measure_times[b : b + 1],
            meta=meta,
        )
        rate, sigma, valid[:, r0:r1] = measure_rates(strip)
        channel_mean(rate, out=lum[:, r0:r1])
        channel_mean(sigma, out=noise[:, r0:r1])
        if n_ch > 1:  # (x / 1 is x)
            noise[:, r0:r1] /= np.float32(np.sqrt(n_ch))
    return lum, noise, valid


def log_frames(lum: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log rates and their noise in log units (first order)."""
    floor = median0(noise)
    pos = np.maximum(lum, 0) + floor
    lv = np.log(pos).astype(np.float32)
    # Floored so that very bright pixels do not get infinite weight (flow and
    # interpolation errors dominate there).
    slv = np.maximum(noise / pos, 0.02).astype(np.float32)
    return lv, slv


def _downsampled(lum: np.ndarray, noise: np.ndarray, valid: np.ndarray, max_px: int):
    """Rates (B, H, W), their noise and validity area-averaged to at most ``max_px`` on
    the longer side; with the scale ``(sx, sy)`` of the working grid."""
    import cv2

    nb, h, w = lum.shape
    scale = min(1.0, max_px / max(h, w))
    if scale >= 1.0:
        return lum, noise, valid, (1.0, 1.0)
    size = (max(8, int(round(w * scale))), max(8, int(round(h * scale))))
    lum = np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in lum])
    noise = np.stack([cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in noise]) * (
        np.float32(scale)
    )
    valid = np.stack(
        [
            cv2.resize(v.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
            for v in valid
        ]
    )
    return lum, noise, valid, (size[0] / w, size[1] / h)


def work_frames(lum: np.ndarray, noise: np.ndarray, valid: np.ndarray, max_px: int):
    """Log-rate bins, their noise in log units and validity, at a working scale."""
    lum, noise, valid, scale_xy = _downsampled(lum, noise, valid, max_px)
    lv, slv = log_frames(lum, noise)
    return lv, slv, valid, scale_xy


def binned_work_frames(cap: Capture, n_bins: int, max_px: int):
    """:func:`work_frames` of ``cap``'s stream summed into ``n_bins`` time bins, with the
    bins' centre times (s). One bin at a time (:meth:`~stages.formats.capture.Capture.time_bin`):
    each bin's sum, rates, noise and validity are made at full resolution and kept at the
    working scale only."""
    nb = min(n_bins, cap.measure_shape[0])

    def work(k: int):
        one = cap.time_bin(nb, k)
        return _downsampled(*_bin_rate(one, 0), max_px), float(one.measure_times[0].mean())

    parts, centres = [], []
    for part, centre in in_order(work, nb):
        parts.append(part)
        centres.append(centre)
    lum, noise, valid = (np.concatenate([p[i] for p in parts]) for i in range(3))
    lv, slv = log_frames(lum, noise)
    return lv, slv, valid, parts[0][3], np.asarray(centres, np.float64)


def equalise_all(lv: np.ndarray) -> list[np.ndarray]:
    import cv2

    from ...flow import _equalise

    sample = lv[:, ::2, ::2].ravel()
    levels = np.unique(np.quantile(sample, np.linspace(0, 1, 257)))
    if len(levels) < 2:
        levels = np.array([float(sample.min()), float(sample.min()) + 1.0])
    return [_equalise(cv2.GaussianBlur(f, (0, 0), 1.0), levels) for f in lv]
