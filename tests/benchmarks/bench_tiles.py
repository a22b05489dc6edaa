"""Benchmark: tiled deblur of a large mono capture (translate:30,0), in-process and on Dask.

Simulates the capture in a child process, then deblurs it in fresh child processes, each
reporting its wall time, peak memory (ru_maxrss of the process and of its worker
processes), the dark-pixel RMS error in stops against the truth (as ``vet evaluate``
scores) and the same error split into a band of 8 px on each side of every tile border
(the seams) and the rest. Configurations: one solve (frames up to 1.4 MP), or where
none fits, larger tiles whose seams lie elsewhere (:func:`control_grid`; the band scored
on them is the same content without this grid's seams); tiles in-process (the solver's own
threads, one a core); tiles on a Dask cluster of 1 worker and on one of 2 workers (one
thread each, as ``vet deblur -j N`` runs them), so that "2 workers against 1" compares
the same engine. Each deblur lets the capture's stream go once binned, as ``vet deblur``
does (on a frame this large its bins are made before the motion estimate).

The Dask runs also report, from the scheduler's task stream, the client's work before
the first tile starts (reading is not timed; the motion estimate and the fit bins do not
spread over workers) and the median time a worker takes for one tile, alone and with a
second worker beside it: "2 workers against 1" is bounded by both.

Run: ``.venv/bin/python -m tests.benchmarks.bench_tiles [WxH] [TILE]`` (default, and what
``make bench`` runs to stay short: 2048x1536 with 1024 px tiles; issue 19's size is
``4096x3072``, and ``vet deblur``'s own tiles are 512 px).
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SEAM_PX = 8


def _simulate(size: str, path: str) -> None:
    import numpy as np

    from stages.formats import write_capture
    from stages.motion import parse_motion
    from stages.rig import RigParams
    from stages.scenes import Scene, builtin_interior, luminance, parse_size
    from stages.simulate import simulate

    w, h = parse_size(size)
    sc = builtin_interior(w, h)
    mono = Scene(luminance(sc.radiance)[..., None].astype(np.float32), ["Y"], sc.source + " (mono)")
    cap = simulate(mono, parse_motion("translate:30,0"), RigParams(sensor_size=(w, h)), seed=0)
    write_capture(path, cap["vet"])


def _deblur(path: str, tile: str, workers: str, seam_tile: int) -> dict:
    import numpy as np

    from stages.deblur import deblur
    from stages.deblur.tiles import halo_yx, tile_grid
    from stages.formats import read_capture
    from stages.metrics import measurable_floor, stops_error

    cap = read_capture(path)
    cluster, scheduler = None, None
    if workers.startswith("dask"):  # a cluster of that many workers, reached by its address
        import logging

        import distributed

        from stages.cluster import WORKER_ENV, environ_kept

        with environ_kept():  # (as vet's own: the workers' variables are theirs)
            cluster = distributed.LocalCluster(
                n_workers=int(workers[4:]),
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=None,
                env=dict(WORKER_ENV),
                silence_logs=logging.ERROR,
            )
        scheduler = cluster.scheduler_address
    t0, wall0 = time.perf_counter(), time.time()
    stream = contextlib.nullcontext(None)
    if cluster is not None:  # (each tile's start and end on its worker)
        watcher = distributed.Client(scheduler)
        stream = distributed.get_task_stream(watcher)
    from stages.deblur import tiles

    shaped = tiles.grid_shape
    if tile.startswith("grid"):  # (the control: a grid given as rows x columns)
        ny, nx = (int(v) for v in tile[4:].split("x"))
        tiles.grid_shape = lambda *_: (ny, nx)
        tile = str(max(cap.shape) - 1)  # (any size under the frame's: the grid is given)
    with stream as tasks:
        img, vel = deblur(
            cap,
            tile=None if tile == "none" else int(tile),
            workers=1 if cluster else int(workers),
            scheduler=scheduler,
            release_stream=True,  # (as vet deblur runs it)
        )
    dt = time.perf_counter() - t0
    tiles.grid_shape = shaped  # (the seam band below is the seam tile's own grid's)
    spans = []
    if cluster is not None:
        for task in tasks.data:
            for ss in task.get("startstops", ()):
                if ss.get("action") == "compute":
                    spans.append((ss["start"] - wall0, ss["stop"] - wall0))
        watcher.close()
        cluster.close()
    rig = cap.rig
    floor = measurable_floor(rig, cap.radiance_scale)

    def dark(mask: np.ndarray | None = None) -> float:
        err = stops_error(img.radiance, cap.truth, cap.T, rig.frame_s, floor=floor, mask=mask)
        return float(err["dark"]["rms"])

    out = {
        "time_s": round(dt, 1),
        "peak_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 2),
        "worker_peak_gb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6, 2),
        "dark_rms": round(dark(), 4),
        "tiles": img.meta.get("tiles"),
    }
    if spans:  # the tiles as their workers ran them
        out["tile_solve_s"] = round(float(np.median([b - a for a, b in spans])), 1)
        out["client_before_tiles_s"] = round(min(a for a, _ in spans), 1)
    if seam_tile:  # the seams of seam_tile's grid, also scored on a one-piece solve
        h, w = cap.shape
        seam = np.zeros((h, w), bool)
        tf = float(cap.meta.get("integration_s", rig.frame_s))
        for t in tile_grid((h, w), seam_tile, halo_yx(vel, tf)):
            y0, y1, x0, x1 = t.core
            for y in (y0, y1):
                if 0 < y < h:
                    seam[max(0, y - SEAM_PX) : y + SEAM_PX, x0:x1] = True
            for x in (x0, x1):
                if 0 < x < w:
                    seam[y0:y1, max(0, x - SEAM_PX) : x + SEAM_PX] = True
        out["seam_dark_rms"] = round(dark(seam), 4)
        out["rest_dark_rms"] = round(dark(~seam), 4)
    return out


def _child(*args: str) -> dict | None:
    cmd = [sys.executable, "-m", "tests.benchmarks.bench_tiles", "--child", *args]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        print(f"  {' '.join(args[:1])} failed: {res.stderr.strip().splitlines()[-1:]}")
        return None
    lines = res.stdout.strip().splitlines()
    return json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}


def _seams(grid: list, shape: tuple[int, int]) -> tuple[set, set]:
    """The rows and columns where ``grid``'s cores meet inside the frame."""
    h, w = shape
    rows = {y for t in grid for y in t.core[:2] if 0 < y < h}
    cols = {x for t in grid for x in t.core[2:] if 0 < x < w}
    return rows, cols


