"""Tiled deblur (stages.deblur.tiles): the grid, the blend, the crop, and that a tiled
solve agrees with the one-piece solve, in-process and on Dask."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from stages.deblur import deblur
from stages.deblur.operator import Layers
from stages.deblur.tiles import (
    Tile,
    _grid,
    blend_weight,
    crop_capture,
    grid_shape,
    halo_px,
    halo_yx,
    resolve_tile,
    tile_grid,
)
from stages.errors import InputError
from stages.metrics import measurable_floor, stops_error
from stages.motion import parse_motion
from stages.rig import RigParams
from stages.scenes import builtin_interior
from stages.simulate import simulate
from vet_cli.main import cli


def test_cores_cover_every_pixel_once_and_halos_stay_in_frame():
    shape, halo = (300, 530), 40
    tiles = tile_grid(shape, 128, halo)
    count = np.zeros(shape, int)
    for t in tiles:
        y0, y1, x0, x1 = t.core
        count[y0:y1, x0:x1] += 1
        oy0, oy1, ox0, ox1 = t.outer
        assert (oy0, ox0) == (max(0, y0 - halo), max(0, x0 - halo))
        assert (oy1, ox1) == (min(300, y1 + halo), min(530, x1 + halo))
        # no tile larger than a 128 x 128 core with its halo
        assert t.pixels == (oy1 - oy0) * (ox1 - ox0) <= (128 + 2 * halo) ** 2
    assert np.all(count == 1)
    # (edge tiles lose their halo outside the frame: fewer tiles than the 3 x 5 squares)
    assert grid_shape(shape, 128, (halo, halo)) == (2, 4)
    with pytest.raises(InputError, match="at least 64"):
        tile_grid(shape, 32, halo)


def test_halo_covers_the_longest_integration_path():
    vel = np.zeros((10, 10, 2), np.float32)
    vel[3, 4] = (30.0, -40.0)  # 50 px/s
    assert halo_px(vel, 1.0, margin=0) == 50
    assert halo_px(vel, 0.5, margin=16) == 25 + 16
    assert halo_px(np.zeros((4, 4, 2)), 1.0, margin=16) == 16


def test_halo_along_each_axis_covers_each_axis_reach():
    # Rows by the vertical reach, columns by the horizontal: a pan grows tiles
    # sideways by its path, and up and down by the margin alone.
    vel = np.zeros((10, 10, 2), np.float32)
    vel[3, 4] = (30.0, -4.0)
    vel[5, 5] = (-10.0, 7.5)
    assert halo_yx(vel, 1.0, margin=0) == (8, 30)
    assert halo_yx(vel, 0.5, margin=16) == (4 + 16, 15 + 16)
    assert halo_px(vel, 1.0, margin=0) == 31  # (the longest path: |(30, -4)|)
    # A measured path reaches farther than its mean velocity: its displacements count.
    paths = Layers(
        np.zeros((10, 10), np.int32),
        np.array([[0.0, 0.0]]),
        [],
        0,
        trajectory=(np.array([0.0, 0.5, 1.0]), np.array([[[0.0, 0.0], [3.0, 12.0], [0.0, 0.0]]])),
    )
    assert halo_yx(np.zeros((10, 10, 2), np.float32), 1.0, margin=0, paths=paths) == (12, 3)
    tiles = tile_grid((300, 530), 128, (5, 40))
    for t in tiles:
        y0, y1, x0, x1 = t.core
        assert t.outer == (max(0, y0 - 5), min(300, y1 + 5), max(0, x0 - 40), min(530, x1 + 40))


def test_a_pans_grid_runs_along_the_pan():
    # A horizontal pan's halo is long sideways and short up and down: rows of tiles as
    # wide as the frame allows solve less of it twice than squares do, and finish
    # sooner two at a time; an even halo keeps the squares.
    shape = (1024, 1280)
    assert grid_shape(shape, 512, (16, 16)) == (2, 3)
    assert grid_shape(shape, 512, (16, 46)) == (3, 2)
    assert grid_shape(shape, 640, (16, 46)) == (4, 1)
    assert grid_shape((1280, 1024), 640, (46, 16)) == (1, 4)  # (a vertical pan)
    # (where no grid of cores at least MIN_TILE_PX a side fits the bound: the squares)
    assert grid_shape((100, 100), 64, (16, 16)) == (2, 2)
    pan = tile_grid(shape, 512, (16, 46))
    squares = _grid(shape, 2, 3, (16, 46))
    assert sum(t.pixels for t in pan) < sum(t.pixels for t in squares)
    assert max(t.pixels for t in pan) <= (512 + 32) * (512 + 92)


def test_the_grid_is_the_same_however_many_tiles_run_at_once(monkeypatch):
    # (Tiles one at a time, or on any number of workers, blend the same image: the
    # grid is shaped for GRID_AT_ONCE, not for what runs them.)
    from stages.deblur import tiles

    for at_once in (1, 2, 4):
        monkeypatch.setattr(tiles, "TILES_AT_ONCE", at_once)
        assert grid_shape((1024, 1280), 512, (16, 46)) == (3, 2)
        assert grid_shape((1024, 1280), 640, (16, 46)) == (4, 1)


def test_blending_a_constant_reproduces_it_and_cores_weigh_one():
    shape, halo = (200, 260), 30
    tiles = tile_grid(shape, 96, halo)
    acc, wsum = np.zeros(shape), np.zeros(shape)
    for t in tiles:
        w = blend_weight(t, shape)
        ys, xs = t.slices()
        assert w.shape == (ys.stop - ys.start, xs.stop - xs.start)
        cy, cx = t.slices("core")
        assert np.all(
            w[cy.start - ys.start : cy.stop - ys.start, cx.start - xs.start : cx.stop - xs.start]
            == 1
        )
        acc[ys, xs] += 7.0 * w
        wsum[ys, xs] += w
    assert wsum.min() >= 1.0
    np.testing.assert_allclose(acc / wsum, 7.0)
    # a lone tile's weight is 1 everywhere (the frame's own edges do not fade)
    lone = Tile((0, 50, 0, 60), (0, 50, 0, 60))
    assert np.all(blend_weight(lone, (50, 60)) == 1)


def test_resolve_tile():
    assert resolve_tile("auto", (1024, 1024)) is None
    assert resolve_tile("auto", (1024, 1280)) == 512
    assert resolve_tile("auto", (3072, 4096)) == 512
    assert resolve_tile("auto", (1024, 1280), channels=1) == 640  # (a mono tile: larger)
    assert resolve_tile("auto", (1024, 1024), channels=1) is None
    assert resolve_tile("none", (3072, 4096)) is None
    assert resolve_tile(256, (100, 100)) == 256
    with pytest.raises(InputError):
        resolve_tile(10, (100, 100))


@pytest.fixture(scope="module")
def moving_capture():
    rig = RigParams(sensor_size=(192, 128))
    scene = builtin_interior(192, 128)
    return simulate(scene, parse_motion("translate:30,0"), rig, seed=3, methods=["vet"])["vet"]


@pytest.fixture(scope="module")
def one_at_a_time(moving_capture):
    """The capture's image solved in 64 px tiles, one after the other, in-process."""
    from stages.deblur import tiles

    before = tiles.TILES_AT_ONCE
    tiles.TILES_AT_ONCE = 1
    try:
        return deblur(moving_capture, motion_init="truth", tile=64)[0]
    finally:
        tiles.TILES_AT_ONCE = before


