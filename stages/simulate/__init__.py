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
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..formats.capture import Capture, provenance_entry
from ..motion import Motion, TrajectoryMotion, trajectory_times
from ..optics import (
    MeasureGeometry,
    close_times,
    pixel_leakage,
    relay_blur,
    slot_transmittance,
    subframe_clock,
    timing_rng,
)
from ..physics import (
    CellMap,
    ClosureController,
    SensorNoise,
    brightest_channel,
    expose,
    noise_streams,
    radiance_scale,
)
from ..rig import RigParams
from ..scenes import Scene, luminance
from .bins import MeasureBins, add_subframe, measure_store

METHODS = ("vet", "long", "short", "adaptive-attenuation")

__all__ = ["METHODS", "Radiance", "RealRig", "add_subframe", "measure_store", "simulate"]


@dataclass(frozen=True)
class Radiance:
    """How bright a scene is at the sensor: ``scale`` electrons per second per scene
    unit; without it, the scene's 99.9th-percentile luminance reaches the threshold in
    ``reach_subframes`` measuring subframes (1 in DESIGN.md §2; 8 is a scene three stops
    dimmer)."""

    scale: float | None = None
    reach_subframes: float = 1.0

    def electrons_per_unit(self, radiance: np.ndarray, rig: RigParams) -> float:
        """Electrons per second per scene unit for the scene ``radiance`` (H, W, C)."""
        if self.scale is not None:
            return float(self.scale)
        p999 = float(np.percentile(luminance(radiance), 99.9))
        return float(radiance_scale(p999, rig, self.reach_subframes))


def simulate(
    scene: Scene,
    motion: Motion,
    rig: RigParams,
    seed: int = 0,
    methods: Sequence[str] = ("vet",),
    measure_bins: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    radiance: Radiance = Radiance(),
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
    radiance : Radiance
        The scene's brightness at the sensor (default: DESIGN.md §2's).

    Returns
    -------
    dict mapping method name to :class:`~stages.formats.capture.Capture`.
    """
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    h, w = scene.radiance.shape[:2]
    if tuple(rig.sensor_size) != (w, h):
        raise ValueError(f"rig sensor {rig.sensor_size} does not match the scene ({w}, {h})")
    scale = radiance.electrons_per_unit(scene.radiance, rig)
    # First, so that a motion that does not fit the scene fails before the render.
    truth_motion = motion.velocity((h, w))
    frame = FrameRender(scene.radiance, motion, rig, seed, set(methods), measure_bins, scale)
    frame.run(progress)
    out = frame.captures(Provenance(scene, motion, seed, truth_motion))
    return {m: out[m] for m in methods}


@dataclass(frozen=True)
class Provenance:
    """What every capture of one :func:`simulate` records about its making."""

    scene: Scene
    motion: Motion
    seed: int
    truth_motion: np.ndarray

    def common(self, rig: RigParams, scale: float) -> tuple[dict[str, Any], dict[str, Any]]:
        """``(capture fields, metadata)`` every method's capture shares: the truth at
        t = 0 (radiance, velocity, and the paths of a motion along paths)."""
        meta: dict[str, Any] = {
            "radiance_scale": float(scale),
            "scene": self.scene.source,
            "motion": self.motion.spec,
            "seed": int(self.seed),
        }
        fields: dict[str, Any] = dict(
            channels=list(self.scene.channels),
            rig=rig,
            truth=self.scene.radiance.astype(np.float32),
            truth_motion=self.truth_motion,
        )
        if isinstance(self.motion, TrajectoryMotion):
            times = trajectory_times(rig.frame_s, rig.subframe_s, rig.n_subframes)
            paths = self.motion.truth(self.scene.radiance.shape[:2], times)
            fields["truth_layers"] = paths.labels
            meta["truth_trajectory"] = paths.meta()
        return fields, meta

    def meta(self, base: dict[str, Any], method: str, integration_s: float, leaky: bool):
        """A method's capture metadata on top of ``base``, with its provenance."""
        m = dict(base, method=method, integration_s=integration_s, leakage_applies=leaky)
        step = provenance_entry(
            "simulate",
            [self.scene.source],
            method=method,
            motion=self.motion.spec,
            seed=int(self.seed),
        )
        m["provenance"] = [step]
        return m


