"""Static HDR from a VET capture: the paper's I/T, made exact.

For a still scene each pixel of the VET sensor integrates

    I/g = L (A (T + eps (W - T))) + d W + noise

(``g`` gain, ``A`` fixed transmittance (1 unless adaptive attenuation), ``T`` when its
LCoS cell closed as applied by the device, which already contains the latency, ``eps``
leakage, ``W`` the sensor's integration window, ``d`` dark current), so

    L = (I/g - d W) / (A (T + eps (W - T)))   [electrons per second]

divided by the capture's radiance scale for simulated captures (scene units), else
multiplied by the gain (DN/s).

Pixels the VET sensor saturated are recovered from the first measuring-image bin (a short
exposure of the same light), all channels alike; where the bin contradicts the VET image
(it lies well below the clipped value's lower bound: the scene moved) the pixel is flagged
doubtful; pixels saturated there too keep a lower bound; pixels below
the noise floor get the noise-equivalent radiance. Each case is flagged in the mask
(:data:`~stages.formats.hdr.MASK_CODES`), never silently wrong.
"""

from __future__ import annotations

import numpy as np

from .formats.capture import Capture, provenance_entry
from .formats.hdr import HDRImage
from .physics import any_channel, bin_may_clip

#: A pixel whose signal is below this many electrons carries no information.
NOISE_FLOOR_E = 1.0
#: A saturated VET pixel's recovery from the first measuring bin contradicts the VET
#: image when the bin's rate lies this many of its standard deviations below the VET
#: image's lower bound in a clipped channel.
CONTRADICTION_SIGMA = 4.0


def effective_exposure(cap: Capture) -> np.ndarray:
    """Light-weighted exposure A (T + eps (W - T)) in seconds, ``(H, W, 1)`` float32.

    Through a real rig's LCoS (:mod:`stages.optics`) the closure's switching ramp, each
    cell's own leakage and the relay blur enter (:func:`stages.optics.vet_exposure`).
    """
    w = float(cap.meta.get("integration_s", cap.rig.frame_s))
    leaks = cap.meta.get("leakage_applies", True)
    if leaks and cap.ideal_T is not None:  # a tile of a frame: its equivalent T
        t = cap.ideal_T.astype(np.float32)
        return (t + np.float32(cap.rig.leakage) * (np.float32(w) - t))[..., None]
    if leaks and cap.models_lcos and cap.transmittance is None:
        from .optics import capture_leakage, vet_exposure

        eps_px = capture_leakage(cap.rig, cap.shape, cap.cell_leakage)
        return vet_exposure(cap.T, eps_px, w, cap.rig)[..., None]
    eps = cap.rig.leakage if leaks else 0.0
    t = cap.T.astype(np.float32)
    e = t + np.float32(eps) * (np.float32(w) - t)
    if cap.transmittance is not None:
        e = e * cap.transmittance
    return e[..., None]


def rate_to_output_units(cap: Capture, rate_e_s: np.ndarray) -> tuple[np.ndarray, str]:
    """Electrons/s at the VET sensor -> scene units (simulated) or DN/s (recorded)."""
    scale = cap.radiance_scale
    if scale:
        return rate_e_s / np.float32(scale), "scene"
    return rate_e_s * np.float32(cap.rig.gain_dn_per_e), "DN/s"


def reconstruction(
    cap: Capture,
    rate_e_s: np.ndarray,
    mask: np.ndarray,
    method: str,
    step: dict,
    **meta: object,
) -> HDRImage:
    """A capture's reconstruction as an HDR image: ``rate_e_s`` (H, W, C) electrons/s at
    the VET sensor in the output units (:func:`rate_to_output_units`), ``mask`` (H, W)
    uint8, the capture's T, and the metadata every reconstruction carries (units, radiance
    scale, rig, ``method``, the capture's method, motion and scene, the provenance chain
    extended by ``step``), plus ``meta``."""
    radiance, units = rate_to_output_units(cap, rate_e_s.astype(np.float32))
    out = {
        "units": units,
        "radiance_scale": cap.radiance_scale,
        "rig": cap.rig.to_dict(),
        "method": method,
        "source_method": cap.method,
        "motion": cap.meta.get("motion"),
        "scene": cap.meta.get("scene"),
        **meta,
        "provenance": list(cap.meta.get("provenance", [])) + [step],
    }
    return HDRImage(
        radiance=radiance.astype(np.float32),
        channels=list(cap.channels),
        meta=out,
        mask=mask,
        exposure_time=cap.T,
    )


