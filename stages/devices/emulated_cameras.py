"""The emulated rig's cameras: :class:`EmulatedMeasurementCamera` and
:class:`EmulatedVETCamera` render a scene with motion through the same sensor physics as
``vet simulate`` (:mod:`stages.physics`) and the parts of a real rig
(:mod:`stages.optics`); the VET camera integrates through the LCoS state that the
emulated controller *applied*, so what it records depends on the link, as on a real rig.

Both can be shown another still scene (:meth:`EmulatedMeasurementCamera.show_scene`,
:meth:`EmulatedVETCamera.show_scene`: a calibration target, a dimmed flat field), as a
lab puts one in front of a real rig; the measurement camera can run on its subframe clock
without a break (:meth:`EmulatedMeasurementCamera.free_run`), and the VET camera can
expose a window of a frame (:meth:`EmulatedVETCamera.expose_window`), as calibration
records them.
"""

from __future__ import annotations

import numpy as np

from ..errors import DeviceError, InputError
from ..motion import Motion, parse_motion
from ..optics import (
    MeasureGeometry,
    close_times,
    free_running_clock,
    leakage_map,
    pixel_leakage,
    relay_blur,
    slot_transmittance,
    subframe_clock,
    timing_rng,
)
from ..physics import CellMap, SensorNoise, expose, noise_streams
from ..rig import RigParams
from .cameras import Camera, Frame


class _SceneSource:
    """Scene radiance in electrons/s at the sensor, rendered at any time."""

    def __init__(self, radiance: np.ndarray, motion: Motion, scale: float):
        self.radiance = radiance
        self.motion = motion
        self.scale = np.float32(scale)
        self._still = radiance * self.scale if motion.is_still else None

    def rate(self, t: float) -> np.ndarray:
        if self._still is not None:
            return self._still
        return self.motion.render(self.radiance, t) * self.scale


#: Subframes whose pixels a free run renders and then repeats (its clock is what matters).
FREE_RUN_RENDERED = 8
#: Stream (added to the seed) of the trigger clocks of :meth:`EmulatedVETCamera.expose_window`.
WINDOW_CLOCK_STREAM = 0x5E7


def _shown(radiance: np.ndarray | None, source: _SceneSource, own: _SceneSource) -> _SceneSource:
    """The scene source a camera shows: ``radiance`` ((H, W, C) or (H, W, 1) in the rig
    scene's units, still) at the rig scene's scale, or its ``own`` scene for None."""
    if radiance is None:
        return own
    r = np.asarray(radiance, np.float32)
    want = own.radiance.shape
    if r.ndim != 3 or r.shape[:2] != want[:2] or r.shape[2] not in (1, want[2]):
        raise InputError(
            f"scene of shape {r.shape} shown to a camera whose scene is {want}: expected (H, W, C)"
        )
    r = np.ascontiguousarray(np.broadcast_to(r, want))
    return _SceneSource(r, parse_motion("none"), float(source.scale))