class FrameRender:
    """One frame's exposures as its subframes are rendered: the VET sensor behind the
    LCoS with the closure loop and the measuring images (:class:`MeasureBins`), a
    whole-frame exposure (long, adaptive attenuation), the first subframe (short). The
    methods' images share one noise realisation (common random numbers)."""

    def __init__(
        self,
        radiance: np.ndarray,
        motion: Motion,
        rig: RigParams,
        seed: int,
        want: set[str],
        measure_bins: int | None,
        scale: float,
    ):
        h, w, nch = radiance.shape
        self.radiance, self.motion, self.rig, self.want = radiance, motion, rig, want
        self.scale = scale
        exposure_stream, subframe_stream = noise_streams(seed)
        self.noise = SensorNoise(radiance.shape, np.random.default_rng(exposure_stream))
        lcos = want & {"vet", "adaptive-attenuation"}
        self.cellmap = CellMap.for_rig(rig, (h, w)) if lcos else None
        self.real = (
            RealRig(rig, self.cellmap, seed) if "vet" in want and not RealRig.ideal(rig) else None
        )
        self.ctrl = None
        if "vet" in want:
            self.ctrl = (
                self.real.controller() if self.real else ClosureController(rig, self.cellmap)
            )
        self.vet_e = np.zeros(radiance.shape, np.float32) if "vet" in want else None
        full = want & {"long", "adaptive-attenuation"}
        self.full_e = np.zeros(radiance.shape, np.float32) if full else None
        self.short_e = None
        bins = measure_bins if self.ctrl is not None else 0
        self.bins = MeasureBins(rig.n_subframes, bins, (*rig.measure_shape, nch))
        self.rate_still = radiance * np.float32(scale) if motion.is_still else None
        self.trans = np.ones((h, w, 1), np.float32)
        # One seeded stream per measuring subframe: frames can be rendered and exposed on
        # worker threads (numpy and OpenCV release the GIL) in any order, same result.
        self.sub_streams = subframe_stream.spawn(rig.n_subframes)

    def rate_at(self, t: float) -> np.ndarray:
        """Electrons per second at the VET sensor at time ``t``, (H, W, C) float32."""
        if self.rate_still is not None:
            return self.rate_still
        return self.motion.render(self.radiance, t) * np.float32(self.scale)

    def render_subframe(self, j: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Subframe ``j``'s light at the VET sensor (e-) and its measuring image (DN)."""
        rig = self.rig
        tau = rig.subframe_s
        step_e = self.rate_at((j + 0.5) * tau) * np.float32(tau)
        frame_dn = None
        if self.ctrl is not None:
            rng_j = np.random.default_rng(self.sub_streams[j])
            dark_sub = np.float32(rig.dark_current_e_s * tau)
            light = step_e * np.float32(rig.measure_fraction)
            if self.real is None:
                frame_dn = expose(light + dark_sub, rig, rng_j)
            else:
                frame_dn = self.real.measure(light, dark_sub, rng_j)
        return step_e, frame_dn

    def add(self, j: int, step_e: np.ndarray, frame_dn: np.ndarray | None) -> None:
        """Subframe ``j`` into every exposure; its measuring image to the closure loop."""
        tau = self.rig.subframe_s
        ctrl, real = self.ctrl, self.real
        if ctrl is not None:
            if real is not None:
                self.trans[..., 0] = real.transmittance(ctrl, j * tau, (j + 1) * tau)
            elif j > 0:
                open_ = ctrl.open_pixels(j)
                self.trans[..., 0] = np.where(open_, np.float32(1.0), np.float32(self.rig.leakage))
            self.vet_e += step_e * self.trans
            if real is None or not real.dropped[j]:
                self.bins.add(j, frame_dn)
                ctrl.step(frame_dn, j)
        if self.full_e is not None:
            self.full_e += step_e
        if j == 0 and "short" in self.want:
            self.short_e = step_e.copy()

    def run(self, progress: Callable[[int, int], None] | None) -> None:
        """Every subframe (rendered ahead on threads), then the frame's tail."""
        rig = self.rig
        k_sub = rig.n_subframes
        for j, (step_e, frame_dn) in enumerate(_pipelined(self.render_subframe, k_sub)):
            self.add(j, step_e, frame_dn)
            if progress:
                progress(j + 1, k_sub)
        tail_s = rig.frame_s - k_sub * rig.subframe_s
        if tail_s <= 1e-9:
            return
        rate = self.rate_at(k_sub * rig.subframe_s + tail_s / 2)
        if self.ctrl is not None:
            if self.real is not None:
                self.trans[..., 0] = self.real.transmittance(
                    self.ctrl, k_sub * rig.subframe_s, rig.frame_s
                )
            else:
                open_ = self.ctrl.open_pixels(k_sub)
                self.trans[..., 0] = np.where(open_, np.float32(1.0), np.float32(rig.leakage))
            self.vet_e += rate * np.float32(tail_s) * self.trans
        if self.full_e is not None:
            self.full_e += rate * np.float32(tail_s)

    def captures(self, made: Provenance) -> dict[str, Capture]:
        """Every method's capture of the frame."""
        rig = self.rig
        tf, tau, dark = rig.frame_s, rig.subframe_s, rig.dark_current_e_s
        common, base = made.common(rig, self.scale)
        h, w = self.radiance.shape[:2]
        out: dict[str, Capture] = {}
        if self.ctrl is not None:
            out["vet"] = self.vet_capture(made, common, base)
        if "long" in self.want:
            img = expose(self.full_e + np.float32(dark * tf), rig, self.noise)
            T = np.full((h, w), tf, np.float32)
            out["long"] = Capture(I=img, T=T, meta=made.meta(base, "long", tf, False), **common)
        if "short" in self.want:
            img = expose(self.short_e + np.float32(dark * tau), rig, self.noise)
            T = np.full((h, w), tau, np.float32)
            out["short"] = Capture(I=img, T=T, meta=made.meta(base, "short", tau, False), **common)
        if "adaptive-attenuation" in self.want:
            a = attenuation_from_previous_frame(
                self.radiance, self.motion, rig, self.scale, self.cellmap
            )
            img = expose(self.full_e * a[..., None] + np.float32(dark * tf), rig, self.noise)
            out["adaptive-attenuation"] = Capture(
                I=img,
                T=np.full((h, w), tf, np.float32),
                transmittance=a,
                meta=made.meta(base, "adaptive-attenuation", tf, False),
                **common,
            )
        return out

    def vet_capture(self, made: Provenance, common: dict, base: dict) -> Capture:
        """The VET capture: I, T as the rig records it, the measuring images kept."""
        rig, real = self.rig, self.real
        img = expose(self.vet_e + np.float32(rig.dark_current_e_s * rig.frame_s), rig, self.noise)
        T = self.ctrl.exposure_time() if real is None else real.exposure_time(self.ctrl)
        meta = made.meta(base, "vet", rig.frame_s, True)
        dropped = None
        if real is not None and real.dropped.any():
            dropped = np.flatnonzero(real.dropped)
            meta["measure_dropped"] = dropped.tolist()
        measure, times, counts = self.bins.images(rig.subframe_s, rig.trigger_offset_s, dropped)
        if measure is not None:
            meta["measure_subframes"] = counts.tolist()
        return Capture(I=img, T=T, measure=measure, measure_times=times, meta=meta, **common)


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