def control_grid(shape: tuple[int, int], tile: int) -> tuple[int, int]:
    """Rows and columns of a grid none of whose core borders lies within ``2 * SEAM_PX``
    of one of ``tile``'s grid (for the simulated pan's halo), each tile no larger than
    one of 1.5 times ``tile`` (:func:`~stages.deblur.tiles.tile_grid`'s bound): of those,
    the one whose tiles hold the fewest pixels in all, then the fewest tiles. Its solve
    scores the content of ``tile``'s seam band away from seams of its own."""
    import numpy as np

    from stages.deblur.tiles import _grid, halo_yx, tile_grid
    from stages.rig import RigParams

    halo = halo_yx(np.array([[[30.0, 0.0]]], np.float32), RigParams().frame_s)
    rows, cols = _seams(tile_grid(shape, tile, halo), shape)
    big = tile * 3 // 2
    most = (big + 2 * halo[0]) * (big + 2 * halo[1])
    apart = lambda xs, ys: all(abs(a - b) > 2 * SEAM_PX for a in xs for b in ys)  # noqa: E731
    best, best_key = None, None
    for ny in range(1, 9):
        for nx in range(1, 9):
            grid = _grid(shape, ny, nx, halo)
            crow, ccol = _seams(grid, shape)
            areas = [t.pixels for t in grid]
            key = (sum(areas), ny * nx)
            if max(areas) <= most and apart(rows, crow) and apart(cols, ccol):
                if best_key is None or key < best_key:
                    best, best_key = (ny, nx), key
    if best is None:
        raise SystemExit(f"no control grid for {shape} beside {tile} px tiles")
    return best


def main(size: str = "2048x1536", tile: str = "1024") -> None:
    w, h = (int(v) for v in size.split("x"))
    with tempfile.TemporaryDirectory(prefix="vet-bench-tiles-") as tmp:
        path = str(Path(tmp) / "cap.npz")
        t0 = time.perf_counter()
        _child("simulate", size, path)
        print(f"simulate {size} mono translate:30,0: {time.perf_counter() - t0:.1f} s", flush=True)
        # Where no one-piece solve fits, larger tiles whose seams lie elsewhere stand in
        # for it: the band scored on them is the same content without this grid's seams.
        control = "none" if w * h <= 1.4e6 else "grid{}x{}".format(*control_grid((h, w), int(tile)))
        runs = [(control, "1")] + [(tile, "1"), (tile, "dask1"), (tile, "dask2")]
        results = {}
        for t, j in runs:
            r = _child("deblur", path, t, j, tile)
            if r is None:
                continue
            results[(t, j)] = r
            if t == "none":
                label = "one solve"
            elif j.startswith("dask"):
                label = f"tiles {t} px, Dask, {j[4:]} worker(s)"
            else:
                kind = f"a {t[4:]} grid" if t.startswith("grid") else f"{t} px"
                label = f"tiles {kind}, in-process" + (
                    f" (seam band: the {tile} px grid's)" if t != tile else ""
                )
            seam = (
                f", seam band {r['seam_dark_rms']:.4f} vs rest {r['rest_dark_rms']:.4f}"
                if "seam_dark_rms" in r
                else ""
            )
            tiles = r.get("tiles") or {}
            print(
                f"{size} {label}: {r['time_s']:.1f} s, peak {r['peak_gb']:.2f} GB "
                f"(workers {r['worker_peak_gb']:.2f} GB), dark RMS {r['dark_rms']:.4f} stops{seam}"
                + (
                    f"; {tiles.get('count')} tiles, halo {tiles.get('halo_px')} px" if tiles else ""
                ),
                flush=True,
            )
        local, one, two = (results.get((tile, j)) for j in ("1", "dask1", "dask2"))
        if one and two:
            print(f"Dask, 2 workers vs 1: {one['time_s'] / two['time_s']:.2f}x", flush=True)
            if "tile_solve_s" in one and "tile_solve_s" in two:
                print(
                    f"  of which: the client's work before the first tile {one['client_before_tiles_s']:.1f}"
                    f" / {two['client_before_tiles_s']:.1f} s (1 / 2 workers; it does not spread);"
                    f" a tile's solve {one['tile_solve_s']:.1f} s alone, {two['tile_solve_s']:.1f} s"
                    f" with another beside it ({two['tile_solve_s'] / one['tile_solve_s']:.2f}x:"
                    " what two cores lose running together)",
                    flush=True,
                )
        if local and two:
            print(
                f"Dask, 2 workers vs in-process: {local['time_s'] / two['time_s']:.2f}x", flush=True
            )


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        what, *rest = sys.argv[2:]
        if what == "simulate":
            _simulate(*rest)
            print("{}")
        else:
            print(json.dumps(_deblur(rest[0], rest[1], rest[2], int(rest[3]))))
    else:
        main(*sys.argv[1:])