class EmulatedMeasurementCamera(Camera):
    """Emulated measurement sensor: subframe ``k`` renders the scene at mid-subframe
    time through the sensor chain with its own seeded stream (same physics and seeding
    rule as ``simulate``, so a perfect link reproduces ``simulate``'s capture).

    With ``realtime`` the whole frame's subframes are rendered when the camera opens
    and then delivered on the real subframe clock (subframe ``k`` at ``(k + 1) tau``
    after the first grab), so the host loop and the throttled LCoS link see real
    timing. ``drop`` lists frame indices to skip, to exercise the capture loop's
    handling of dropped frames. Each frame is stamped with its subframe's start on the
    rig's trigger clock (:func:`stages.optics.subframe_clock`: offset and jitter, s after
    the VET exposure's start), the frames of ``drop_rate`` are never delivered.
    """

    def __init__(
        self,
        radiance: np.ndarray,
        motion: Motion,
        rig: RigParams,
        scale: float,
        seed: int = 0,
        drop: tuple[int, ...] = (),
        realtime: bool = False,
    ):
        super().__init__()
        self.rig = rig
        self.source = _SceneSource(radiance, motion, scale)
        self.streams = noise_streams(seed)[1].spawn(rig.n_subframes + 1)
        # A real rig's measurement camera (stages.optics): its own grid, gain and
        # vignetting; its trigger offset and the frames it drops (drop_rate).
        self.geom = None if rig.ideal_geometry else MeasureGeometry(rig)
        self.starts, rig_drops = subframe_clock(rig, timing_rng(seed))
        self.drop = set(drop) | set(np.flatnonzero(rig_drops).tolist())
        self.seed = seed
        self.realtime = realtime
        self._own = self.source
        self._run: tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]] | None = None
        self._frames: np.ndarray | None = None
        self._t0: float | None = None
        self._k = 0

    def _do_open(self) -> None:
        self._k = 0
        self._t0 = None
        self._run = None
        if self.realtime:
            from concurrent.futures import ThreadPoolExecutor

            k_sub = self.rig.n_subframes
            shape = (*self.rig.measure_shape, self.source.radiance.shape[2])
            self._frames = np.empty((k_sub, *shape), np.int16)  # DN fit: [-black, 4095]
            with ThreadPoolExecutor(max_workers=2) as ex:
                for k, frame in enumerate(ex.map(self.render, range(k_sub))):
                    self._frames[k] = frame

    def start_at(self, t0: float | None) -> None:
        """Pace against a frame start ``t0`` (``time.monotonic``): subframe ``k`` is
        delivered at ``t0 + (k + 1) tau``, its end, as a triggered camera does."""
        self._t0 = t0

    def show_scene(self, radiance: np.ndarray | None) -> None:
        """Image a still ``radiance`` from now ((H, W, C) or (H, W, 1) on the VET grid, in
        the rig scene's units: a calibration target, a dimmed flat field), through the
        camera's own geometry, vignetting, gain and noise; None: the rig's scene again.
        Frames rendered ahead (``realtime``) are dropped: later ones render on demand."""
        self.source = _shown(radiance, self.source, self._own)
        self._frames = None
        if self._run is not None:
            self._run[2].clear()

    def free_run(self, subframes: int) -> None:
        """Run on the subframe clock without a break from now: the next grabs deliver the
        frames of subframes ``0 .. subframes - 1`` of this run that do not drop, each
        with its index and its start on the run's jittered clock
        (:func:`stages.optics.free_running_clock`, seeded by the camera's seed: what
        :func:`stages.calibrate.frame_clock.emulated_timestamps` gives), then frames on
        the nominal clock, none dropped, for as long as the host grabs. The pixels are
        those of the scene's first :data:`FREE_RUN_RENDERED` subframes, repeated."""
        if subframes < 1:
            raise InputError(f"a free run needs one subframe or more, got {subframes}")
        starts, dropped = free_running_clock(self.rig, int(subframes), self.seed)
        self.open()
        self._k = 0
        self._run = (starts, dropped, {})

    def _free_run_frame(self) -> Frame:
        starts, dropped, pixels = self._run
        while self._k < dropped.size and dropped[self._k]:
            self._k += 1
        k = self._k
        self._k += 1
        rig = self.rig
        stamp = starts[k] if k < starts.size else rig.trigger_offset_s + k * rig.subframe_s
        j = k % FREE_RUN_RENDERED
        if j not in pixels:
            pixels[j] = self.render(j)
        return Frame(pixels[j], k, float(stamp))

    def render(self, k: int) -> np.ndarray:
        rig = self.rig
        tau = rig.subframe_s
        lam = self.source.rate((k + 0.5) * tau) * np.float32(tau * rig.measure_fraction)
        rng = np.random.default_rng(self.streams[min(k, len(self.streams) - 1)])
        if self.geom is not None:
            return self.geom.expose(lam, np.float32(rig.dark_current_e_s * tau), rng)
        lam += np.float32(rig.dark_current_e_s * tau)
        return expose(lam, rig, rng)

    def _do_grab(self) -> Frame:
        import time

        if self._run is not None:
            return self._free_run_frame()
        while self._k in self.drop:
            self._k += 1
        k = self._k
        if k >= self.rig.n_subframes:
            raise DeviceError("measurement camera: frame is over (no more subframes)")
        self._k += 1
        stamp = float(self.starts[k])
        if self._frames is None:
            return Frame(self.render(k), k, stamp)
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now - k * self.rig.subframe_s
        due = self._t0 + (k + 1) * self.rig.subframe_s
        if due > now:
            time.sleep(due - now)
        return Frame(self._frames[k], k, stamp)  # int16 DN, as a sensor delivers

    def _do_close(self) -> None:
        self._frames = None
        self._run = None


