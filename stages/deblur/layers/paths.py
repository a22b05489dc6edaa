"""Layers that move along paths, measured from the full-rate measuring stream.

The layered estimate (:mod:`.estimate`) gives each layer a constant velocity. When the
motion changes within the frame (camera shake, an object swinging back and forth; Uda et
al. 2016, Eq. 8: ``D(x, t)`` any function of time), the paths are measured directly, as
a burst's alignment measures them (Hasinoff et al. 2016, §4: tiles registered to a
reference frame):

1. **Groups.** The stream's subframes are summed in :data:`GROUPS` consecutive groups
   (two or three subframes each: a finely sampled path), log-compressed above the
   read noise.
2. **Tile paths.** Overlapping tiles of :data:`TILE_PX` pixels are registered from the
   first group to every later one by normalised cross-correlation (OpenCV
   ``matchTemplate``, sub-pixel parabolic peak) near where the path so far predicts;
   each confident tile gets a path ``p(t_g)``.
3. **Layer paths.** Tile paths are grouped greedily (the path that most tiles follow
   within :data:`SAME_PATH_PX` RMS, their median, then the next among the rest), at most
   :data:`MAX_PATHS`. Each is fitted with a constant velocity; when none leaves it by
   :data:`MIN_DEVIATION_PX`, the motion is constant velocity and the caller keeps the
   layered estimate (``TilePaths.changing`` says so).
4. **Layers.** Every pixel takes the path along which its groups agree best
   (a box-filtered squared spread of the pulled-back groups), the one most tiles follow
   unless another fits clearly better (:data:`SWITCH_RATIO`); smaller layers are in
   front.

:func:`path_layers` returns :class:`stages.deblur.operator.Layers` with a trajectory
``(times, disp)``: ``D_k(0) = 0``, the group mid-times, and the frame's end (both ends
extrapolated by a parabola through the three nearest groups).

References
----------
S. W. Hasinoff et al., "Burst photography for high dynamic range and low-light imaging
on mobile cameras", ACM Trans. Graphics 35(6), 2016.
"""

from __future__ import annotations

import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ...cluster import in_order, solve_threads
from ...physics import channel_mean
from ...rig import RigParams
from ..operator import Layers

log = logging.getLogger(__name__)

#: Groups of consecutive subframes registered.
GROUPS = 48
#: Tile side and stride of the tile registration, pixels.
TILE_PX = 48
#: Correlation below which a tile's registration is not trusted.
MIN_RESPONSE = 0.3
#: Search radius around a tile's predicted position, pixels.
SEARCH_PX = 12
#: A layer's path must leave its constant-velocity fit by this much (px) for the
#: motion to count as changing.
MIN_DEVIATION_PX = 0.75
#: Tiles whose paths differ by less than this RMS (px) follow one layer.
SAME_PATH_PX = 1.0
#: At most this many layers; a layer needs this share of the confident tiles.
MAX_PATHS = 4
MIN_PATH_SHARE = 0.05
#: A pixel leaves the main layer for another only when that fits this much better.
SWITCH_RATIO = 0.7


class Groups:
    """The stream summed over groups of consecutive subframes, as log DN (H, W) float32
    above a floor of 3 read noises of a group (step 1), made one at a time as asked: all
    of them (G frames) are never held at once.

    ``mids`` (G,) s are the groups' mid-times, ``floor`` the log floor (DN), ``first``
    group 0 (the reference every later group is registered to)."""

    def __init__(self, measure: np.ndarray, times: np.ndarray, rig: RigParams, n_groups: int):
        k_n = measure.shape[0]
        edges = np.linspace(0, k_n, min(n_groups, k_n) + 1).round().astype(int)
        self.spans = [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b > a]
        per = k_n / max(len(self.spans), 1)
        self.floor = float(3.0 * rig.gain_dn_per_e * float(rig.read_noise_e) * np.sqrt(per) + 1.0)
        self.measure, self.times = measure, times
        self.mids = np.asarray(
            [0.5 * (float(times[a][0]) + float(times[b - 1][1])) for a, b in self.spans]
        )
        self.first = self[0]

    def __len__(self) -> int:
        return len(self.spans)

    def __getitem__(self, g: int) -> np.ndarray:
        measure = self.measure
        a, b = self.spans[g]
        n_ch = measure.shape[3]
        acc = np.zeros(measure.shape[1:3], np.float32)
        mean = np.empty_like(acc)
        for k in range(a, b):
            if n_ch == 1:  # (the mean of one channel is itself)
                acc += measure[k, ..., 0]
                continue
            acc += channel_mean(measure[k], np.float32, out=mean)  # (in float32)
        np.maximum(acc, 0.0, out=acc)
        acc += np.float32(self.floor)
        return np.log(acc, out=acc)

    def each(self, start: int = 0):
        """Groups ``start``, ``start + 1``, ... in order, made on the process's threads a
        few at a time."""
        return in_order(lambda g: self[start + g], len(self) - start)


