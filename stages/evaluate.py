"""Evaluation: every method on one scene and motion, one table, plots and pictures.

Reproduces the paper's published comparison: one :func:`stages.simulate.simulate` pass
renders the VET capture and the comparison captures (long, short, adaptive
attenuation) from the same scene, motion and noise; each is reconstructed (hdr-static for
the comparison methods and for VET without optimisation; deblur for VET with it, default
and published methods, and the default method with the true motion as an oracle; the
burst merge of the VET capture's measuring images alone, :mod:`stages.burst`) and
scored against the true scene at t = 0 with :func:`stages.metrics.stops_error`, split by
the VET capture's exposure time: ``dark`` pixels were exposed the whole frame, ``bright``
ones closed early. The same split is used for every method so that rows compare like
with like. Pixels are scored down to the level the rig can measure at all
(:func:`stages.metrics.measurable_floor`: a whole-frame exposure gathers as much signal
as noise), however dark; only those below it are left out.

Outputs (written atomically into the report folder): ``results.csv``, ``results.md``,
``errors.png`` (bar chart), ``contact_sheet.png`` (all methods and the truth, tone-mapped
with one operator and one set of levels), ``exposure_time.png`` and ``motion.png``.
"""

from __future__ import annotations

import csv
import io
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .formats.io import atomic_output
from .metrics import BORDER_PX

log = logging.getLogger(__name__)

#: Table rows in order.
ROWS = (
    "vet-deblur",
    "vet-deblur-paper",
    "vet-static",
    "burst-merge",
    "adaptive-attenuation",
    "long",
    "short",
    "vet-deblur-oracle",
)
#: Rows run only when asked for: hdr-static with the rig's parts ignored (a capture of a
#: real rig reconstructed as if the rig were ideal: what its calibration is worth).
EXTRA_ROWS = ("vet-static-ideal-rig",)
REGIONS = ("all", "dark", "bright")
STATS = ("median", "p99", "rms")


@dataclass
class Evaluation:
    """Scores, images and timings of one evaluation."""

    scene: str
    motion: str
    size: tuple[int, int]
    seed: int
    scores: dict[str, dict[str, Any]] = field(default_factory=dict)
    runtime_s: dict[str, float] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    truth: np.ndarray | None = None
    T: np.ndarray | None = None
    velocity: np.ndarray | None = None
    truth_motion: np.ndarray | None = None
    frame_s: float = 1.0
    subframe_s: float = 0.01
    radiance_scale: float = float("nan")
    reach_subframes: float | None = 1.0  # None: the radiance scale was given
    rig_changes: dict[str, Any] = field(default_factory=dict)
    rig_profile: str = "ideal"  # stages.optics.rig_profile
    floor: float = 0.0  # truth level (scene units) at or below which pixels are not scored
    floor_e: float = 0.0  # the same, as electrons of a whole-frame VET exposure


