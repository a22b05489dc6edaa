"""Render what a VET rig records from an HDR scene with known motion.

One pass over the K measuring subframes renders every requested method from the same
scene, motion and noise, so they can be compared on equal terms: the methods' images are
exposed with one shared noise realisation (:class:`stages.physics.SensorNoise`), so a
pixel that two methods expose alike records the same value in both, and differences
between methods come from the methods, not from independent noise draws.

``vet``
    The VET rig: measuring subframes with their own noise, host threshold on the LCoS
    cell grid (a cell closes on its brightest pixel), closure after the latency, leakage
    through closed cells, dark current, shot and read noise, full well, ADC.
``long``
    A standard exposure of the whole frame, no LCoS (saturates, blurs).
``short``
    A standard exposure of one subframe (noisy in the dark).
``adaptive-attenuation``
    Mannami et al. 2007: a whole-frame exposure through an LCoS whose per-cell
    transmittance is set from the previous frame's true radiance (so that the brightest
    pixel of each cell would reach the threshold in a frame), quantised to 8 bits and
    floored at the leakage. HDR = I / (a Tf).

Within one subframe the scene is sampled at the subframe's mid-time (motion inside a
7.58 ms subframe is 0.23 px at 30 px/s, below what the model needs to resolve).

References
----------
S. Uda, F. Sakaue, J. Sato, "Variable exposure time imaging for obtaining unblurred HDR
images", IPSJ Trans. Computer Vision and Applications 8, 2016.
H. Mannami, R. Sagawa, Y. Mukaigawa, T. Echigo, Y. Yagi, "High dynamic range camera
using reflective liquid crystal", ICCV 2007.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .formats.capture import Capture, measure_bin_edges, provenance_entry
from .motion import Motion, TrajectoryMotion, trajectory_times
from .optics import (
    MeasureGeometry,
    close_times,
    pixel_leakage,
    relay_blur,
    slot_transmittance,
    subframe_clock,
    timing_rng,
)
from .physics import (
    CellMap,
    ClosureController,
    SensorNoise,
    brightest_channel,
    expose,
    noise_streams,
    radiance_scale,
)
from .rig import RigParams
from .scenes import Scene, luminance

METHODS = ("vet", "long", "short", "adaptive-attenuation")


def simulate(
    scene: Scene,
    motion: Motion,
    rig: RigParams,
    seed: int = 0,
    methods: Sequence[str] = ("vet",),
    measure_bins: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    scale: float | None = None,
    reach_subframes: float = 1.0,
) -> dict[str, Capture]:
    """Render captures of ``scene`` moving by ``motion`` as recorded by each method.

    Parameters
    ----------
    scene : Scene
        Linear radiance (H, W, C) in scene units; the rig's sensor takes its size.
    motion : Motion
        How the scene moves during the frame.
    rig : RigParams
        Rig physics; ``sensor_size`` must equal the scene's (W, H).
    seed : int
        Seeds all noise: one stream for the measuring subframes, one for the noise
        realisation that every method's image shares. A method's capture is the same
        whichever other methods are rendered beside it.
    methods : sequence of str
        Any of :data:`METHODS`.
    measure_bins : int, optional
        Time bins of measuring images stored in the VET capture (0: none); None (the
        default) keeps every subframe, as whole DN in int16 (:func:`measure_store`).
    progress : callable, optional
        Called as ``progress(done, total)`` after each subframe.
    scale : float, optional
        Electrons per second per scene unit; default from the scene's 99.9th-percentile
        luminance (DESIGN.md §2).
    reach_subframes : float
        Without ``scale``: the measuring subframes the scene's 99.9th-percentile
        luminance takes to reach the threshold (1 in DESIGN.md §2; 8 is a scene three
        stops dimmer).

    Returns
    -------
    dict mapping method name to :class:`~stages.formats.capture.Capture`.
    """
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    radiance = scene.radiance
    h, w, nch = radiance.shape
    if tuple(rig.sensor_size) != (w, h):
        raise ValueError(f"rig sensor {rig.sensor_size} does not match the scene ({w}, {h})")
    if scale is None:
        p999 = float(np.percentile(luminance(radiance), 99.9))
        scale = radiance_scale(p999, rig, reach_subframes)
    k_sub = rig.n_subframes
    tau, tf = rig.subframe_s, rig.frame_s
    tail_s = tf - k_sub * tau
    dark = rig.dark_current_e_s
    exposure_stream, subframe_stream = noise_streams(seed)
    # First, so that a motion that does not fit the scene fails before the render.
    truth_motion = motion.velocity((h, w))

    want = set(methods)
    shape = (h, w, nch)
    # The methods' images share one noise realisation (common random numbers).
    noise = SensorNoise(shape, np.random.default_rng(exposure_stream))
    cellmap = CellMap.for_rig(rig, (h, w)) if want & {"vet", "adaptive-attenuation"} else None
    real = RealRig(rig, cellmap, seed) if "vet" in want and not RealRig.ideal(rig) else None
    ctrl = None
    if "vet" in want:
        ctrl = real.controller() if real is not None else ClosureController(rig, cellmap)
    vet_e = np.zeros(shape, np.float32) if "vet" in want else None
    full_e = np.zeros(shape, np.float32) if want & {"long", "adaptive-attenuation"} else None
    short_e = None
    meas_shape = (*rig.measure_shape, nch)
    edges, measure = measure_store(k_sub, measure_bins, meas_shape) if ctrl else (None, None)
    bin_of = (
        np.searchsorted(edges, np.arange(k_sub), side="right") - 1 if edges is not None else None
    )

    still = motion.is_still
    rate_still = radiance * np.float32(scale) if still else None
    trans = np.ones((h, w, 1), np.float32)
    eps = np.float32(rig.leakage)
    meas_gain = np.float32(rig.measure_fraction)
    dark_sub = np.float32(dark * tau)
    # One seeded stream per measuring subframe: frames can be rendered and exposed on
    # worker threads (numpy and OpenCV release the GIL) in any order, same result.
    sub_streams = subframe_stream.spawn(k_sub)

    def rate_at(t: float) -> np.ndarray:
        return rate_still if still else motion.render(radiance, t) * np.float32(scale)

    def render_subframe(j: int) -> tuple[np.ndarray, np.ndarray | None]:
        step_e = rate_at((j + 0.5) * tau) * np.float32(tau)
        frame_dn = None
        if ctrl is not None:
            rng_j = np.random.default_rng(sub_streams[j])
            if real is None:
                frame_dn = expose(step_e * meas_gain + dark_sub, rig, rng_j)
            else:
                frame_dn = real.measure(step_e * meas_gain, dark_sub, rng_j)
        return step_e, frame_dn

    for j, (step_e, frame_dn) in enumerate(_pipelined(render_subframe, k_sub)):
        if ctrl is not None:
            if real is not None:
                trans[..., 0] = real.transmittance(ctrl, j * tau, (j + 1) * tau)
            elif j > 0:
                trans[..., 0] = np.where(ctrl.open_pixels(j), np.float32(1.0), eps)
            vet_e += step_e * trans
            if real is None or not real.dropped[j]:
                if measure is not None:
                    add_subframe(measure, bin_of[j], frame_dn)
                ctrl.step(frame_dn, j)
        if full_e is not None:
            full_e += step_e
        if j == 0 and "short" in want:
            short_e = step_e.copy()
        if progress:
            progress(j + 1, k_sub)
    if tail_s > 1e-9:
        rate = rate_at(k_sub * tau + tail_s / 2)
        if ctrl is not None:
            if real is not None:
                trans[..., 0] = real.transmittance(ctrl, k_sub * tau, tf)
            else:
                trans[..., 0] = np.where(ctrl.open_pixels(k_sub), np.float32(1.0), eps)
            vet_e += rate * np.float32(tail_s) * trans
        if full_e is not None:
            full_e += rate * np.float32(tail_s)

    base_meta: dict[str, Any] = {
        "radiance_scale": float(scale),
        "scene": scene.source,
        "motion": motion.spec,
        "seed": int(seed),
    }
    truth = radiance.astype(np.float32)
    common = dict(channels=list(scene.channels), rig=rig, truth=truth, truth_motion=truth_motion)
    if isinstance(motion, TrajectoryMotion):
        paths = motion.truth((h, w), trajectory_times(tf, tau, k_sub))
        common["truth_layers"] = paths.labels
        base_meta["truth_trajectory"] = paths.meta()

    def meta_for(method: str, integration_s: float, leakage_applies: bool) -> dict[str, Any]:
        m = dict(
            base_meta, method=method, integration_s=integration_s, leakage_applies=leakage_applies
        )
        m["provenance"] = [
            provenance_entry(
                "simulate", [scene.source], method=method, motion=motion.spec, seed=int(seed)
            )
        ]
        return m

    out: dict[str, Capture] = {}
    if ctrl is not None:
        img = expose(vet_e + np.float32(dark * tf), rig, noise)
        mt = None
        counts = None
        if measure is not None:
            off = rig.trigger_offset_s
            mt = np.stack([edges[:-1] * tau + off, edges[1:] * tau + off], axis=1)
            counts = np.diff(edges)
        T = ctrl.exposure_time() if real is None else real.exposure_time(ctrl)
        meta = meta_for("vet", tf, True)
        if real is not None and real.dropped.any():
            dropped = np.flatnonzero(real.dropped)
            meta["measure_dropped"] = dropped.tolist()
            if measure is not None:
                lost = np.bincount(bin_of[dropped], minlength=len(counts))
                keep = counts > lost
                counts = (counts - lost)[keep]
                measure, mt = measure[keep], mt[keep]
        cap = Capture(I=img, T=T, measure=measure, measure_times=mt, meta=meta, **common)
        if measure is not None:
            cap.meta["measure_subframes"] = counts.tolist()
        out["vet"] = cap
    if "long" in want:
        img = expose(full_e + np.float32(dark * tf), rig, noise)
        out["long"] = Capture(
            I=img, T=np.full((h, w), tf, np.float32), meta=meta_for("long", tf, False), **common
        )
    if "short" in want:
        img = expose(short_e + np.float32(dark * tau), rig, noise)
        out["short"] = Capture(
            I=img, T=np.full((h, w), tau, np.float32), meta=meta_for("short", tau, False), **common
        )
    if "adaptive-attenuation" in want:
        a = attenuation_from_previous_frame(radiance, motion, rig, scale, cellmap)
        img = expose(full_e * a[..., None] + np.float32(dark * tf), rig, noise)
        out["adaptive-attenuation"] = Capture(
            I=img,
            T=np.full((h, w), tf, np.float32),
            transmittance=a,
            meta=meta_for("adaptive-attenuation", tf, False),
            **common,
        )
    return {m: out[m] for m in methods}


def measure_store(
    n_subframes: int, measure_bins: int | None, shape: tuple[int, ...]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Bin edges and the zeroed array the measuring images gather in (None, None for
    ``measure_bins`` 0): ``measure_bins`` None keeps every subframe, (K, *shape) int16
    (a subframe's whole DN, ``-black_level_dn .. max_dn``, fit exactly); N bins sum
    subframes in float32."""
    if measure_bins == 0:
        return None, None
    if measure_bins is None:
        measure_bins = n_subframes
    edges = measure_bin_edges(n_subframes, measure_bins)
    one_each = bool(np.all(np.diff(edges) == 1))
    dtype = np.int16 if one_each else np.float32
    return edges, np.zeros((len(edges) - 1, *shape), dtype)


