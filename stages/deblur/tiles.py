"""Deblur in overlapping tiles: memory bounded by the tiles in flight, one frame spread
over workers.

The motion is estimated once for the whole frame (:func:`stages.deblur.start_motion`), so
every tile sees the same motion. The frame is cut into a grid of *cores* (each pixel in
exactly one core); a tile is its core grown by a *halo* that covers every integration path
reaching the core, along each axis: ``ceil(max |u| * frame length) + margin`` columns and
``ceil(max |v| * frame length) + margin`` rows, ``(u, v)`` the motion estimate's velocities
(:func:`halo_yx`; a horizontal pan grows tiles by the margin alone vertically). The grid's
rows and columns follow the halo (:func:`grid_shape`): a pan's cores are longer along it,
so that less of the frame is solved twice, each tile no larger than a ``tile`` x ``tile``
core with its halo. Each tile is deblurred on its own (the default method with the global
motion fixed), and the tiles are blended with weights that are 1 on the core and fall
linearly to 0 across the halo (1 up to the frame's own edges), so neighbouring solutions
cross-fade instead of meeting at a seam.

Tiles run in-process, :data:`TILES_AT_ONCE` at a time on the process's threads where
it has the cores (each solved on one thread, the same image as one after the other), or
as Dask tasks on the engine ``vet batch`` uses (an embedded ``LocalCluster`` on loopback,
or an existing scheduler).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InputError, VetError
from ..formats.capture import Capture

#: Pixels added to the longest integration path to make the halo.
HALO_MARGIN_PX = 16
#: Smallest core side a tile may have.
MIN_TILE_PX = 64
#: Tiles solved side by side in one process (each on one thread), where it has the cores.
TILES_AT_ONCE = 2
#: Tiles the grid is shaped for solving at once (:func:`grid_shape`; whatever runs them).
GRID_AT_ONCE = 2
#: Tiles in flight per Dask worker (one solving, one on its way).
DASK_AHEAD = 2
#: ``tile="auto"``: frames with a side over AUTO_ABOVE_PX are solved in tiles of AUTO_TILE_PX
#: (colour), or of AUTO_TILE_PX_MONO where the capture has one channel: a tile's memory is
#: mostly per channel, and a larger tile repeats less of its halo.
AUTO_TILE_PX = 512
AUTO_TILE_PX_MONO = 640
AUTO_ABOVE_PX = 1024


def resolve_tile(tile: int | str | None, shape: tuple[int, int], channels: int = 3) -> int | None:
    """The tile size (:func:`tile_grid`'s ``tile``) for a frame of ``shape`` (H, W) of
    ``channels`` colour channels: an int as given, ``"auto"`` (:data:`AUTO_TILE_PX`, or
    :data:`AUTO_TILE_PX_MONO` for one channel, on frames with a side over
    :data:`AUTO_ABOVE_PX`, else one solve), ``None`` or ``"none"`` for one solve."""
    if tile is None or tile == "none":
        return None
    if tile == "auto":
        if max(shape) <= AUTO_ABOVE_PX:
            return None
        return AUTO_TILE_PX_MONO if channels == 1 else AUTO_TILE_PX
    if isinstance(tile, bool) or not isinstance(tile, int) or tile < MIN_TILE_PX:
        raise InputError(f"tile must be auto, none or an integer >= {MIN_TILE_PX}, got {tile!r}")
    return tile


@dataclass(frozen=True)
class Tile:
    """A tile: ``core`` and ``outer`` boxes ``(y0, y1, x0, x1)`` in frame pixels."""

    core: tuple[int, int, int, int]
    outer: tuple[int, int, int, int]

    @property
    def pixels(self) -> int:
        """Pixels of the tile, halo included."""
        y0, y1, x0, x1 = self.outer
        return (y1 - y0) * (x1 - x0)

    def slices(self, box: str = "outer") -> tuple[slice, slice]:
        y0, y1, x0, x1 = getattr(self, box)
        return slice(y0, y1), slice(x0, x1)


def halo_px(
    velocity: np.ndarray, frame_s: float, margin: int = HALO_MARGIN_PX, paths: Any = None
) -> int:
    """Pixels of halo that cover every integration path of ``velocity`` (H, W, 2) px/s,
    and of ``paths`` (:class:`~stages.deblur.operator.Layers` with trajectories) if given:
    the farthest any layer gets from its place at t = 0."""
    speed = float(np.hypot(velocity[..., 0], velocity[..., 1]).max()) if velocity.size else 0.0
    reach = speed * frame_s
    disp = _displacements(paths)
    if disp.size:
        reach = max(reach, float(np.hypot(disp[..., 0], disp[..., 1]).max()))
    return int(math.ceil(reach)) + margin


def _displacements(paths: Any) -> np.ndarray:
    """The displacements (..., 2) px of ``paths``' trajectories; empty without them."""
    if paths is None or paths.trajectory is None:
        return np.zeros((0, 2))
    return np.asarray(paths.trajectory[1], np.float64)


def halo_yx(
    velocity: np.ndarray, frame_s: float, margin: int = HALO_MARGIN_PX, paths: Any = None
) -> tuple[int, int]:
    """:func:`halo_px` along each axis, ``(rows, columns)``: the farthest any integration
    path gets from its place at t = 0 vertically and horizontally, plus ``margin``."""
    disp = _displacements(paths)
    reach = [0.0, 0.0]  # (x, y)
    for a in (0, 1):
        if velocity.size:
            reach[a] = float(np.abs(velocity[..., a]).max()) * frame_s
        if disp.size:
            reach[a] = max(reach[a], float(np.abs(disp[..., a]).max()))
    return int(math.ceil(reach[1])) + margin, int(math.ceil(reach[0])) + margin


def tile_grid(shape: tuple[int, int], tile: int, halo: int | tuple[int, int]) -> list[Tile]:
    """Cores covering ``shape`` (H, W), each grown by ``halo`` pixels, or by ``(rows,
    columns)`` (:func:`halo_yx`) (clipped to the frame), in rows and columns
    (:func:`grid_shape`): no tile, halo included, larger than a ``tile`` x ``tile`` core
    grown by the halo."""
    if tile < MIN_TILE_PX:
        raise InputError(f"tile size must be at least {MIN_TILE_PX} pixels, got {tile}")
    hy, hx = (halo, halo) if isinstance(halo, int) else halo
    return _grid(shape, *grid_shape(shape, tile, (hy, hx)), (hy, hx))


def _grid(shape: tuple[int, int], ny: int, nx: int, halo: tuple[int, int]) -> list[Tile]:
    """``ny`` x ``nx`` cores of near-equal sides covering ``shape``, grown by ``halo``."""
    h, w = shape
    hy, hx = halo
    ys, xs = _cuts(ny, h), _cuts(nx, w)
    tiles = []
    for i in range(ny):
        for j in range(nx):
            core = (int(ys[i]), int(ys[i + 1]), int(xs[j]), int(xs[j + 1]))
            outer = (
                max(0, core[0] - hy),
                min(h, core[1] + hy),
                max(0, core[2] - hx),
                min(w, core[3] + hx),
            )
            tiles.append(Tile(core, outer))
    return tiles


def _cuts(n: int, size: int) -> np.ndarray:
    """The ``n + 1`` borders of ``n`` near-equal parts of ``size`` pixels."""
    return np.linspace(0, size, n + 1).round().astype(int)


def grid_shape(shape: tuple[int, int], tile: int, halo: tuple[int, int]) -> tuple[int, int]:
    """Rows and columns of cores for ``shape`` (H, W): of the grids whose every tile
    (halo included) has at most the pixels of a ``tile`` x ``tile`` core grown by
    ``halo`` (rows, columns), the one whose tiles, solved in order :data:`GRID_AT_ONCE`
    at a time with a tile's cost its pixels, finish first; then the one with the fewest
    pixels in all, then the fewest tiles (the square grid where none fits). A halo that
    is longer along one axis (a pan) gets cores that are longer along it, so less of the
    frame is solved twice; an even halo, a grid near the square one. The same grid
    however the tiles are run (the same image on any number of workers)."""
    h, w = shape
    hy, hx = halo
    most = min(tile + 2 * hy, h) * min(tile + 2 * hx, w)
    square = (max(1, math.ceil(h / tile)), max(1, math.ceil(w / tile)))

    def lengths(n: int, size: int, grow: int) -> np.ndarray:  # (the tiles' along an axis)
        cuts = _cuts(n, size)
        return np.minimum(cuts[1:] + grow, size) - np.maximum(cuts[:-1] - grow, 0)

    best, best_key = square, None
    # (Up to four times the square grid's count along each axis: finer grids repeat
    # more of their halos.)
    for ny in range(1, min(max(1, h // MIN_TILE_PX), 4 * square[0]) + 1):
        rows = lengths(ny, h, hy)
        for nx in range(1, min(max(1, w // MIN_TILE_PX), 4 * square[1]) + 1):
            areas = np.outer(rows, lengths(nx, w, hx)).ravel()  # (in the tiles' order)
            if areas.max() > most:
                continue
            if best_key is not None and areas.sum() / GRID_AT_ONCE > best_key[0]:
                continue  # (it cannot finish sooner)
            load = [0] * GRID_AT_ONCE
            for a in areas.tolist():  # (each tile to the first thread free)
                load[load.index(min(load))] += a
            key = (max(load), int(areas.sum()), ny * nx)
            if best_key is None or key < best_key:
                best, best_key = (ny, nx), key
    return best


def blend_weight(tile: Tile, shape: tuple[int, int]) -> np.ndarray:
    """Weight over ``tile.outer``: 1 on the core, falling linearly to 0 across the halo
    towards neighbouring tiles, 1 up to the frame's own edges."""
    h, w = shape
    y0, y1, x0, x1 = tile.outer
    c0, c1, d0, d1 = tile.core

    def ramp(lo: int, hi: int, core_lo: int, core_hi: int, n: int) -> np.ndarray:
        pos = np.arange(lo, hi, dtype=np.float32) + 0.5
        rise = (
            np.ones_like(pos) if core_lo == 0 else np.clip((pos - lo) / max(core_lo - lo, 1), 0, 1)
        )
        fall = (
            np.ones_like(pos) if core_hi == n else np.clip((hi - pos) / max(hi - core_hi, 1), 0, 1)
        )
        return np.minimum(rise, fall)

    wy = ramp(y0, y1, c0, c1, h)
    wx = ramp(x0, x1, d0, d1, w)
    wgt = np.outer(wy, wx)
    wgt[c0 - y0 : c1 - y0, d0 - x0 : d1 - x0] = 1.0
    return wgt


def crop_capture(cap: Capture, tile: Tile) -> Capture:
    """The capture restricted to ``tile.outer``: every per-pixel array cropped, the rest
    (rig, metadata, time bins) shared."""
    ys, xs = tile.slices()
    h, w = cap.shape
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(cap):
        value = getattr(cap, f.name)
        if not isinstance(value, np.ndarray) or value.ndim < 2:
            continue
        if value.shape[:2] == (h, w):
            changes[f.name] = np.ascontiguousarray(value[ys, xs])
        elif value.ndim >= 3 and value.shape[1:3] == (h, w):
            changes[f.name] = np.ascontiguousarray(value[:, ys, xs])
    if cap.camera_bins is not None:  # a real rig's bins on its camera's grid
        changes["camera_bins"] = cap.camera_bins.crop(tile.outer, (h, w))
    return dataclasses.replace(cap, **changes)


def deblur_tile(
    solve: Callable[..., Any],
    cap: Capture,
    velocity: np.ndarray,
    motion_model: str,
    options: object | None,
    paths: Any = None,
) -> tuple[np.ndarray, str]:
    """One tile deblurred by ``solve`` (:func:`stages.deblur.deblur`) with a given motion
    (and its layers along paths, cropped to the tile, when the frame's motion has them):
    (radiance (H, W, C) in output units, what its still pixels took). ``cap`` is the
    tile's own crop (:func:`crop_capture`): its measuring stream is let go of once binned."""
    img, _vel = solve(
        cap,
        method="vet",
        motion=velocity,
        motion_model=motion_model,
        options=options,
        release_stream=True,
        motion_paths=paths,
    )
    return img.radiance, str(img.meta.get("still_pixels", ""))


def _deblur_tile_on_worker(
    solve: Callable[..., Any], job: tuple[Capture, np.ndarray, Any], motion_model: str, options
) -> tuple[np.ndarray, str]:
    """:func:`deblur_tile` of ``job`` (crop, velocity, paths: :func:`_tile_job`) on a Dask
    worker."""
    from ..cluster import limit_threads

    limit_threads()  # N workers mean N cores, on an embedded or an external cluster
    cap, velocity, paths = job
    return deblur_tile(solve, cap, velocity, motion_model, options, paths)


def _tile_jobs(
    cap: Capture, velocity: np.ndarray, tiles: list[Tile], paths: Any = None
) -> list[Callable[[], tuple[Capture, np.ndarray, Any]]]:
    """Per tile, a call that makes its job (crop, velocity, paths) when it is run."""
    return [functools.partial(_tile_job, cap, velocity, t, paths) for t in tiles]


def _tile_job(
    cap: Capture, velocity: np.ndarray, t: Tile, paths: Any
) -> tuple[Capture, np.ndarray, Any]:
    ys, xs = t.slices()
    crop = None
    if paths is not None:
        crop = dataclasses.replace(paths, label=np.ascontiguousarray(paths.label[ys, xs]))
    return crop_capture(cap, t), np.ascontiguousarray(velocity[ys, xs]), crop


def deblur_in_tiles(
    solve: Callable[..., Any],
    cap: Capture,
    velocity: np.ndarray,
    motion_model: str,
    options: object | None,
    tile: int,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    paths: Any = None,
    soon: Any = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Deblur ``cap`` tile by tile with the whole frame's ``velocity`` (H, W, 2) px/s,
    each tile by ``solve`` (:func:`stages.deblur.deblur`, passed in by its caller);
    ``paths``: that motion as :class:`~stages.deblur.operator.Layers` along their
    trajectories (a measured camera path), each tile solved along its crop of them.
    ``soon``: the Dask client to run them on, started by the caller
    (:class:`~stages.cluster.ClientSoon`; ``workers`` and ``scheduler`` are then its).

    Returns the blended radiance (H, W, C) in output units and a record ``{"size",
    "halo_px", "halo_yx_px", "count", "executor", "workers", "still_pixels"}`` (the halo
    along rows and columns, :func:`halo_yx`, and the wider of the two).
    """
    tf = float(cap.meta.get("integration_s", cap.rig.frame_s))
    halo = halo_yx(velocity, tf, paths=paths)
    tiles = tile_grid(cap.shape, tile, halo)
    h, w = cap.shape
    acc = np.zeros((h, w, cap.I.shape[2]), np.float32)
    wsum = np.zeros((h, w), np.float32)
    info: dict[str, Any] = {}
    still: list[str] = []  # (each blended tile's, in order)
    # Blended in the tiles' order whatever order they finish in (the overlaps' sums
    # then round alike: the same image on any number of workers).
    held: dict[int, tuple[np.ndarray, str]] = {}
    for i, result in _run(
        solve,
        _tile_jobs(cap, velocity, tiles, paths),
        len(tiles),
        motion_model,
        options,
        workers,
        scheduler,
        progress,
        info,
        soon,
    ):
        held[i] = result
        while (k := len(still)) in held:  # (the next tile in order, once it is in)
            radiance, still_pixels = held.pop(k)
            ys, xs = tiles[k].slices()
            wgt = blend_weight(tiles[k], (h, w))
            acc[ys, xs] += radiance * wgt[..., None]
            wsum[ys, xs] += wgt
            still.append(still_pixels)
    acc /= np.maximum(wsum, 1e-12)[..., None]
    record = {
        "size": int(tile),
        "halo_px": int(max(halo)),
        "halo_yx_px": [int(v) for v in halo],
        "count": len(tiles),
        "executor": info.get("executor", "in-process"),
        "workers": int(info.get("workers", 1)),
        "still_pixels": still[0] if len(set(still)) == 1 else "mixed",
    }
    return acc, record


def _run(
    solve: Callable[..., Any],
    jobs: list[Callable[[], tuple[Capture, np.ndarray, Any]]],
    n: int,
    motion_model: str,
    options: object | None,
    workers: int,
    scheduler: str | None,
    progress: Callable[[int, int], None] | None,
    info: dict[str, Any],
    soon: Any = None,
) -> Iterator[tuple[int, tuple[np.ndarray, str]]]:
    """Yield ``(tile index, deblur_tile result)`` as tiles finish: in-process with
    ``workers <= 1`` and no ``scheduler`` or ``soon``, else as Dask tasks (on ``soon``'s
    client where given)."""
    if soon is None and scheduler is None and workers <= 1:
        from ..cluster import in_order, one_thread_here, opencv_single_threaded, solve_threads

        info["executor"] = "in-process"
        # Tiles side by side on the process's threads, each solved on one: tiles share
        # the cores better than one solve's products do. At most TILES_AT_ONCE solving
        # (memory: one tile's operators and observations each); the next ones queued
        # behind them (a queued tile holds nothing until it starts: its crop is made
        # then), so a thread whose tile finishes first starts another while the one
        # handed out next is still solving. OpenCV on one thread however many run at
        # once, as on a Dask worker: the same image either way.
        with opencv_single_threaded():
            side = min(TILES_AT_ONCE, solve_threads()) > 1

            def one(i: int) -> tuple[np.ndarray, str]:
                cap, vel, paths = jobs[i]()  # (the crop made on the thread that solves it)
                with one_thread_here() if side else contextlib.nullcontext():
                    return deblur_tile(solve, cap, vel, motion_model, options, paths)

            for i, result in enumerate(
                in_order(one, n, ahead=2, most=TILES_AT_ONCE) if side else map(one, range(n))
            ):
                yield i, result
                if progress:
                    progress(i + 1, n)
        return
    import distributed

    from ..cluster import dask_client

    if soon is not None:  # (started by the caller, closed by it)
        started = contextlib.nullcontext(soon.client())
        info.update(soon.info)
    else:
        started = dask_client(workers, scheduler, info)
    with started as client:
        # Each tile's data scattered to the workers (not in the task graph, which the
        # scheduler would unpickle and hold), DASK_AHEAD tiles a worker in flight: the
        # cluster holds a few tiles' data at a time, not the frame's.
        window = max(1, DASK_AHEAD * max(1, int(info.get("workers", 1))))
        index: dict[Any, int] = {}

        def submit(i: int) -> Any:
            [data] = client.scatter([jobs[i]()], hash=False)
            fut = client.submit(
                _deblur_tile_on_worker, solve, data, motion_model, options, pure=False
            )
            index[fut] = i
            return fut

        queue = distributed.as_completed(
            [submit(i) for i in range(min(n, window))], loop=client.loop
        )
        done, started = 0, min(n, window)
        for fut in queue:
            try:
                result = fut.result()
            except VetError:
                raise
            except Exception as exc:  # noqa: BLE001 - a worker died or a task failed
                raise VetError(f"tile {index[fut]} failed on a Dask worker ({exc})") from None
            fut.release()
            if started < n:
                queue.add(submit(started))
                started += 1
            done += 1
            if progress:
                progress(done, n)
            yield index.pop(fut), result