class EmulatedVETCamera(Camera):
    """Emulated VET sensor behind the LCoS.

    :meth:`expose_frame` integrates one frame given, per LCoS cell, the subframe index
    from which the cell was closed as the controller applied it; :meth:`expose_pattern`
    images a static LCoS mask (calibration); :meth:`expose_window` exposes the start of
    a frame (calibration's switching series). ``true_homography`` may differ from the
    rig's nominal one, which is what calibration must discover.
    """

    def __init__(
        self,
        radiance: np.ndarray,
        motion: Motion,
        rig: RigParams,
        scale: float,
        seed: int = 0,
        true_homography: np.ndarray | None = None,
    ):
        super().__init__()
        self.rig = rig
        self.source = _SceneSource(radiance, motion, scale)
        h, w = radiance.shape[:2]
        hom = np.asarray(
            rig.homography if true_homography is None else true_homography, dtype=float
        )
        self.cellmap = CellMap(hom, rig.lcos_cells, (h, w))
        self.rng = np.random.default_rng(noise_streams(seed)[0])
        self._frames = 0
        self._own = self.source
        # A real rig's LCoS (stages.optics): per-cell leakage, relay blur, switching on
        # the measurement camera's trigger clock (the same seeded clock as its camera's).
        self.real = not rig.ideal_shutter
        self.eps = pixel_leakage(rig, self.cellmap).astype(np.float64)
        self.starts, _ = subframe_clock(rig, timing_rng(seed))
        self._window_clocks = timing_rng(seed + WINDOW_CLOCK_STREAM)

    def _do_open(self) -> None:
        self._frames = 0

    def _do_grab(self) -> Frame:
        raise DeviceError("the VET camera delivers frames through expose_frame()")

    def show_scene(self, radiance: np.ndarray | None) -> None:
        """Image a still ``radiance`` from now ((H, W, C) or (H, W, 1), in the rig scene's
        units: a calibration target, a dimmed flat field); None: the rig's scene again."""
        self.source = _shown(radiance, self.source, self._own)

    def _slot(self, t_close: np.ndarray, a: float, b: float) -> np.ndarray:
        """(H, W, 1) mean transmittance over ``[a, b]`` (s) of pixels whose cells were
        applied closed at ``t_close`` ((H, W) s, inf: open): switching, leakage, relay blur."""
        t = slot_transmittance(t_close, a, b, self.eps, self.rig)
        return relay_blur(t, self.rig.relay_blur_px)[..., None]

    def transmission(self, open_cells: np.ndarray) -> np.ndarray:
        """(H, W, 1) transmittance for a per-cell open mask (length ``n_cells``)."""
        if self.real:
            leak = leakage_map(self.rig).ravel()
            per_cell = np.append(np.where(open_cells, np.float32(1.0), leak), np.float32(1.0))
            trans = self.cellmap.to_pixels(per_cell.astype(np.float32))
            return relay_blur(trans, self.rig.relay_blur_px)[..., None]
        per_cell = np.append(np.where(open_cells, 1.0, self.rig.leakage), 1.0).astype(np.float32)
        return self.cellmap.to_pixels(per_cell)[..., None]

    def expose_frame(self, close_subframe: np.ndarray) -> Frame:
        """Integrate a frame; ``close_subframe[c]`` (length ``n_cells``; < 0 or beyond
        the frame = never closed) is when cell ``c`` closed, in subframes."""
        rig = self.rig
        k_sub, tau = rig.n_subframes, rig.subframe_s
        cs = np.where(close_subframe < 0, np.iinfo(np.int32).max, close_subframe)
        per_pixel = self.cellmap.to_pixels(np.append(cs, np.iinfo(np.int32).max))[..., None]
        eps = np.float32(rig.leakage)
        acc = np.zeros(self.source.radiance.shape, np.float32)
        t_close = None
        if self.real:
            t_close = self.cellmap.to_pixels(
                np.append(close_times(close_subframe, self.starts), np.inf)
            )

        def trans_of(j: int, a: float, b: float) -> np.ndarray:
            if t_close is None:
                return np.where(per_pixel > j, np.float32(1.0), eps)
            return self._slot(t_close, a, b)

        for j in range(k_sub):
            trans = trans_of(j, j * tau, (j + 1) * tau)
            acc += self.source.rate((j + 0.5) * tau) * np.float32(tau) * trans
        tail = rig.frame_s - k_sub * tau
        if tail > 1e-9:
            trans = trans_of(k_sub, k_sub * tau, rig.frame_s)
            acc += self.source.rate(k_sub * tau + tail / 2) * np.float32(tail) * trans
        acc += np.float32(rig.dark_current_e_s * rig.frame_s)
        # A frame's noise is drawn as simulate draws the noise its methods share.
        noise = SensorNoise(acc.shape, self.rng)
        frame = Frame(expose(acc, rig, noise), self._frames, 0.0)
        self._frames += 1
        return frame

    def expose_pattern(
        self, open_cells: np.ndarray | None, exposure_s: float, light: bool = True
    ) -> np.ndarray:
        """A still exposure of ``exposure_s`` through a static mask (None: all open);
        ``light=False`` is a dark frame (lens capped)."""
        rig = self.rig
        lam = np.zeros(self.source.radiance.shape, np.float32)
        if light:
            rate = self.source.rate(0.0)
            trans = 1.0 if open_cells is None else self.transmission(open_cells)
            lam += rate * np.float32(exposure_s) * trans
        lam += np.float32(rig.dark_current_e_s * exposure_s)
        return expose(lam, rig, self.rng)

    def expose_window(self, close_subframe: np.ndarray, window_s: float) -> np.ndarray:
        """The first ``window_s`` seconds of a frame (the camera's exposure set to that
        window, started by the frame's trigger) of a still scene (a moving one at
        mid-window), through cells applied closed at ``close_subframe`` (per cell, length
        ``n_cells``, as :meth:`expose_frame`; < 0: never) on a trigger clock drawn anew
        for each exposure (:func:`stages.optics.subframe_clock`: offset, jitter), with
        switching, leakage and relay blur: (H, W, C) float32 DN, dark current included."""
        rig = self.rig
        w = float(window_s)
        if not w > 0:
            raise InputError(f"exposure window must be positive, got {window_s}")
        starts, _ = subframe_clock(rig, self._window_clocks)
        t_close = self.cellmap.to_pixels(np.append(close_times(close_subframe, starts), np.inf))
        lam = self.source.rate(w / 2) * np.float32(w) * self._slot(t_close, 0.0, w)
        lam += np.float32(rig.dark_current_e_s * w)
        return expose(lam, rig, self.rng)