@dataclass
class TilePaths:
    """The registration of the stream's groups (see the module docstring)."""

    mids: np.ndarray  # (G,) s, group mid-times
    groups: Groups  # the log-compressed group sums, made as asked
    paths: np.ndarray  # (N, G, 2) px, each confident tile's displacement from group 0
    layer_paths: list  # the paths most tiles follow, (G, 2) px each, most followed first
    deviation_px: float  # the largest departure of those from a constant velocity
    main_deviation_px: float = 0.0  # that of the path most tiles follow

    @property
    def changing(self) -> bool:
        """Some layer's path leaves a constant velocity."""
        return len(self.layer_paths) > 0 and self.deviation_px >= MIN_DEVIATION_PX

    @property
    def main_changing(self) -> bool:
        """The path most tiles follow leaves a constant velocity (camera shake): a
        cautious test, since a minor cluster of tile paths (tiles straddling a moving
        object's edge) can leave a constant velocity when no layer does."""
        return len(self.layer_paths) > 0 and self.main_deviation_px >= MIN_DEVIATION_PX


def _match(ref: np.ndarray, img: np.ndarray, x0: int, y0: int, guess: np.ndarray, r: int):
    """Where the patch ``ref`` (taken at ``x0, y0`` of the first group) lies in ``img``
    near ``guess``: the sub-pixel peak of the normalised cross-correlation within ``r``
    pixels, as a displacement (px), and the peak's correlation (None if off the image)."""
    import cv2

    ph, pw = ref.shape
    h, w = img.shape
    gx, gy = int(round(guess[0])), int(round(guess[1]))
    xa, ya = x0 + gx - r, y0 + gy - r
    if xa < 0 or ya < 0 or xa + pw + 2 * r > w or ya + ph + 2 * r > h:
        return None, 0.0
    win = np.ascontiguousarray(img[ya : ya + ph + 2 * r, xa : xa + pw + 2 * r])
    cc = cv2.matchTemplate(win, ref, cv2.TM_CCOEFF_NORMED)
    _mn, peak, _lmn, (px, py) = cv2.minMaxLoc(cc)

    def sub(a: float, b: float, c: float) -> float:
        d = a - 2 * b + c
        return 0.0 if d >= 0 else 0.5 * (a - c) / d

    fx = sub(cc[py, px - 1], cc[py, px], cc[py, px + 1]) if 0 < px < cc.shape[1] - 1 else 0.0
    fy = sub(cc[py - 1, px], cc[py, px], cc[py + 1, px]) if 0 < py < cc.shape[0] - 1 else 0.0
    return np.array([gx - r + px + fx, gy - r + py + fy]), float(peak)


