"""Capture files: what a VET rig (real or simulated) records in one frame.

Layers (see :mod:`stages.formats.layered` for the container):

=================  ===========  =====================================================
layer              channels     meaning
=================  ===========  =====================================================
``I``              Y or R,G,B   variable exposure image, DN
``T``              Y            exposure time image: when each pixel's LCoS cell
                                closed as *applied by the device*, seconds (frame
                                length where it never closed)
``A``              Y            optional fixed transmittance (adaptive attenuation)
``M00`` ...        Y or R,G,B   optional measuring images: each is the sum of the
                                measuring subframes in one time bin, DN; bin times
                                in ``meta["measure_times"]``; two digits at least
                                (``M100`` follows ``M99``); of the measurement
                                camera's size (``rig.measure_size``), which may differ
                                from the VET sensor's: then a second part of an EXR
``truth``          Y or R,G,B   optional ground truth: scene radiance at t = 0, in
                                scene units (simulated captures)
``truth_motion``   u, v         optional true image velocity at t = 0, pixels/s
``truth_layers``   Y            optional true layer of each pixel at t = 0 (0, 1, ...)
                                for a motion along paths: ``meta["truth_trajectory"]``
                                holds ``times`` (M,) s and ``disp`` (layers, M, 2) px,
                                each layer's displacement from t = 0; for layers that
                                turn, ``anchor`` (layers, 2) and ``linear`` (layers,
                                M, 2, 2) too (:class:`TruthPaths`); ``front`` the
                                layers front to back
=================  ===========  =====================================================

Metadata: ``kind = "capture"``, ``rig`` (:class:`~stages.rig.RigParams`),
``method`` (``vet``, ``long``, ``short``, ``adaptive-attenuation``),
``radiance_scale`` (electrons per second per scene unit, simulated captures only),
``measure_times``, ``motion``, ``scene``, ``seed`` and ``provenance``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..cluster import in_order
from ..errors import FormatError, InputError
from ..rig import RigParams
from .container import stack_of
from .layered import Layered, read_layered, write_layered

CAPTURE_FILENAMES = ("capture.exr", "capture.npz")


def provenance_entry(step: str, inputs: list[str] | None = None, **params: Any) -> dict[str, Any]:
    """One link of the provenance chain carried by every file."""
    return {
        "step": step,
        "software": f"vet {__version__}",
        "command": " ".join(sys.argv),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "inputs": inputs or [],
        "params": params,
    }


def measure_bin_edges(n_subframes: int, n_bins: int) -> np.ndarray:
    """Subframe index edges of ``n_bins`` near-equal bins (``n_bins + 1`` integers)."""
    n_bins = max(1, min(n_bins, n_subframes))
    return np.linspace(0, n_subframes, n_bins + 1).round().astype(int)


def bin_span(n_images: int, n_bins: int, k: int) -> tuple[int, int]:
    """The measuring images ``[a, b)`` that bin ``k`` of :meth:`Capture.time_bins`
    ``(n_bins)`` sums, of ``n_images`` (each its own bin where there are no more of them
    than bins)."""
    edges = measure_bin_edges(n_images, n_bins) if n_images > n_bins else np.arange(n_images + 1)
    return int(edges[k]), int(edges[k + 1])


def bin_times(measure_times: np.ndarray, n_bins: int) -> np.ndarray:
    """The ``[start, end)`` times (B, 2) s of measuring images with ``measure_times``
    (F, 2) summed into ``n_bins`` time bins (:meth:`Capture.time_bins`)."""
    mt = np.asarray(measure_times, np.float64)
    if len(mt) <= n_bins:
        return mt
    edges = measure_bin_edges(len(mt), n_bins)
    return np.stack([mt[edges[:-1], 0], mt[edges[1:] - 1, 1]], axis=1)


def sum_bins_in_place(box: list[np.ndarray], edges: np.ndarray) -> np.ndarray | None:
    """The sums of a stream (F, ...) over its frames ``edges[k]:edges[k + 1]``, float32
    (B, ...), made in the stream's own memory, which then shrinks to theirs.

    ``box`` is a list holding the stream alone: the function takes it out, so that its
    reference is the only one. Each bin is summed on the process's threads into a
    temporary, then copied over the start of the stream, where only frames before
    ``edges[k + 1]`` lie (read already); ``ndarray.resize`` then hands the rest back to
    the system (the C library shrinks the block without copying it).

    Returns None, the stream put back in ``box`` untouched, where this cannot be done
    safely: the stream is a view or not one contiguous block, anything else holds it or
    a view of it (numpy refuses to resize it then), or it has too few frames per bin
    for the bins to stay behind the frames still to be read.
    """
    stream = box.pop()
    shape, n_bins = stream.shape, len(edges) - 1
    plane = int(np.prod(shape[1:], dtype=np.int64))
    bin_bytes, frame_bytes = plane * 4, plane * stream.itemsize
    if (
        n_bins < 1
        or not stream.flags.owndata
        or not stream.flags.c_contiguous
        or (n_bins * bin_bytes) % stream.itemsize
        or any((k + 1) * bin_bytes > int(edges[k + 1]) * frame_bytes for k in range(n_bins))
    ):
        box.append(stream)
        return None
    try:  # (numpy resizes only an array nothing else holds: asked before any write)
        stream.resize(stream.size + 1)
    except ValueError:
        box.append(stream)
        return None
    frames = stream[:-1].reshape(shape)
    raw = stream.view(np.uint8)
    sums = in_order(
        lambda k, f=frames: np.sum(f[edges[k] : edges[k + 1]], axis=0, dtype=np.float32), n_bins
    )
    for k, total in enumerate(sums):
        raw[k * bin_bytes : (k + 1) * bin_bytes].view(np.float32)[:] = total.reshape(-1)
    del frames, raw, total, sums  # (no view of the stream is left: it may be resized)
    stream.resize(n_bins * bin_bytes // stream.itemsize)
    return stream.view(np.float32).reshape(n_bins, *shape[1:])


def dn_bound(rig: RigParams, n_subframes: int) -> float:
    """The largest magnitude (DN) a sum of ``n_subframes`` readings may hold: no sensor
    the rig's schema allows (ADC of 24 bits at most) records more, black level and all."""
    return float(n_subframes) * (2.0**24 + rig.black_level_dn)


