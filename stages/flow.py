"""Motion initialisation from the measuring images, and a colour-wheel picture of motion.

The measuring images of a capture are sums of the measurement sensor's subframes in a few
time bins (:func:`stages.simulate.measure_bin_edges`). Dark regions are noisy in a single
subframe, so flow is computed between *bins*, each normalised to a rate by its own
duration, compressed by a logarithm above its noise floor (so that the huge dynamic range
of a VET scene fits the 8 bits OpenCV's flow wants and dark regions keep their texture),
and lightly smoothed. The motion model is a per-pixel constant velocity ``u(x)`` px/s
(``D(x, t) = u(x) t``, :mod:`stages.motion`'s convention): each flow between two bins is
divided by the time between the bins' centres, several bin pairs are combined by a
per-pixel median, and the result is smoothed with weights from each pixel's
signal-to-noise ratio (normalised convolution), which fills flat and noisy areas from
their textured, well-lit neighbours.

References
----------
G. Farnebäck, "Two-frame motion estimation based on polynomial expansion", SCIA 2003.
T. Kroeger, R. Timofte, D. Dai, L. Van Gool, "Fast optical flow using dense inverse
search", ECCV 2016.
S. Baker, D. Scharstein, J. P. Lewis, S. Roth, M. J. Black, R. Szeliski, "A database and
evaluation methodology for optical flow", IJCV 92, 2011 (the colour wheel).
"""

from __future__ import annotations

import numpy as np

from .formats.capture import MOTION_BINS, Capture
from .formats.layered import Layered, write_layered
from .physics import bin_may_clip, channel_mean

FLOW_METHODS = ("farneback", "dis")


def motion_bins(cap: Capture) -> Capture:
    """The capture as the motion estimators read it: a capture that keeps its whole
    measuring stream is summed into :data:`~stages.formats.capture.MOTION_BINS` time
    bins (a single subframe is too noisy in the dark to match alone); one with time bins
    as it is."""
    return cap.time_bins(MOTION_BINS) if cap.keeps_stream else cap


def measure_rates(cap: Capture) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Measuring bins as rates at the VET sensor, with noise and validity.

    Returns
    -------
    rate : ndarray of shape (B, H, W, C), float32
        Electrons per second (dark current removed), on the VET sensor's scale.
    sigma : ndarray of shape (B, H, W, C), float32
        Standard deviation of ``rate`` (shot, read and quantisation noise).
    valid : ndarray of shape (B, H, W), bool
        False where some subframe of the bin clipped.
    """
    if cap.measure is None or cap.measure_times is None:
        from .errors import InputError

        raise InputError("capture has no measuring images; motion cannot be estimated from it")
    cap = motion_bins(cap)
    rig = cap.rig
    g = rig.gain_dn_per_e
    dur = np.diff(cap.measure_times, axis=1)[:, 0]
    n_sub = np.maximum(np.rint(dur / rig.subframe_s), 1)
    shape = (1, 1, 1)  # (per bin: float64 arrays, so the variance is float64 as a whole)
    dark = rig.dark_current_e_s * dur
    read_var = n_sub * (rig.read_noise_e**2 + 1.0 / (12 * g * g))
    scale = dur * rig.measure_fraction
    rate = np.empty(cap.measure.shape, np.float32)
    sigma = np.empty(cap.measure.shape, np.float32)
    valid = np.empty(cap.measure.shape[:3], bool)
    for b in range(cap.measure.shape[0]):  # one bin at a time: one float64 temporary
        e = cap.measure[b] / np.float32(g) - np.float32(dark[b])
        var = e.astype(np.float64)
        var += dark[b]
        np.maximum(var, 0, out=var)
        var += read_var[b]
        # (float64 quotients rounded to float32, as assigning them would)
        np.divide(e, np.full(shape, scale[b]), out=rate[b], casting="same_kind")
        np.sqrt(var, out=var)
        np.divide(var, np.full(shape, scale[b]), out=sigma[b], casting="same_kind")
        del var
        valid[b] = ~bin_may_clip(cap.measure[b] / np.float32(n_sub[b]), rig)
    return rate, sigma, valid


def _equalise(values: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Map values through a common equalising table (quantiles ``levels``) to 8 bits."""
    v = np.interp(values, levels, np.linspace(0.0, 255.0, len(levels)))
    return np.clip(v, 0, 255).astype(np.uint8)