def tile_paths(measure: np.ndarray, times: np.ndarray, rig: RigParams) -> TilePaths:
    """Register the stream's groups tile by tile (steps 1-3 of the module docstring).

    Each tile's patch in the first group is found in every later group by normalised
    cross-correlation within :data:`SEARCH_PX` of the position its path so far predicts
    (the last step repeated), so paths of any length are followed. The groups are taken
    in time order, every tile registered on each before the next is made."""
    groups = Groups(measure, times, rig, GROUPS)
    n_g = len(groups)
    h, w = groups.first.shape
    ts = min(TILE_PX, h // 2, w // 2)
    stride = max(ts // 2, 1)
    tiles = []
    for y0 in range(SEARCH_PX, max(h - ts - SEARCH_PX, SEARCH_PX) + 1, stride):
        for x0 in range(SEARCH_PX, max(w - ts - SEARCH_PX, SEARCH_PX) + 1, stride):
            ref = np.ascontiguousarray(groups.first[y0 : y0 + ts, x0 : x0 + ts])
            if float(ref.std()) >= 1e-3:
                tiles.append((x0, y0, ref))
    p = np.zeros((len(tiles), n_g, 2))
    alive = np.ones(len(tiles), bool)

    def follow(g: int, comp: np.ndarray, part: range) -> None:
        for i in part:
            if not alive[i]:
                continue
            x0, y0, ref = tiles[i]
            guess = p[i, g - 1] + (p[i, g - 1] - p[i, g - 2] if g >= 2 else 0.0)
            found, peak = _match(ref, comp, x0, y0, guess, SEARCH_PX)
            if found is None or peak < MIN_RESPONSE:
                alive[i] = False
            else:
                p[i, g] = found

    # Each tile's path is its own: the tiles are shared out over the process's threads
    # (OpenCV's matching releases the GIL), each writing its own tiles' entries.
    threads = max(1, min(solve_threads(), len(tiles)))
    parts = [range(k, len(tiles), threads) for k in range(threads)]
    with ThreadPoolExecutor(threads) as pool:
        for g, comp in enumerate(groups.each(1), start=1):
            list(pool.map(functools.partial(follow, g, comp), parts))
    arr = p[alive].reshape(-1, n_g, 2)
    mids = groups.mids
    found = _cluster(arr) if n_g >= 3 else []
    dev = main_dev = 0.0
    if found:
        lp = np.stack(found)
        t = mids - mids[0]
        # Least-squares constant velocity through the origin, per path and axis.
        v = (lp * t[None, :, None]).sum(axis=1) / max(float((t * t).sum()), 1e-12)
        per_path = np.abs(lp - v[:, None, :] * t[None, :, None]).max(axis=(1, 2))
        dev, main_dev = float(per_path.max()), float(per_path[0])
    return TilePaths(mids, groups, arr, found, dev, main_dev)


def _cluster(paths: np.ndarray) -> list[np.ndarray]:
    """Greedy grouping of tile paths (step 4): the layers' paths, most followed first."""
    from scipy.spatial.distance import cdist

    out: list[np.ndarray] = []
    need = max(2, int(np.ceil(MIN_PATH_SHARE * len(paths))))
    if len(paths) < need:
        return out
    # Two paths are close where their RMS distance over the groups is under SAME_PATH_PX:
    # their squared distance as (G * 2)-vectors under G SAME_PATH_PX^2 (N x N booleans,
    # not the N x N x G x 2 differences).
    flat = paths.reshape(len(paths), -1).astype(np.float64)
    close = cdist(flat, flat, "sqeuclidean") < paths.shape[1] * SAME_PATH_PX**2
    left = np.arange(len(paths))
    while len(left) >= need and len(out) < MAX_PATHS:
        sub = close[np.ix_(left, left)]
        best = int(np.argmax(sub.sum(axis=1)))
        members = sub[best]
        if members.sum() < need:
            break
        out.append(np.median(paths[left[members]], axis=0))
        left = left[~members]
    return out


#: Subframes per short group registered near the frame's start, and how many.
START_GROUP = 2
START_GROUPS = 4


def _start(tp: TilePaths, mask: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A layer's path over its first few short groups of :data:`START_GROUP` subframes,
    each registered to the first group over the whole (eroded) layer by ECC (Evangelidis
    and Psarakis, IEEE TPAMI 30(10), 2008; translation, started from the coarse path):
    ``(times (n,), displacement from the first group (n, 2))``. Falls back to the coarse
    path's first three groups where the layer is too small or a registration fails."""
    import cv2

    fallback = tp.mids[:3], path[:3]
    measure, times, floor = tp.groups.measure, tp.groups.times, tp.groups.floor
    m = cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8))
    b = 2 + int(np.ceil(np.abs(path).max()))
    m[:b], m[-b:], m[:, :b], m[:, -b:] = 0, 0, 0, 0
    if int(m.sum()) < 400 or measure.shape[0] < START_GROUP * START_GROUPS:
        return fallback
    per = measure.shape[0] / len(tp.mids)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 80, 1e-5)
    ts, ds = [], []
    for j in range(START_GROUPS):
        a, e = j * START_GROUP, (j + 1) * START_GROUP
        g = sum(np.asarray(measure[i], np.float32).mean(axis=2) for i in range(a, e))
        g = np.log(np.maximum(g * np.float32(per / START_GROUP), 0) + np.float32(floor))
        t = 0.5 * (float(times[a][0]) + float(times[e - 1][1]))
        guess = np.array([np.interp(t, tp.mids, path[:, 0]), np.interp(t, tp.mids, path[:, 1])])
        warp = np.array([[1, 0, guess[0]], [0, 1, guess[1]]], np.float32)
        try:
            _cc, warp = cv2.findTransformECC(
                tp.groups.first, g.astype(np.float32), warp, cv2.MOTION_TRANSLATION, criteria, m, 5
            )
        except cv2.error:
            return fallback
        d = np.array([warp[0, 2], warp[1, 2]], np.float64)
        if not np.all(np.isfinite(d)) or np.hypot(*(d - guess)) > 3.0:
            return fallback
        ts.append(t)
        ds.append(d)
    return np.asarray(ts), np.asarray(ds)