@dataclass
class TruthPaths:
    """A simulated capture's true motion along paths (``truth_layers`` and
    ``meta["truth_trajectory"]``): rigid layers on the t = 0 grid, each moving by an
    affine map per time. The point ``x0`` (x, y px, pixel centres on integers, y down)
    of layer ``k`` is at time ``times[m]`` at

        ``x = anchor[k] + disp[k, m] + linear[k, m] @ (x0 - anchor[k])``

    so its displacement ``D(x0, t) = x - x0`` is one vector per layer where ``linear``
    is None (every layer translates: ``disp`` alone, anchors irrelevant) and varies
    over the layer where it turns. ``labels`` (H, W) int32 is each pixel's layer at
    t = 0 (0 the background), ``times`` (M,) s, ``disp`` (K, M, 2) px, ``anchor``
    (K, 2) px, ``linear`` (K, M, 2, 2) or None, ``front`` the layers that occlude, front
    to back (every layer but 0, the background)."""

    labels: np.ndarray
    times: np.ndarray
    disp: np.ndarray
    anchor: np.ndarray
    linear: np.ndarray | None
    front: list[int]

    def maps(self) -> np.ndarray:
        """Each layer's map at each time as ``x = A x0 + b``: (K, M, 2, 3) float64."""
        k_n, m_n = self.disp.shape[:2]
        lin = self.linear
        if lin is None:
            lin = np.broadcast_to(np.eye(2), (k_n, m_n, 2, 2))
        out = np.empty((k_n, m_n, 2, 3))
        out[..., :2] = lin
        a = self.anchor[:, None, :]
        out[..., 2] = a + self.disp - np.einsum("kmij,kj->kmi", lin, self.anchor)
        return out

    def positions(self, m: int) -> np.ndarray:
        """Where each pixel of t = 0 is at ``times[m]``: (H, W, 2) px (x, y)."""
        h, w = self.labels.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        a = self.maps()[:, m][self.labels]  # (H, W, 2, 3)
        return a[..., 0] * xx[..., None] + a[..., 1] * yy[..., None] + a[..., 2]

    def meta(self) -> dict[str, Any]:
        """The ``truth_trajectory`` metadata (:class:`stages.formats.schema.TruthTrajectory`)."""
        out: dict[str, Any] = {"times": self.times.tolist(), "disp": self.disp.tolist()}
        if self.linear is not None:
            out["anchor"] = np.asarray(self.anchor, float).tolist()
            out["linear"] = self.linear.tolist()
        out["front"] = [int(k) for k in self.front]
        return out