def add_subframe(measure: np.ndarray, b: int, frame_dn: np.ndarray) -> None:
    """Gather one subframe (whole DN, float) into measuring image ``b``."""
    if measure.dtype == np.int16:
        np.rint(frame_dn, out=measure[b], casting="unsafe")
    else:
        measure[b] += frame_dn


def attenuation_from_previous_frame(
    radiance: np.ndarray,
    motion: Motion,
    rig: RigParams,
    scale: float,
    cellmap: CellMap,
    samples: int = 8,
) -> np.ndarray:
    """Per-pixel LCoS transmittance of adaptive attenuation, from the previous frame.

    The previous frame spans ``[-Tf, 0)``; its mean rate per pixel (brightest channel)
    sets each cell's transmittance so that its brightest pixel would collect the
    threshold in a frame, quantised to 8 bits and floored at the leakage.
    """
    tf = rig.frame_s
    prev = np.zeros(radiance.shape[:2], np.float32)
    for i in range(samples):
        t = -tf + (i + 0.5) * tf / samples
        prev += brightest_channel(motion.render(radiance, t))
    rate = prev / samples * np.float32(scale)
    want = np.where(rate > 0, rig.threshold_e / np.maximum(rate * tf, 1e-30), 1.0)
    cell_a = cellmap.cell_min(want.astype(np.float32))
    cell_a = np.clip(np.where(np.isfinite(cell_a), cell_a, 1.0), 0.0, 1.0)
    cell_a = np.round(cell_a * 255.0) / 255.0
    cell_a = np.maximum(cell_a, rig.leakage)
    return cellmap.to_pixels(cell_a.astype(np.float32))


