"""HDR image files: linear float32 radiance plus a quality mask.

Layers: the unnamed layer (``R, G, B``: viewers and pfstools show it directly), ``mask.Y``
(see :data:`MASK_CODES`), and optionally ``T.Y`` (the capture's exposure time, which lets
evaluation split bright and dark pixels). Metadata: ``kind = "hdr"``, ``units``
(``"scene"`` for simulated captures, else ``"DN/s"``), ``radiance_scale``, ``rig``, and
the ``provenance`` chain.

A mono image is stored as three equal ``R, G, B`` channels with ``mono = true`` in the
metadata (pfstools builds its colour channels only from R, G, B, so a lone ``Y`` channel
fails ``pfstmo_*`` with "Missing X, Y, Z channels"); reading gives back one ``Y`` channel.
Files of earlier versions, with a ``Y`` channel, read the same.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
from .container import count_nonfinite
from .layered import Layered, read_layered, write_layered

#: Mask codes written by hdr-static and deblur.
MASK_CODES = {
    0: "valid",
    1: "VET pixel saturated; radiance recovered from the measuring images",
    2: "saturated in every image; value is a lower bound",
    3: "below the noise floor; value is the noise-equivalent radiance",
    4: "VET pixel saturated and the first measuring bin contradicts it (the scene moved): "
    "doubtful; value from that bin",
}


@dataclass
class HDRImage:
    radiance: np.ndarray  # (H, W, C) float32, linear
    channels: list[str]
    meta: dict[str, Any] = field(default_factory=dict)
    mask: np.ndarray | None = None  # (H, W) uint8 codes
    exposure_time: np.ndarray | None = None  # (H, W) seconds

    def to_layered(self) -> Layered:
        data = Layered()
        mono = list(self.channels) == ["Y"]
        if mono:
            data.add("", np.repeat(self.radiance, 3, axis=2), ["R", "G", "B"])
        else:
            data.add("", self.radiance, self.channels)
        if self.mask is not None:
            data.add("mask", self.mask.astype(np.float32), ["Y"])
        if self.exposure_time is not None:
            data.add("T", self.exposure_time, ["Y"])
        meta = dict(self.meta)
        meta["kind"] = "hdr"
        meta["channels"] = list(data.channels[""])
        meta.pop("mono", None)
        if mono:
            meta["mono"] = True
        meta["mask_codes"] = {str(k): v for k, v in MASK_CODES.items()}
        data.meta = meta
        return data

    @classmethod
    def from_layered(cls, data: Layered, what: str = "HDR image") -> HDRImage:
        if "" not in data.layers:
            raise FormatError(f"{what}: no image channels (R, G, B or Y)")
        mask = data.layers.get("mask")
        t = data.layers.get("T")
        radiance, channels, meta = data.layers[""], data.channels[""], dict(data.meta)
        bad = count_nonfinite(radiance)
        if bad:
            raise FormatError(
                f"{what}: {bad} of {radiance.size} radiance values are NaN or infinite; an HDR "
                "image's radiance must be finite"
            )
        if meta.pop("mono", False) is True and channels == ["R", "G", "B"]:
            radiance, channels = np.ascontiguousarray(radiance[:, :, :1]), ["Y"]
            meta["channels"] = channels
        return cls(
            radiance=radiance,
            channels=channels,
            meta=meta,
            mask=None if mask is None else mask[:, :, 0].astype(np.uint8),
            exposure_time=None if t is None else t[:, :, 0],
        )


def read_hdr(path: str | Path) -> HDRImage:
    """Read an HDR image written by vet, or any plain linear EXR (treated as radiance)."""
    what = "standard input" if str(path) == "-" else str(path)
    data = read_layered(path)
    kind = data.meta.get("kind")
    if kind not in (None, "hdr"):
        raise FormatError(f"{what}: is a {kind} file, not an HDR image")
    if kind is None:
        # A foreign EXR: use its colour channels, ignore alpha and the rest.
        data = _foreign_to_hdr(data, what)
    return HDRImage.from_layered(data, what)


def _foreign_to_hdr(data: Layered, what: str) -> Layered:
    base = data.layers.get("")
    names = data.channels.get("", [])
    if base is None:
        raise FormatError(f"{what}: no R, G, B or Y channels")
    pick = [c for c in ("R", "G", "B") if c in names]
    if len(pick) != 3:
        pick = ["Y"] if "Y" in names else names[:1]
    out = Layered(meta={"kind": "hdr", "units": "unknown"})
    out.add("", base[:, :, [names.index(c) for c in pick]], pick)
    return out


def write_hdr(path: str | Path, image: HDRImage) -> None:
    write_layered(path, image.to_layered())