#: Time bins the motion estimators read of a capture that keeps its whole stream.
MOTION_BINS = 8


@dataclass
class Capture:
    """One recorded (or simulated) VET frame. Arrays are float32."""

    I: np.ndarray  # noqa: E741 - the paper's symbol; (H, W, C) DN
    T: np.ndarray  # (H, W) seconds
    channels: list[str]
    rig: RigParams
    meta: dict[str, Any] = field(default_factory=dict)
    measure: np.ndarray | None = None  # (B, H, W, C) DN
    measure_times: np.ndarray | None = None  # (B, 2) seconds [start, end)
    transmittance: np.ndarray | None = None  # (H, W)
    truth: np.ndarray | None = None  # (H, W, C) scene units
    truth_motion: np.ndarray | None = None  # (H, W, 2) px/s
    truth_layers: np.ndarray | None = None  # (H, W) layer index (motions along paths)
    # (H, W) transmittance: the leakage of the LCoS cell each pixel's centre lies in, as a
    # calibration measured it (Calibration.cell_leakage); read in place of the rig's
    # configured per-cell pattern (stages.optics.capture_leakage).
    cell_leakage: np.ndarray | None = None
    # Set by stages.optics.register_measure (never stored): the measuring images lie on
    # the VET grid, and these (2, H, W) factors scale the ideal rig's shot and read
    # variances of each of their pixels.
    measure_noise: np.ndarray | None = None
    # Set by stages.deblur (never stored): (H, W) the T of the ideal shutter that exposes
    # a still pixel as the real rig's LCoS did (switching, per-cell leakage, relay blur),
    # computed on the whole frame so that tiles cropped from it keep it right.
    ideal_T: np.ndarray | None = None
    # Set by stages.deblur for a tile of a real rig's frame (never stored): its measuring
    # bins on the measurement camera's grid with the camera's sampling of the tile
    # (stages.deblur.camera_grid.CameraBins), beside ``measure`` registered onto the tile.
    camera_bins: Any = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.I.shape[:2]

    def truth_paths(self) -> TruthPaths | None:
        """The true motion along paths of a simulated capture, or None (no
        ``truth_layers``: constant velocities, in ``truth_motion``)."""
        tt = self.meta.get("truth_trajectory")
        if self.truth_layers is None or not isinstance(tt, dict):
            return None
        disp = np.asarray(tt["disp"], np.float64)
        k_n = disp.shape[0]
        linear = tt.get("linear")
        return TruthPaths(
            labels=self.truth_layers.astype(np.int32),
            times=np.asarray(tt["times"], np.float64),
            disp=disp,
            anchor=np.asarray(tt.get("anchor", np.zeros((k_n, 2))), np.float64),
            linear=None if linear is None else np.asarray(linear, np.float64),
            front=[int(k) for k in tt.get("front", range(k_n - 1, 0, -1))],
        )

    @property
    def models_lcos(self) -> bool:
        """Whether its exposure goes through a real LCoS (:func:`stages.optics.vet_exposure`):
        the rig's shutter is not the ideal one, or the capture has a calibrated per-cell
        leakage."""
        return not self.rig.ideal_shutter or self.cell_leakage is not None

    @property
    def keeps_stream(self) -> bool:
        """Whether the capture keeps its measuring stream: two or more measuring images,
        each one subframe long."""
        if self.measure is None or self.measure_times is None or self.measure.shape[0] < 2:
            return False
        dur = np.diff(np.asarray(self.measure_times, np.float64), axis=1)[:, 0]
        return bool(np.all(np.rint(dur / self.rig.subframe_s) <= 1))

    def time_bins(self, n_bins: int, consume: bool = False) -> Capture:
        """The capture with its measuring images summed into ``n_bins`` near-equal time
        bins (float32 DN, times ``[start of the first, end of the last)``); itself when it
        has no more images than that.

        ``consume``: the caller needs no more of this capture's measuring images. Its
        ``measure`` is set to None, and where nothing else holds them the bins are made in
        their memory (:func:`sum_bins_in_place`): a stream and its bins are then never
        held side by side."""
        from dataclasses import replace

        if self.measure is None or self.measure_times is None or self.measure.shape[0] <= n_bins:
            return self
        shape = self.measure.shape
        edges = measure_bin_edges(shape[0], n_bins)
        times = self.bin_times(n_bins)
        n = self.measure_counts()
        box = [self.measure]
        bins = None
        if consume:
            self.measure = None
            bins = sum_bins_in_place(box, edges)
        if bins is None:
            stream = box.pop()
            # Filled in place: no list of bins beside their stacked copy.
            bins = np.empty((len(edges) - 1, *shape[1:]), np.float32)

            def fill(k: int) -> None:
                np.sum(stream[edges[k] : edges[k + 1]], axis=0, dtype=np.float32, out=bins[k])

            for _ in in_order(fill, len(bins)):  # (the bins on the process's threads)
                pass
        meta = dict(self.meta)
        meta["measure_subframes"] = [
            int(n[a:b].sum()) for a, b in zip(edges[:-1], edges[1:], strict=True)
        ]
        return replace(self, measure=bins, measure_times=times, meta=meta)

    def bin_times(self, n_bins: int) -> np.ndarray:
        """The ``[start, end)`` times (B, 2) s of :meth:`time_bins` ``(n_bins)``'s
        measuring images, without summing them."""
        return bin_times(self.measure_times, n_bins)

    @property
    def measure_shape(self) -> tuple[int, ...]:
        """The measuring images' shape (B, H, W, C)."""
        return self.measure.shape

    def time_bin(self, n_bins: int, k: int) -> Capture:
        """Bin ``k`` of :meth:`time_bins` ``(n_bins)`` alone, as a capture of one
        measuring image (the same sum, times and subframe count), made without the
        others."""
        from dataclasses import replace

        a, b = bin_span(self.measure.shape[0], n_bins, k)
        meta = dict(self.meta)
        meta["measure_subframes"] = [int(c) for c in self.measure_counts()[a:b]]
        part = replace(
            self, measure=self.measure[a:b], measure_times=self.measure_times[a:b], meta=meta
        )
        return part.time_bins(1)

    def measure_counts(self) -> np.ndarray:
        """Subframes summed in each measuring image, (B,) int: the metadata's
        ``measure_subframes`` where it fits, else each time bin's length in subframes (a
        bin spanning a dropped subframe holds one fewer than its span)."""
        if self.measure is None or self.measure_times is None:
            return np.zeros(0, int)
        n = self.meta.get("measure_subframes")
        if isinstance(n, list) and len(n) == self.measure.shape[0]:
            return np.maximum(np.asarray(n, int), 1)
        dur = np.diff(np.asarray(self.measure_times, np.float64), axis=1)[:, 0]
        return np.maximum(np.rint(dur / self.rig.subframe_s), 1).astype(int)

    @property
    def method(self) -> str:
        return str(self.meta.get("method", "vet"))

    @property
    def radiance_scale(self) -> float | None:
        s = self.meta.get("radiance_scale")
        return float(s) if s else None

    def validate(self, what: str = "capture") -> None:
        """Check shapes and values, and that every pixel saw light; raise
        :class:`FormatError` with one sentence."""
        self._check_images(what)
        self._check_exposure(what)
        if self.measure is not None:
            self._check_measuring(what)
        if self.truth_layers is not None:
            tt = self.meta.get("truth_trajectory")
            n_layers = len(tt.get("disp", [])) if isinstance(tt, dict) else 0
            if self.truth_layers.shape != self.T.shape or not n_layers:
                raise FormatError(f"{what}: truth_layers without a matching truth_trajectory")
            if int(self.truth_layers.min()) < 0 or int(self.truth_layers.max()) >= n_layers:
                raise FormatError(f"{what}: truth_layers names a layer truth_trajectory lacks")
        if self.cell_leakage is not None:
            if self.cell_leakage.shape != self.T.shape:
                raise FormatError(f"{what}: cell_leakage does not match T's size")
            leak = self.cell_leakage
            if not (np.isfinite(leak).all() and (leak >= 0).all() and (leak < 1).all()):
                raise FormatError(f"{what}: cell_leakage must hold transmittances in [0, 1)")

    def _check_images(self, what: str) -> None:
        """I (H, W, C) and T (H, W), finite, T within the frame."""
        if self.I.ndim != 3 or self.I.shape[2] != len(self.channels) or self.I.shape[2] == 0:
            raise FormatError(f"{what}: I must be (H, W, C) with C = {len(self.channels)}")
        if self.T.shape != self.I.shape[:2]:
            raise FormatError(
                f"{what}: I is {self.I.shape[1]}x{self.I.shape[0]} but T is "
                f"{self.T.shape[1] if self.T.ndim > 1 else '?'}x{self.T.shape[0]}; they must match"
            )
        if not np.all(np.isfinite(self.T)):
            raise FormatError(f"{what}: T holds NaN or infinite exposure times")
        if not np.all(np.isfinite(self.I)):
            raise FormatError(f"{what}: I holds NaN or infinite values")
        tf = self.rig.frame_s
        if self.T.size and (float(self.T.min()) < 0 or float(self.T.max()) > tf * (1 + 1e-6)):
            raise FormatError(f"{what}: T outside [0, {tf}] s (the frame length)")
        top = dn_bound(self.rig, 1)
        if self.I.size and float(np.abs(self.I).max()) > top:
            raise FormatError(
                f"{what}: I holds values beyond +/-{top:g} DN; no sensor records more "
                "(the rig's ADC has at most 24 bits)"
            )

    def _check_exposure(self, what: str) -> None:
        """Every pixel was exposed: T > 0 where no light leaks past a closed cell (leakage
        0, or a plain exposure's), a fixed transmittance A in (0, 1]."""
        if self.transmittance is not None:
            a = self.transmittance
            if a.shape != self.T.shape:
                raise FormatError(f"{what}: transmittance does not match T's size")
            if not (np.isfinite(a).all() and (a > 0).all() and (a <= 1).all()):
                raise FormatError(f"{what}: transmittance A must hold values in (0, 1]")
        leaks = self.meta.get("leakage_applies", True) is not False and self.rig.leakage > 0
        dark = int(np.count_nonzero(self.T <= 0)) if not leaks else 0
        if dark:
            raise FormatError(
                f"{what}: T is 0 s at {dark} of {self.T.size} pixels and no light leaks past "
                f"a closed cell (rig.leakage = {self.rig.leakage:g}): those pixels saw no light; "
                "allowed T > 0"
            )

    def _check_measuring(self, what: str) -> None:
        """The measuring images: (B, H, W, C) of I's or the measurement camera's size,
        finite, one time bin each."""
        grids = (self.I.shape, (*self.rig.measure_shape, self.I.shape[2]))
        if self.measure.ndim != 4 or self.measure.shape[1:] not in grids:
            raise FormatError(
                f"{what}: measuring images match neither I's size nor the measurement camera's"
            )
        if self.measure_times is None or self.measure_times.shape != (self.measure.shape[0], 2):
            raise FormatError(f"{what}: measuring images lack their time bins")
        if self.measure.dtype.kind == "f" and not all(np.isfinite(m).all() for m in self.measure):
            raise FormatError(f"{what}: measuring images hold NaN or infinite values")
        if self.measure.dtype not in (np.int16, np.float16):  # (those cannot reach it)
            for b, n in enumerate(self.measure_counts()):
                top = dn_bound(self.rig, int(n))
                if self.measure[b].size and float(np.abs(self.measure[b]).max()) > top:
                    raise FormatError(
                        f"{what}: measuring image M{b:02d} holds values beyond +/-{top:g} DN, "
                        f"more than its {n} subframes can record (an ADC of 24 bits at most)"
                    )

    # --- conversion to/from the layered container ---------------------------------
    def to_layered(self) -> Layered:
        data = Layered()
        data.add("I", self.I, self.channels)
        data.add("T", self.T, ["Y"])
        if self.transmittance is not None:
            data.add("A", self.transmittance, ["Y"])
        if self.measure is not None:
            for b in range(self.measure.shape[0]):
                data.add(f"M{b:02d}", self.measure[b], self.channels, own_size=True)
        if self.truth is not None:
            data.add("truth", self.truth, self.channels)
        if self.truth_motion is not None:
            data.add("truth_motion", self.truth_motion, ["u", "v"])
        if self.truth_layers is not None:
            data.add("truth_layers", self.truth_layers, ["Y"])
        if self.cell_leakage is not None:
            data.add("cell_leakage", self.cell_leakage, ["Y"])
        meta = dict(self.meta)
        meta["kind"] = "capture"
        meta["format_version"] = 1
        meta["rig"] = self.rig.to_dict()
        meta["channels"] = list(self.channels)
        meta["units"] = {
            "I": "DN",
            "T": "s",
            "M": "DN",
            "A": "1",
            "cell_leakage": "transmittance",
            "truth": "scene",
            "truth_motion": "px/s",
        }
        if self.measure_times is not None:
            meta["measure_times"] = np.asarray(self.measure_times, dtype=float).tolist()
        data.meta = meta
        return data

    @classmethod
    def from_layered(cls, data: Layered, what: str = "capture") -> Capture:
        """The capture a container holds. Its measuring images are taken out of ``data``
        as they are stacked (a reader's container is done with once read)."""
        meta = dict(data.meta)
        if meta.get("kind") != "capture":
            kind = meta.get("kind") or "not a vet file"
            raise FormatError(f"{what}: not a capture (kind: {kind})")
        for needed in ("I", "T"):
            if needed not in data.layers:
                raise FormatError(f"{what}: capture has no {needed} layer")
        rig_d = meta.pop("rig", None)
        if not isinstance(rig_d, dict):
            raise FormatError(f"{what}: capture metadata has no rig parameters")
        try:
            rig = RigParams.from_dict(rig_d)
        except InputError as exc:
            raise FormatError(f"{what}: {exc}") from None
        channels = data.channels["I"]
        mkeys = sorted(
            (k for k in data.layers if len(k) >= 3 and k[0] == "M" and k[1:].isdigit()),
            key=lambda k: int(k[1:]),
        )
        measure = _stack_layers(data, mkeys, what) if mkeys else None
        mt = meta.get("measure_times")
        measure_times = (
            np.asarray(mt, dtype=np.float64) if mt is not None and measure is not None else None
        )
        cap = cls(
            I=data.layers["I"],
            T=data.layers["T"][:, :, 0],
            channels=list(channels),
            rig=rig,
            meta=meta,
            measure=measure,
            measure_times=measure_times,
            transmittance=data.layers["A"][:, :, 0] if "A" in data.layers else None,
            truth=data.layers.get("truth"),
            truth_motion=data.layers.get("truth_motion"),
            cell_leakage=(
                data.layers["cell_leakage"][:, :, 0] if "cell_leakage" in data.layers else None
            ),
            truth_layers=(
                np.rint(data.layers["truth_layers"][:, :, 0]).astype(np.int32)
                if "truth_layers" in data.layers
                else None
            ),
        )
        cap.validate(what)
        return cap