def test_crop_takes_every_per_pixel_array(moving_capture):
    cap = moving_capture
    t = Tile((10, 40, 20, 70), (0, 50, 5, 90))
    sub = crop_capture(cap, t)
    assert sub.I.shape[:2] == sub.T.shape == (50, 85)
    np.testing.assert_array_equal(sub.I, cap.I[0:50, 5:90])
    np.testing.assert_array_equal(sub.measure, cap.measure[:, 0:50, 5:90])
    np.testing.assert_array_equal(sub.truth_motion, cap.truth_motion[0:50, 5:90])
    np.testing.assert_array_equal(sub.measure_times, cap.measure_times)
    assert sub.rig == cap.rig


def _dark_rms(cap, img):
    err = stops_error(
        img.radiance,
        cap.truth,
        exposure_time=cap.T,
        frame_s=cap.rig.frame_s,
        floor=measurable_floor(cap.rig, cap.radiance_scale),
    )
    return err["dark"]["rms"]


def test_tiled_solve_matches_the_one_piece_solve(moving_capture):
    cap = moving_capture
    whole, _ = deblur(cap, motion_init="truth")
    tiled, vel = deblur(cap, motion_init="truth", tile=96)
    assert tiled.meta["tiles"]["count"] == 2
    assert tiled.meta["tiles"]["halo_px"] == 30 + 16
    assert tiled.meta["tiles"]["halo_yx_px"] == [
        16,
        30 + 16,
    ]  # (a pan: the margin alone up and down)
    np.testing.assert_array_equal(vel, cap.truth_motion)
    a, b = _dark_rms(cap, whole), _dark_rms(cap, tiled)
    assert b <= a * 1.05, (a, b)
    assert tiled.radiance.shape == whole.radiance.shape
    assert tiled.mask.shape == whole.mask.shape