def _flow_pair(
    a: np.ndarray, b: np.ndarray, method: str, init: np.ndarray | None = None
) -> np.ndarray:
    """Dense flow from ``a`` to ``b`` (H, W, 2) px; ``init`` is a starting flow, which
    both methods refine from their coarsest scale (a displacement far beyond what the
    pyramid finds on its own, such as a predicted long-baseline one, is then found)."""
    import cv2

    start = None if init is None else np.ascontiguousarray(init, np.float32).copy()
    if method == "farneback":
        return cv2.calcOpticalFlowFarneback(
            a,
            b,
            start,
            pyr_scale=0.5,
            levels=5,
            winsize=21,
            iterations=5,
            poly_n=7,
            poly_sigma=1.5,
            flags=0 if start is None else cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
    if method == "dis":
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        return dis.calc(a, b, start)
    raise ValueError(f"unknown flow method {method!r}; choose from {', '.join(FLOW_METHODS)}")


def warp_residual(a: np.ndarray, b: np.ndarray, flow: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """Local mean squared difference between ``a`` and ``b`` sampled along ``flow`` (how
    well the flow explains the pair), pooled over a Gaussian of ``sigma`` px."""
    import cv2

    h, w = a.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    warped = cv2.remap(
        b.astype(np.float32),
        xx + flow[..., 0],
        yy + flow[..., 1],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return cv2.GaussianBlur((warped - a.astype(np.float32)) ** 2, (0, 0), sigma)


def estimate_velocity(
    cap: Capture,
    method: str = "farneback",
    gaps: tuple[int, ...] = (2, 4),
    smooth_px: float = 6.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel constant velocity from optical flow between measuring bins.

    Parameters
    ----------
    cap : Capture
        A VET capture with measuring images (at least two bins).
    method : {'farneback', 'dis'}
        Farnebäck (the published choice) or dense inverse search.
    gaps : tuple of int
        Bin-index gaps of the pairs ``(b, b + gap)`` whose flows are combined; gaps too
        large for the number of bins are skipped.
    smooth_px : float
        Standard deviation (pixels) of the confidence-weighted smoothing of the result.

    Returns
    -------
    velocity : ndarray of shape (H, W, 2), float32
        ``(u, v)`` in px/s.
    confidence : ndarray of shape (H, W), float32
        Per-pixel weight in [0, 1] (signal-to-noise of the bins, and agreement of the
        pairs).
    """
    import cv2

    cap = motion_bins(cap)
    rate, sigma, valid = measure_rates(cap)
    nb = rate.shape[0]
    h, w = rate.shape[1:3]
    if nb < 2:
        from .errors import InputError

        raise InputError("capture has fewer than two measuring bins; motion cannot be estimated")
    lum = channel_mean(rate)
    noise = channel_mean(sigma) / np.sqrt(rate.shape[3])
    # Saturated bins carry a lower bound: take the rate of the VET image's first bin there.
    floor = np.median(noise, axis=0)
    lv = np.log(np.maximum(lum, 0) + floor).astype(np.float32)
    # One equalising table for all bins (so brightness constancy holds between them):
    # every level of the log-rate gets its share of the 8 bits, dark texture included.
    sample = lv[:, ::2, ::2].ravel()
    levels = np.unique(np.quantile(sample, np.linspace(0, 1, 257)))
    if len(levels) < 2:
        levels = np.array([float(sample.min()), float(sample.min()) + 1.0])
    frames = []
    for b in range(nb):
        img = _equalise(cv2.GaussianBlur(lv[b], (0, 0), 1.0), levels)
        frames.append(img)
    centres = cap.measure_times.mean(axis=1)
    pairs = [(b, b + gap) for gap in gaps for b in range(nb - gap)]
    if not pairs:
        pairs = [(b, b + 1) for b in range(nb - 1)]
    vels = np.empty((len(pairs), h, w, 2), np.float32)
    for i, (p, q) in enumerate(pairs):
        f = _flow_pair(frames[p], frames[q], method)
        vels[i] = f / np.float32(centres[q] - centres[p])
    vel = np.median(vels, axis=0)
    spread = np.median(np.abs(vels - vel[None]), axis=0).max(axis=2)
    snr = np.median(np.maximum(lum, 0) / np.maximum(noise, 1e-12), axis=0)
    # Confidence: well above the noise, textured, and the pairs agree.
    gx = cv2.Sobel(lv.mean(axis=0).astype(np.float32), cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(lv.mean(axis=0).astype(np.float32), cv2.CV_32F, 0, 1)
    texture = np.hypot(gx, gy)
    conf = (snr / (snr + 5.0)) * (texture / (texture + 0.05)) / (1.0 + spread / 2.0)
    conf *= valid.all(axis=0)
    conf = conf.astype(np.float32)
    if smooth_px > 0:
        # Where no confident pixel is near, fall back to the global median velocity.
        glob = (
            np.median(vel[conf > np.percentile(conf, 50)], axis=0)
            if conf.max() > 0
            else np.zeros(2)
        )
        vel = smooth_by_confidence(vel, conf, smooth_px, fallback=glob)
    return vel.astype(np.float32), np.clip(conf, 0, 1)


def smooth_by_confidence(
    velocity: np.ndarray,
    confidence: np.ndarray,
    sigma_px: float,
    fallback: np.ndarray | tuple[float, float] = (0.0, 0.0),
    min_weight: float = 1e-3,
) -> np.ndarray:
    """Confidence-weighted Gaussian smoothing of a velocity field (H, W, 2).

    Each pixel takes the mean of its neighbours' velocities (Gaussian of ``sigma_px``)
    weighted by their ``confidence`` (H, W); where the summed weight is below
    ``min_weight`` (no confident pixel near), it takes ``fallback``.
    """
    import cv2

    conf = confidence.astype(np.float32)
    num = np.stack(
        [cv2.GaussianBlur(velocity[..., k] * conf, (0, 0), sigma_px) for k in range(2)], -1
    )
    den = cv2.GaussianBlur(conf, (0, 0), sigma_px)[..., None]
    fill = np.asarray(fallback, np.float32)[None, None, :]
    return np.where(den > min_weight, num / np.maximum(den, 1e-12), fill).astype(np.float32)


def write_motion(path: str, velocity: np.ndarray, meta: dict | None = None) -> None:
    """Write a velocity field as a layered file (layer ``motion``, channels u, v; px/s)."""
    data = Layered()
    data.add("motion", velocity.astype(np.float32), ["u", "v"])
    m = dict(meta or {})
    m.update(kind="motion", units="px/s", model="constant velocity, D(x, t) = u(x) t")
    data.meta = m
    write_layered(path, data)


def flow_to_color(velocity: np.ndarray, max_speed: float | None = None) -> np.ndarray:
    """Colour-wheel picture of a velocity field (hue: direction, saturation: speed).

    Parameters
    ----------
    velocity : ndarray of shape (H, W, 2)
        ``u`` (right) and ``v`` (down), px/s.
    max_speed : float, optional
        Speed shown fully saturated; default :func:`picture_speed_scale` of the field.

    Returns
    -------
    ndarray of shape (H, W, 3), uint8 RGB. White is still; the hue is the direction of
    motion in image coordinates: right red, down yellow-green, left cyan, up violet
    (:func:`flow_key` draws the wheel).
    """
    import cv2

    u = velocity[..., 0].astype(np.float32)
    v = velocity[..., 1].astype(np.float32)
    mag = np.hypot(u, v)
    if max_speed is None:
        max_speed = picture_speed_scale(velocity)
    max_speed = max(max_speed, 1e-6)
    ang = (np.degrees(np.arctan2(v, u)) % 360.0) / 2.0  # OpenCV hue is 0..180
    sat = np.clip(mag / max_speed, 0, 1) * 255
    hsv = np.stack([ang, sat, np.full_like(ang, 255)], axis=-1).astype(np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


#: Speeds shown fully saturated are never below this (px/s), so flow noise in a nearly
#: still field stays pale instead of filling the picture with colour.
MIN_PICTURE_SPEED = 1.0


def picture_speed_scale(*fields: np.ndarray) -> float:
    """Speed to show fully saturated: the 99th percentile of the moving pixels' speeds.

    Pixels with zero speed (a still background) do not count, so a small moving object is
    shown in full colour; the result is at least :data:`MIN_PICTURE_SPEED`.
    """
    speeds = [np.hypot(f[..., 0], f[..., 1]).ravel() for f in fields]
    s = np.concatenate(speeds) if speeds else np.zeros(0)
    s = s[np.isfinite(s) & (s > 0)]
    return max(float(np.percentile(s, 99)) if s.size else 0.0, MIN_PICTURE_SPEED)


def flow_key(max_speed: float, size: int = 112) -> np.ndarray:
    """The colour wheel of :func:`flow_to_color` under its speed scale, (H, size, 3) uint8.

    A disc whose rim is ``max_speed`` in every direction (centre: still), captioned with
    that speed (the speed shown fully saturated).
    """
    import cv2

    from .formats.images import captioned

    r = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    vel = np.stack([xx - r, yy - r], axis=-1) * np.float32(max_speed / r)
    wheel = flow_to_color(vel, max_speed)
    wheel[np.hypot(xx - r, yy - r) > r] = 255
    cv2.circle(wheel, (size // 2, size // 2), int(r), (0, 0, 0), 1, cv2.LINE_AA)
    return captioned(wheel, f"{max_speed:.3g} px/s")


def motion_picture(
    panels: list[tuple[str, np.ndarray]], max_speed: float | None = None
) -> np.ndarray:
    """Velocity fields side by side on one colour-wheel scale, captioned, with the key.

    Parameters
    ----------
    panels : list of (caption, velocity (H, W, 2))
        Fields of one size, e.g. ``[("estimated", est), ("true", truth)]``.
    max_speed : float, optional
        Speed shown fully saturated; default :func:`picture_speed_scale` of all panels.

    Returns
    -------
    ndarray (H', W', 3) uint8 RGB: a caption bar over each panel, the key on the right.
    """
    from .formats.images import captioned

    if max_speed is None:
        max_speed = picture_speed_scale(*(v for _, v in panels))
    tiles = []
    for caption, vel in panels:
        pic = flow_to_color(vel, max_speed)
        pic[[0, -1], :] = pic[:, [0, -1]] = 160  # a grey frame: white is still
        tile = captioned(pic, caption)
        tiles += [tile, np.full((tile.shape[0], 8, 3), 255, np.uint8)]
    key = flow_key(max_speed)
    height = max(tiles[0].shape[0], key.shape[0])
    padded = [
        np.pad(t, ((0, height - t.shape[0]), (0, 0), (0, 0)), constant_values=255)
        for t in tiles + [key]
    ]
    return np.concatenate(padded, axis=1)


def moving_mask(cap: Capture, smooth_px: float = 4.0, threshold: float = 1.5) -> np.ndarray:
    """Pixels whose measuring bins are *not* consistent with a still scene.

    For a still pixel every bin measures the same rate, so the chi-square of the bins'
    rates about their inverse-variance-weighted mean has mean ``B - 1``; motion across
    texture raises it. The per-pixel statistic is smoothed over ``smooth_px`` (Gaussian)
    and compared with ``threshold (B - 1)``; the mask is dilated by a few pixels.

    Returns
    -------
    ndarray of shape (H, W), bool
    """
    import cv2

    rate, sigma, valid = measure_rates(cap)
    nb = rate.shape[0]
    if nb < 2:
        return np.zeros(cap.shape, bool)
    wgt = valid[..., None] / np.maximum(sigma, 1e-12) ** 2
    mean = (wgt * rate).sum(axis=0) / np.maximum(wgt.sum(axis=0), 1e-30)
    chi2 = (wgt * (rate - mean[None]) ** 2).sum(axis=0).mean(axis=2)
    dof = np.maximum(valid.sum(axis=0) - 1, 1)
    stat = cv2.GaussianBlur((chi2 / dof).astype(np.float32), (0, 0), smooth_px)
    moving = (stat > threshold).astype(np.uint8)
    moving = cv2.dilate(moving, np.ones((5, 5), np.uint8))
    return moving.astype(bool)