def _extrapolate(t: np.ndarray, d: np.ndarray, at: float) -> np.ndarray:
    """Value at ``at`` of the parabola (a line for two points) through ``d`` (K, n, 2)
    at times ``t`` (n,), per path and axis: (K, 2)."""
    deg = min(2, len(t) - 1)
    out = np.empty((d.shape[0], 2))
    for k in range(d.shape[0]):
        for a in range(2):
            out[k, a] = np.polyval(np.polyfit(t, d[k, :, a], deg), at)
    return out


def path_layers(tp: TilePaths, frame_s: float) -> Layers | None:
    """Layers along the tiles' paths (step 4), or None when no path is followed."""
    import cv2

    paths = list(tp.layer_paths)
    if not paths:
        return None
    n_g = len(tp.groups)
    h, w = tp.groups.first.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    # Each path's spread of the pulled-back groups (their variance over the groups), from
    # running sums of their departures from the first group: the groups in time order,
    # none held beside the next.
    first = tp.groups.first
    s1 = np.zeros((len(paths), h, w), np.float32)
    s2 = np.zeros_like(s1)
    for g, comp in enumerate(tp.groups.each(1), start=1):
        for k, p in enumerate(paths):
            d = cv2.remap(
                comp,
                xx + np.float32(p[g, 0]),
                yy + np.float32(p[g, 1]),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REFLECT,
            )
            d -= first  # (paths start at 0: group 0 pulled back is itself)
            s1[k] += d
            d *= d
            s2[k] += d
    s1 /= np.float32(n_g)
    s2 /= np.float32(n_g)
    s2 -= s1 * s1
    cost = np.stack([cv2.blur(np.maximum(v, 0.0), (9, 9)) for v in s2])
    del s1, s2
    label = np.zeros((h, w), np.int32)
    for k in range(1, len(paths)):
        better = cost[k] < SWITCH_RATIO * cost[label, yy.astype(int), xx.astype(int)]
        label[better] = k
    label = cv2.medianBlur(label.astype(np.uint8), 5).astype(np.int32)
    counts = np.bincount(label.ravel(), minlength=len(paths))
    keep = [k for k in range(len(paths)) if counts[k] > 0]
    remap = np.full(len(paths), 0, np.int32)
    remap[keep] = np.arange(len(keep))
    label = remap[label]
    paths = [paths[k] for k in keep]
    counts = counts[keep]
    # Paths from t = 0: the first group's own displacement by the first step's velocity,
    # then linear past the last group to the frame's end.
    mids = tp.mids
    disp = np.stack(paths)  # (K, G, 2) from group 0
    # Where each path is at t = 0: a parabola through its first few short groups, each
    # registered over the whole layer (:func:`_start`); at the frame's end, through the
    # last three groups.
    for k in range(len(paths)):
        t_fine, d_fine = _start(tp, label == k, disp[k])
        disp[k] -= _extrapolate(t_fine, d_fine[None], 0.0)[0]
    last = _extrapolate(mids[-3:], disp[:, -3:], frame_s)
    times = np.concatenate([[0.0], mids, [frame_s]])
    d_all = np.concatenate([np.zeros((len(paths), 1, 2)), disp, last[:, None]], axis=1)
    bg = int(np.argmax(counts))
    front = [int(k) for k in np.argsort(counts, kind="stable") if k != bg]
    log.info(
        "deblur: the motion changes within the frame (tile paths leave constant velocity "
        "by %.1f px); %d layer(s) along measured paths",
        tp.deviation_px,
        len(paths),
    )
    return Layers(label, d_all[:, -1] / frame_s, front, bg, trajectory=(times, d_all))