def _stack_layers(data: Layered, keys: list[str], what: str) -> np.ndarray:
    """The layers ``keys`` of ``data`` as one (B, H, W, C) array, taken out of ``data``
    one at a time as they are copied in (the stack never sits beside all of them: a
    stream of 131 subframes is most of a capture's memory)."""
    first = data.layers[keys[0]]
    stack = stack_of([data.layers[k] for k in keys])
    if stack is not None:  # (read into one stack: taken as it is)
        for k in keys:
            del data.layers[k]
        return stack
    dtype = np.result_type(*(data.layers[k].dtype for k in keys))
    for k in keys:
        if data.layers[k].shape != first.shape:
            raise FormatError(f"{what}: measuring image {k} is not the size of {keys[0]}")
    out = np.empty((len(keys), *first.shape), dtype)
    for b, k in enumerate(keys):
        out[b] = data.layers.pop(k)
    return out


def resolve_capture_path(path: str | Path) -> str:
    """A capture argument may be a file, ``-``, or a capture folder holding one."""
    if str(path) == "-":
        return "-"
    p = Path(path)
    if p.is_dir():
        for name in CAPTURE_FILENAMES:
            if (p / name).is_file():
                return str(p / name)
        raise InputError(f"{p}: folder holds no capture file ({' or '.join(CAPTURE_FILENAMES)})")
    return str(p)


#: The simulator's truth layers (``simulate``, the emulated rig): for scoring only.
TRUTH_LAYERS = frozenset({"truth", "truth_motion", "truth_layers"})


def read_capture(path: str | Path, truth: bool = True) -> Capture:
    """The capture at ``path`` (a file, a capture folder or ``-``); ``truth=False``
    leaves the simulator's truth layers unread (:data:`TRUTH_LAYERS`: a reconstruction
    that does not score itself does not hold them)."""
    real = resolve_capture_path(path)
    what = "standard input" if real == "-" else real
    return Capture.from_layered(read_layered(real, frozenset() if truth else TRUTH_LAYERS), what)


def write_capture(path: str | Path, capture: Capture) -> None:
    capture.validate()
    write_layered(path, capture.to_layered())