def run_evaluation(
    scene_spec: str,
    motion_spec: str,
    size: tuple[int, int] | None = None,
    seed: int = 0,
    rows: tuple[str, ...] = ROWS,
    progress: Callable[[str], None] | None = None,
    rig_changes: dict[str, Any] | None = None,
    rig_profile: str = "ideal",
    scale: float | None = None,
    reach_subframes: float = 1.0,
    on_step: Callable[[int, int], None] | None = None,
) -> Evaluation:
    """Simulate, reconstruct and score the methods in ``rows`` (module docstring).

    ``rig_changes`` are :class:`~stages.rig.RigParams` fields that differ from the
    rig of ``rig_profile`` (:func:`stages.optics.rig_profile`); ``scale`` and ``reach_subframes`` set the radiance scale as in
    :func:`stages.simulate.simulate`. Only the comparison captures that ``rows`` needs
    are rendered; the VET capture always is, since it defines the dark/bright split.
    ``progress(message)`` names each part as it starts (the simulation, then one per
    row); ``on_step(done, total)`` reports the work done in hundredths of a part
    (``total = 100 * parts``), from ``(0, total)`` to ``(total, total)``.
    """
    from .burst import burst_hdr
    from .deblur import deblur
    from .hdr_static import hdr_static
    from .metrics import measurable_floor, stops_error
    from .motion import check_in_frame, parse_motion
    from .scenes import load_scene
    from .simulate import Radiance, simulate

    unknown = [r for r in rows if r not in ROWS + EXTRA_ROWS]
    if unknown or not rows:
        raise ValueError(f"unknown methods {unknown}; choose from {', '.join(ROWS + EXTRA_ROWS)}")
    say = progress or (lambda msg: None)
    step = on_step or (lambda done, total: None)
    units = 100 * (1 + len(rows))

    def part(i: int) -> Callable[[int, int], None]:
        """Progress within part ``i`` (0: the simulation) as the evaluation's."""
        return lambda d, t: step(100 * i + min(100, 100 * d // max(t, 1)), units)

    scene = load_scene(scene_spec, size)
    h, w = scene.radiance.shape[:2]
    motion = parse_motion(motion_spec)
    check_in_frame(motion, (h, w))
    changes = dict(rig_changes or {})
    from .optics import rig_profile as make_rig

    rig = make_rig(rig_profile, (w, h), **changes)
    renders = ["vet"] + [m for m in ("long", "short", "adaptive-attenuation") if m in rows]
    step(0, units)
    say(f"simulating {w}x{h} {motion.spec}")
    t0 = time.perf_counter()
    caps = simulate(
        scene,
        motion,
        rig,
        seed=seed,
        methods=renders,
        progress=part(0),
        radiance=Radiance(scale, reach_subframes),
    )
    sim_s = time.perf_counter() - t0
    vet = caps["vet"]
    ev = Evaluation(
        scene_spec,
        motion.spec,
        (w, h),
        seed,
        truth=vet.truth,
        T=vet.T,
        truth_motion=vet.truth_motion,
        frame_s=rig.frame_s,
        subframe_s=rig.subframe_s,
        radiance_scale=float(vet.radiance_scale),
        reach_subframes=float(reach_subframes) if scale is None else None,
        rig_changes=changes,
        rig_profile=rig_profile,
    )
    ev.floor = measurable_floor(rig, ev.radiance_scale)
    ev.floor_e = ev.floor * ev.radiance_scale * rig.frame_s
    ev.runtime_s["simulate"] = sim_s
    plan: dict[str, Callable[[Callable[[int, int], None]], Any]] = {
        "vet-static": lambda p: (hdr_static(vet), None),
        "vet-static-ideal-rig": lambda p: (hdr_static(vet, assume_ideal_rig=True), None),
        "burst-merge": lambda p: (burst_hdr(vet, p), None),
        "adaptive-attenuation": lambda p: (hdr_static(caps["adaptive-attenuation"]), None),
        "long": lambda p: (hdr_static(caps["long"]), None),
        "short": lambda p: (hdr_static(caps["short"]), None),
        "vet-deblur": lambda p: deblur(vet, "vet", progress=p),
        "vet-deblur-paper": lambda p: deblur(vet, "paper", progress=p),
        "vet-deblur-oracle": lambda p: deblur(vet, "vet", motion_init="truth", progress=p),
    }
    for i, name in enumerate(rows):
        step(100 * (1 + i), units)
        say(f"reconstructing {name}")
        t0 = time.perf_counter()
        img, vel = plan[name](part(1 + i))
        ev.runtime_s[name] = time.perf_counter() - t0
        if name == "vet-deblur":
            ev.velocity = vel
        ev.images[name] = img.radiance
        ev.scores[name] = stops_error(img.radiance, vet.truth, vet.T, rig.frame_s, floor=ev.floor)
        log.debug(
            "evaluate: %s dark rms %.3f (%.1f s)",
            name,
            ev.scores[name]["dark"]["rms"],
            ev.runtime_s[name],
        )
    step(units, units)
    return ev


def table_rows(ev: Evaluation) -> list[dict[str, Any]]:
    """One dict per method: ``method``, ``{region}_{stat}`` in stops, ``n_*``, ``runtime_s``."""
    out = []
    for name in ev.scores:
        s = ev.scores[name]
        row: dict[str, Any] = {"method": name}
        for reg in REGIONS:
            for st in STATS:
                row[f"{reg}_{st}"] = s.get(reg, {}).get(st, float("nan"))
        for reg in REGIONS:
            row[f"n_{reg}"] = s.get(reg, {}).get("n", 0)
        row["runtime_s"] = ev.runtime_s.get(name, float("nan"))
        out.append(row)
    return out


def results_csv(ev: Evaluation) -> str:
    rows = table_rows(ev)
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=list(rows[0].keys()), lineterminator="\n")
    wr.writeheader()
    for r in rows:
        wr.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def results_markdown(ev: Evaluation) -> str:
    rows = table_rows(ev)
    w, h = ev.size
    lines = [
        f"# vet evaluate: {ev.scene}, motion {ev.motion}, {w}x{h}, seed {ev.seed}",
        "",
        "Error in stops, |log2(estimate / truth)| of luminance; dark = pixels exposed the whole "
        "frame by the VET rig, bright = pixels that closed early.",
        "",
        rig_sentence(ev),
        "",
        "| method | all median | all p99 | all RMS | dark median | dark p99 | dark RMS "
        "| bright median | bright p99 | bright RMS | runtime s |",
        "|---|" + "---:|" * 10,
    ]
    for r in rows:
        cells = [_cell(r[f"{reg}_{st}"]) for reg in REGIONS for st in STATS]
        lines.append(f"| {r['method']} | " + " | ".join(cells) + f" | {r['runtime_s']:.1f} |")
    lines += [
        "",
        f"Pixels scored: all {rows[0]['n_all']}, dark {rows[0]['n_dark']}, "
        f"bright {rows[0]['n_bright']} ({BORDER_PX} px from the border excluded, and pixels whose truth is "
        f"at or below {ev.floor:.4g} scene units, where a whole-frame exposure gathers "
        f"{ev.floor_e:.1f} e-, no more signal than noise). "
        f"Simulation took {ev.runtime_s.get('simulate', 0):.1f} s.",
    ]
    empty = [reg for reg in REGIONS if rows[0][f"n_{reg}"] == 0]
    if empty:
        lines.append(f"No pixel is {' or '.join(empty)} in this capture: its columns are '-'.")
    if any(np.isinf(r[f"{reg}_{st}"]) for r in rows for reg in REGIONS for st in STATS):
        lines.append("'inf': the method gave a zero, negative or non-finite value there.")
    lines.append("")
    return "\n".join(lines)


def rig_sentence(ev: Evaluation) -> str:
    """The rig and radiance scale the captures were rendered with, as one sentence."""
    defaults = "vet's default rig (the values `vet simulate --help` lists)"
    if ev.rig_profile != "ideal":
        defaults += f" with the parts of rig profile {ev.rig_profile}"
    if ev.rig_changes:
        rig = f"{defaults} except " + ", ".join(
            f"{k} = {v}" for k, v in sorted(ev.rig_changes.items())
        )
    else:
        rig = defaults
    if ev.reach_subframes is None:
        how = "as given"
    else:
        n = ev.reach_subframes
        how = f"the scene's 99.9th-percentile luminance reaches the threshold in {n:g} subframe"
        how += "" if n == 1 else "s"
    return f"Rig: {rig}. Radiance scale {ev.radiance_scale:.6g} e-/s per scene unit ({how})."


def _cell(value: float) -> str:
    """A table cell: 3 decimals, '-' for a region without pixels, 'inf' as such."""
    return "-" if np.isnan(value) else f"{value:.3f}"


def _figure_png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def chart_bars(
    ev: Evaluation,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Bar heights of :func:`errors_chart`: RMS per region and method (``ev.scores`` order).

    An infinite error (a zero, negative or non-finite estimate) is drawn to ``top``, 10%
    above the largest finite bar, and flagged; a region without pixels is NaN (no bar).
    Returns ``(heights, infinite, top)``.
    """
    names = list(ev.scores)
    rms = {
        reg: np.array([ev.scores[n].get(reg, {}).get("rms", np.nan) for n in names], float)
        for reg in REGIONS
    }
    finite = np.concatenate([v[np.isfinite(v)] for v in rms.values()])
    top = 1.1 * float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    infinite = {reg: np.isinf(v) for reg, v in rms.items()}
    heights = {reg: np.where(infinite[reg], top, v) for reg, v in rms.items()}
    return heights, infinite, top


def errors_chart(ev: Evaluation) -> bytes:
    """Bar chart of the RMS error per method and region, PNG bytes (matplotlib Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = list(ev.scores)
    fig = Figure(figsize=(9, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(len(names))
    heights, infinite, top = chart_bars(ev)
    for i, reg in enumerate(REGIONS):
        bars = ax.bar(x + (i - 1) * 0.27, heights[reg], 0.27, label=reg)
        for b, is_inf in zip(bars, infinite[reg], strict=True):
            if is_inf:
                b.set_hatch("//")
                ax.text(b.get_x() + b.get_width() / 2, top, "inf", ha="center", va="bottom")
    ax.set_ylim(0, top * 1.12)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=20, ha="right")
    ax.set_ylabel("RMS error, stops")
    ax.set_title(f"{Path(ev.scene).name}, {ev.motion}")
    ax.legend()
    fig.tight_layout()
    return _figure_png(fig)


def contact_sheet(ev: Evaluation) -> np.ndarray:
    """All methods and the truth, one log tone mapping with the truth's levels, (H', W', 3)."""
    from .formats.images import captioned
    from .tonemap import tonemap

    lum = ev.truth.mean(axis=2)
    pos = lum[lum > 0]
    white = float(np.percentile(pos, 99.5)) if pos.size else 1.0
    black = max(float(np.percentile(pos, 1.0)) if pos.size else 1e-3, white * 1e-6)
    tiles = [("truth", ev.truth)] + list(ev.images.items())
    out_tiles = []
    for name, rad in tiles:
        d = np.asarray(
            tonemap(rad, operator="log", exposure=0.0, black=black, white=white), np.float32
        )
        if d.ndim == 2:
            d = d[..., None]
        if d.shape[2] == 1:
            d = np.repeat(d, 3, axis=2)
        img = np.ascontiguousarray((np.clip(d, 0, 1) * 255).astype(np.uint8))
        out_tiles.append(captioned(img, name, dark=True))
    cols = 4
    while len(out_tiles) % cols:
        out_tiles.append(np.zeros_like(out_tiles[0]))
    rows = [np.concatenate(out_tiles[i : i + cols], axis=1) for i in range(0, len(out_tiles), cols)]
    return np.concatenate(rows, axis=0)


def motion_picture(ev: Evaluation) -> np.ndarray:
    """Estimated (default deblur) and true motion side by side on one colour-wheel scale
    (the true motion alone when the default deblur was not run)."""
    from .flow import motion_picture as picture

    true = (
        ev.truth_motion
        if ev.truth_motion is not None
        else np.zeros((*ev.truth.shape[:2], 2), np.float32)
    )
    if ev.velocity is None:  # vet-deblur was not among the rows
        return picture([("true", true)])
    return picture([("estimated (vet-deblur)", ev.velocity), ("true", true)])


def write_report(ev: Evaluation, folder: str | Path) -> list[Path]:
    """Write every output of the evaluation into ``folder`` (created), atomically."""
    from .falsecolor import render_exposure_time_map
    from .formats.images import write_display_image

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in (("results.csv", results_csv(ev)), ("results.md", results_markdown(ev))):
        with atomic_output(folder / name) as tmp:
            tmp.write_text(text)
        written.append(folder / name)
    with atomic_output(folder / "errors.png") as tmp:
        tmp.write_bytes(errors_chart(ev))
    written.append(folder / "errors.png")
    write_display_image(folder / "contact_sheet.png", contact_sheet(ev))
    written.append(folder / "contact_sheet.png")
    write_display_image(
        folder / "exposure_time.png", render_exposure_time_map(ev.T, ev.frame_s, ev.subframe_s)
    )
    written.append(folder / "exposure_time.png")
    write_display_image(folder / "motion.png", motion_picture(ev))
    written.append(folder / "motion.png")
    return written