def test_tiles_side_by_side_give_the_image_of_one_at_a_time(
    moving_capture, one_at_a_time, monkeypatch
):
    # In one process, tiles are solved two at a time, each on one thread: the image is
    # the one of tiles solved one after the other, to the bit.
    import threading

    from stages import cluster
    from stages.deblur import tiles

    cap, alone = moving_capture, one_at_a_time
    seen = []
    solve_one = tiles.deblur_tile

    def spy(*args):
        seen.append((threading.get_ident(), cluster.solve_threads()))
        return solve_one(*args)

    monkeypatch.setattr(tiles, "TILES_AT_ONCE", 2)
    monkeypatch.setattr(tiles, "deblur_tile", spy)
    monkeypatch.setattr(cluster.os, "cpu_count", lambda: 2)  # (the process not limited:)
    monkeypatch.setattr(cluster, "_threads_limited", False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    both, _ = deblur(cap, motion_init="truth", tile=64)
    assert both.meta["tiles"]["count"] == len(seen) >= 4
    assert len({t for t, _ in seen}) == 2 and {n for _, n in seen} == {1}
    np.testing.assert_array_equal(both.radiance, alone.radiance)


@pytest.mark.slow
def test_tiles_on_a_separately_started_dask_cluster(moving_capture, tmp_path):
    from tests.dask_local import separate_dask_cluster

    cap = moving_capture
    local, _ = deblur(cap, motion_init="truth", tile=96)
    with separate_dask_cluster(tmp_path, workers=2) as address:
        remote, _ = deblur(cap, motion_init="truth", tile=96, scheduler=address)
    assert remote.meta["tiles"]["executor"] == f"dask scheduler {address}"
    assert remote.meta["tiles"]["workers"] >= 1
    np.testing.assert_allclose(remote.radiance, local.radiance, rtol=1e-5, atol=1e-6)


def test_cli_tile_options(tmp_path):
    res = CliRunner().invoke(cli, ["deblur", "x.exr", "-o", "y.exr", "--tile", "32"])
    assert res.exit_code == 2 and "tile size >= 64" in res.output
    res = CliRunner().invoke(cli, ["deblur", "x.exr", "-o", "y.exr", "-j", "0"])
    assert res.exit_code == 2


def test_tiles_on_an_embedded_cluster_are_scattered_beside_their_tasks(
    moving_capture, one_at_a_time, monkeypatch
):
    # Each tile's data goes to the workers beside its task (no large task graph: Dask
    # warns of one over its threshold, lowered here below a tile's data), at most
    # DASK_AHEAD tiles a worker in flight, the next submitted as others finish; the
    # image is the one solved in-process. The cluster starts before the motion is
    # estimated (its start and the workers' imports overlap that work).
    import warnings

    import dask
    import distributed

    import stages.deblur
    from stages import cluster
    from stages.deblur import tiles

    events = []

    class Recorded(cluster.ClientSoon):
        def __init__(self, *a, **kw):
            events.append("cluster")
            super().__init__(*a, **kw)

    motion = stages.deblur.start_motion
    monkeypatch.setattr(cluster, "ClientSoon", Recorded)
    monkeypatch.setattr(
        stages.deblur, "start_motion", lambda *a: events.append("motion") or motion(*a)
    )

    in_flight = []

    class Watched(distributed.as_completed):  # (how many tiles are out, at each step)
        def __init__(self, futures, **kw):
            super().__init__(futures, **kw)
            in_flight.append(self.count())

        def add(self, future):
            super().add(future)
            in_flight.append(self.count())

    cap, alone = moving_capture, one_at_a_time
    monkeypatch.setattr(tiles, "DASK_AHEAD", 1)  # (tiles submitted as others finish)
    monkeypatch.setattr(distributed, "as_completed", Watched)
    with (
        dask.config.set({"distributed.admin.large-graph-warning-threshold": "20kB"}),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("error")  # (a large-graph warning fails the test)
        spread, _ = deblur(cap, motion_init="truth", tile=64, workers=2)
    assert spread.meta["tiles"]["executor"].startswith("dask LocalCluster, 2 worker")
    assert events == ["cluster", "motion"]
    assert spread.meta["tiles"]["count"] == alone.meta["tiles"]["count"] > 2
    assert len(in_flight) == spread.meta["tiles"]["count"] - 1  # (the first two, then one each)
    assert max(in_flight) <= 2  # (DASK_AHEAD x 2 workers)
    np.testing.assert_array_equal(spread.radiance, alone.radiance)


def test_tiles_finishing_in_any_order_blend_to_the_same_image(
    moving_capture, one_at_a_time, monkeypatch
):
    # Dask hands tiles back as they finish; they are blended in the grid's order, so
    # the overlaps' sums round alike: the same image to the bit.
    from stages.deblur import tiles

    cap, in_order = moving_capture, one_at_a_time
    run = tiles._run
    monkeypatch.setattr(tiles, "_run", lambda *a: reversed(list(run(*a))))
    reversed_, _ = deblur(cap, motion_init="truth", tile=64)
    assert reversed_.meta["tiles"] == in_order.meta["tiles"]
    np.testing.assert_array_equal(reversed_.radiance, in_order.radiance)


def test_a_thread_whose_tile_finishes_first_starts_the_next(monkeypatch):
    # In process, two tiles solve side by side. While the tile handed out first is still
    # solving, a thread that finished the other starts the tile after them (queued
    # behind them), not idle until the first is done. Tile 0 waits for tile 2 to start.
    import threading

    import stages.cluster as cluster_mod
    import stages.deblur.tiles as tiles_mod

    monkeypatch.setattr(cluster_mod, "solve_threads", lambda: 2)
    started = [threading.Event() for _ in range(4)]
    seen: dict[str, bool] = {}

    def fake_tile(solve, cap, vel, motion_model, options, paths):
        started[cap].set()
        if cap == 0:
            seen["third started while the first solved"] = started[2].wait(timeout=10)
        return np.full((1, 1, 1), cap, np.float32), "fused"

    monkeypatch.setattr(tiles_mod, "deblur_tile", fake_tile)
    jobs = [lambda i=i: (i, None, None) for i in range(4)]
    info: dict = {}
    got = list(tiles_mod._run(None, jobs, 4, "given", None, 1, None, None, info))
    assert [i for i, _ in got] == [0, 1, 2, 3]  # (handed out in order)
    assert seen == {"third started while the first solved": True}