def hdr_static(
    cap: Capture, assume_ideal_rig: bool = False, registered: Capture | None = None
) -> HDRImage:
    """Invert a capture assuming a still scene.

    A real rig's parts (:mod:`stages.optics`, recorded in the capture's rig) enter: the
    measuring images are fitted onto the VET grid through the measurement camera's
    geometry, gain and vignetting (:func:`fit_through_geometry`), and the exposure holds
    the switching ramp, each cell's leakage and the relay blur (:func:`effective_exposure`).

    Parameters
    ----------
    cap : Capture
        Any capture (VET or a comparison method).
    assume_ideal_rig : bool
        Ignore those parts (:func:`stages.optics.ideal_rig`): what reconstructing
        without the rig's calibration gives. The measurement camera must then have the
        VET sensor's size.
    registered : Capture, optional
        ``register_measure(cap)`` when the caller has it already (a stream registered
        once, not twice).

    Returns
    -------
    HDRImage
        ``radiance`` (H, W, C) float32 in scene units or DN/s, ``mask`` (H, W) uint8,
        ``exposure_time`` the capture's T.
    """
    from .measure_grid import register_measure
    from .optics import ideal_rig

    if assume_ideal_rig:
        from dataclasses import replace

        if cap.measure is not None and cap.measure.shape[1:3] != cap.shape:
            from .errors import InputError

            raise InputError(
                "the measuring images are not on the VET sensor's grid: the rig cannot be "
                "assumed ideal"
            )
        cap = replace(cap, rig=ideal_rig(cap.rig), cell_leakage=None)
    raw = cap
    if registered is None or assume_ideal_rig:
        registered = register_measure(cap)  # onto the VET grid (a real rig's camera)
    cap = registered
    # Fitted through the camera's sampling when it came on the camera's own grid (a tile
    # of a frame comes registered already: interpolated).
    registered = cap.measure_noise is not None and raw.measure_noise is None
    rig = cap.rig
    g = np.float32(rig.gain_dn_per_e)
    w = float(cap.meta.get("integration_s", rig.frame_s))
    signal_e = cap.I / g - np.float32(rig.dark_current_e_s * w)
    expo = effective_exposure(cap)
    rate = signal_e / expo

    mask = np.zeros(cap.shape, np.uint8)
    vet_sat = cap.I >= np.float32(rig.saturation_dn)
    if vet_sat.any():
        sat_px = any_channel(vet_sat)
        rec, rec_ok, rec_sd = _rate_from_measure(cap)
        if rec is not None:
            use = sat_px & rec_ok
            # The first bin measures the light directly, unclipped, nearer to t = 0. The
            # clipped VET value only bounds the mean over [0, T], which a moving scene
            # breaks (a bright edge arriving late pushes it far above the scene at t=0).
            # A clipped VET value bounds the mean rate over the exposure from below. When
            # the bin lies far below that bound (a bright edge arrived after the bin: the
            # scene moved), the two disagree: the bin's value stands (the scene nearer
            # t = 0) but the pixel is flagged doubtful.
            bound = rec  # where the bin clipped too: its top code, a lower bound
            if registered:
                # A measurement camera of its own: its bin fitted onto the VET grid
                # through its geometry, where a still scene's pixel is at least the VET
                # image's own bound in a clipped channel.
                rec = fit_through_geometry(raw, rec, rate, signal_e, expo, vet_sat)
            contra = use & np.any((rec < rate - CONTRADICTION_SIGMA * rec_sd) & vet_sat, axis=2)
            if registered:
                rec = np.where(vet_sat, np.maximum(rec, rate), rec)
            rate = np.where(use[..., None], rec, rate)
            mask[use] = 1
            mask[contra] = 4
            mask[sat_px & ~rec_ok] = 2
            lower = sat_px & ~rec_ok
            rate = np.where(lower[..., None], np.maximum(bound, rate), rate)
        else:
            mask[sat_px] = 2
    floor_rate = np.float32(NOISE_FLOOR_E) / expo
    low = any_channel(signal_e < NOISE_FLOOR_E) & (mask == 0)
    mask[low] = 3
    rate = np.maximum(rate, floor_rate)

    method = "vet-static" if cap.method == "vet" else cap.method
    return reconstruction(cap, rate, mask, method, provenance_entry("hdr-static"))


