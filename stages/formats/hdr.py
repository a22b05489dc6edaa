"""HDR image files: linear float32 radiance plus a quality mask.

Layers: the unnamed layer (``Y`` or ``R, G, B``: viewers show it directly), ``mask.Y``
(see :data:`MASK_CODES`), and optionally ``T.Y`` (the capture's exposure time, which lets
evaluation split bright and dark pixels). Metadata: ``kind = "hdr"``, ``units``
(``"scene"`` for simulated captures, else ``"DN/s"``), ``radiance_scale``, ``rig``, and
the ``provenance`` chain.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError
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
        data.add("", self.radiance, self.channels)
        if self.mask is not None:
            data.add("mask", self.mask.astype(np.float32), ["Y"])
        if self.exposure_time is not None:
            data.add("T", self.exposure_time, ["Y"])
        meta = dict(self.meta)
        meta["kind"] = "hdr"
        meta["channels"] = list(self.channels)
        meta["mask_codes"] = {str(k): v for k, v in MASK_CODES.items()}
        data.meta = meta
        return data

    @classmethod
    def from_layered(cls, data: Layered, what: str = "HDR image") -> HDRImage:
        if "" not in data.layers:
            raise FormatError(f"{what}: no image channels (R, G, B or Y)")
        mask = data.layers.get("mask")
        t = data.layers.get("T")
        return cls(
            radiance=data.layers[""],
            channels=data.channels[""],
            meta=dict(data.meta),
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
