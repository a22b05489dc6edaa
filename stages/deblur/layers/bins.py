"""The measuring bins of a capture as log luminance rates at a working scale."""

from __future__ import annotations

import numpy as np

from ...formats.capture import Capture


def rate_frames(cap: Capture) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Luminance rate of each measuring bin (B, H, W), its noise, and validity."""
    from ...flow import measure_rates

    rate, sigma, valid = measure_rates(cap)
    lum = rate.mean(axis=3)
    noise = sigma.mean(axis=3) / np.float32(np.sqrt(rate.shape[3]))
    return lum, noise, valid


def log_frames(lum: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log rates and their noise in log units (first order)."""
    floor = np.median(noise, axis=0)
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
    bins' centre times (s). Each bin's rates, noise and validity are made at full
    resolution one bin at a time and kept at the working scale only (the summed bins are
    the one full-resolution array of all of them)."""
    from dataclasses import replace

    binned = cap.time_bins(n_bins)
    counts = binned.measure_counts()
    parts = []
    for b in range(binned.measure.shape[0]):
        one = replace(
            binned,
            measure=binned.measure[b : b + 1],
            measure_times=binned.measure_times[b : b + 1],
            meta={**binned.meta, "measure_subframes": [int(counts[b])]},
        )
        parts.append(_downsampled(*rate_frames(one), max_px))
    lum, noise, valid = (np.concatenate([p[i] for p in parts]) for i in range(3))
    lv, slv = log_frames(lum, noise)
    centres = binned.measure_times.mean(axis=1).astype(np.float64)
    return lv, slv, valid, parts[0][3], centres


def equalise_all(lv: np.ndarray) -> list[np.ndarray]:
    import cv2

    from ...flow import _equalise

    sample = lv[:, ::2, ::2].ravel()
    levels = np.unique(np.quantile(sample, np.linspace(0, 1, 257)))
    if len(levels) < 2:
        levels = np.array([float(sample.min()), float(sample.min()) + 1.0])
    return [_equalise(cv2.GaussianBlur(f, (0, 0), 1.0), levels) for f in lv]