class RealRig:
    """The parts of a real rig (:mod:`stages.optics`) as a capture renders them: the
    measurement camera's own grid, gain and vignetting, the host thresholding each cell on
    the measuring pixels that image it, the VET sensor's blurred, leaky, slowly switching
    LCoS, and the measurement camera's trigger clock (offset, jitter, dropped frames).
    ``simulate`` and the emulated rig share it."""

    def __init__(self, rig: RigParams, cellmap: CellMap, seed: int):
        self.rig = rig
        self.cellmap = cellmap
        self.geom = None if rig.ideal_geometry else MeasureGeometry(rig)
        self.eps = pixel_leakage(rig, cellmap).astype(np.float64)
        self.starts, self.dropped = subframe_clock(rig, timing_rng(seed))

    @staticmethod
    def ideal(rig: RigParams) -> bool:
        return rig.ideal_geometry and rig.ideal_shutter and rig.drop_rate == 0

    def controller(self) -> ClosureController:
        if self.geom is None:
            return ClosureController(self.rig, self.cellmap)
        cm, starts, cells = self.geom.host_cells(self.cellmap)
        return ClosureController(self.rig, cm, extras=(starts, cells), dn_scale=self.geom.flat)

    def measure(
        self, light_e: np.ndarray, dark_e: np.float32, rng: np.random.Generator
    ) -> np.ndarray:
        """One measuring subframe in DN on the measurement grid from the light (e-) the
        ideal measurement sensor would receive on the VET grid."""
        if self.geom is None:
            return expose(light_e + dark_e, self.rig, rng)
        return self.geom.expose(light_e, dark_e, rng)

    def transmittance(self, ctrl: ClosureController, a: float, b: float) -> np.ndarray:
        """Mean transmittance over ``[a, b]`` s of each VET pixel, (H, W) float32."""
        t = self.cellmap.to_pixels(close_times(ctrl.close_subframe, self.starts))
        return relay_blur(slot_transmittance(t, a, b, self.eps, self.rig), self.rig.relay_blur_px)

    def exposure_time(self, ctrl: ClosureController) -> np.ndarray:
        """T as the rig records it: the subframe at which the device applied the closure,
        on the nominal trigger clock (offset known, jitter not), (H, W) float32."""
        rig = self.rig
        c = ctrl.close_subframe.astype(np.float64)
        t = np.minimum(c * rig.subframe_s + rig.trigger_offset_s, rig.frame_s)
        return self.cellmap.to_pixels(t.astype(np.float32))


def _pipelined(fn: Callable[[int], Any], n: int, workers: int = 2, depth: int = 4):
    """Yield ``fn(0) .. fn(n-1)`` in order, computing up to ``depth`` ahead on threads."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=workers) as ex:
        pending = [ex.submit(fn, j) for j in range(min(depth, n))]
        for j in range(n):
            result = pending[j].result()
            pending[j] = None  # type: ignore[call-overload]
            if j + depth < n:
                pending.append(ex.submit(fn, j + depth))
            yield result