def _rate_from_measure(
    cap: Capture,
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray | None]:
    """Rate (e-/s at the VET sensor) from the first measuring bin (H, W, C), where it is
    valid (H, W), and its noise standard deviation (H, W, C), e-/s. Of more than eight
    measuring images (a capture's whole stream), the first eighth, summed, is the bin."""
    if cap.measure is None or cap.measure_times is None:
        return None, np.zeros(cap.shape, bool), None
    rig = cap.rig
    g = np.float32(rig.gain_dn_per_e)
    # A stream's first eighth of subframes, summed, as an 8-bin capture's first bin.
    n0 = 1
    if cap.measure.dtype != np.float32 or cap.measure.shape[0] > 8:
        from .formats.capture import measure_bin_edges

        n0 = int(measure_bin_edges(cap.measure.shape[0], 8)[1])
    t0, t1 = float(cap.measure_times[0][0]), float(cap.measure_times[n0 - 1][1])
    dur = t1 - t0
    n_sub = int(cap.measure_counts()[:n0].sum())
    if n_sub != max(1, int(round(dur / rig.subframe_s))):  # a dropped subframe among them
        dur = n_sub * rig.subframe_s
    m0 = np.sum(cap.measure[:n0], axis=0, dtype=np.float32)  # (no float32 copy of them)
    rate = (m0 / g - np.float32(rig.dark_current_e_s * dur)) / np.float32(
        dur * rig.measure_fraction
    )
    # Valid unless some subframe of the bin may have clipped; for a still pixel the
    # subframes are alike, so the bin mean per subframe tells.
    ok = ~bin_may_clip(m0 / np.float32(n_sub), rig)
    shot = read = np.float32(1.0)
    if cap.measure_noise is not None:  # registered: vignetting and interpolation
        shot, read = (v[..., None] for v in cap.measure_noise)
    var_e = np.maximum(m0 / g, 0) * shot + np.float32(n_sub * rig.read_noise_e**2) * read
    sd = np.sqrt(var_e) / np.float32(dur * rig.measure_fraction)
    return rate.astype(np.float32), ok, sd.astype(np.float32)


def fit_through_geometry(
    raw: Capture,
    start: np.ndarray,
    vet_rate: np.ndarray,
    vet_signal_e: np.ndarray,
    expo: np.ndarray,
    vet_sat: np.ndarray,
) -> np.ndarray:
    """The first measuring bin of a measurement camera with its own grid, inverted onto
    the VET grid through its forward model, (H, W, C) e-/s.

    Interpolating the bin onto the VET grid smooths what it saw (its pixels sample the
    scene between the VET pixels). Instead the VET-grid rate is fitted to every measuring
    pixel through the camera's sampling (:func:`stages.optics.fit_bin`) together with the
    VET image's unclipped channels (``vet_rate``, variance from ``vet_signal_e`` over the
    exposure ``expo``), from ``start`` (the interpolated bin, e-/s). ``raw``: the capture
    as recorded (measuring images on the measurement grid); ``vet_sat`` (H, W, C): the
    VET image's clipped channels.
    """
    from .formats.capture import measure_bin_edges
    from .measure_grid import fit_bin
    from .optics import MeasureGeometry

    rig = raw.rig
    geom = MeasureGeometry(rig)
    n0 = 1
    if raw.measure.dtype != np.float32 or raw.measure.shape[0] > 8:
        n0 = int(measure_bin_edges(raw.measure.shape[0], 8)[1])
    n_sub = int(raw.measure_counts()[:n0].sum())
    dur = n_sub * rig.subframe_s
    scale = dur * rig.measure_fraction
    dark = rig.dark_current_e_s * dur
    m0 = np.sum(raw.measure[:n0], axis=0, dtype=np.float32)
    # The VET image's pixels as electrons of the bin: rate * scale + dark.
    var_v = (np.maximum(vet_signal_e, 0) + rig.read_noise_e**2) / np.square(expo.astype(np.float64))
    w_v = np.where(vet_sat, 0.0, 1.0 / (var_v * scale**2))
    y_v = vet_rate.astype(np.float64) * scale + dark
    x = fit_bin(geom, m0, n_sub, start.astype(np.float64) * scale + dark, extra=(w_v, y_v))
    return ((x - dark) / scale).astype(np.float32)
