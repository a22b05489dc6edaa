"""Describe a vet file: its metadata and a summary of its layers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .formats.capture import resolve_capture_path
from .formats.layered import read_layered


def describe(path: str | Path, layers: bool = True) -> dict[str, Any]:
    """Metadata plus, per layer, channels, size and finite min/max/mean."""
    real = resolve_capture_path(path) if Path(str(path)).is_dir() else str(path)
    data = read_layered(real)
    out: dict[str, Any] = {"file": str(path), "metadata": data.meta}
    h, w = data.shape
    out["size"] = {"width": int(w), "height": int(h)}
    if layers:
        summary = {}
        for name, arr in data.layers.items():
            finite = arr[np.isfinite(arr)]
            summary[name or "(image)"] = {
                "channels": data.channels[name],
                "min": float(finite.min()) if finite.size else None,
                "max": float(finite.max()) if finite.size else None,
                "mean": float(finite.mean(dtype=np.float64)) if finite.size else None,
                "nonfinite": int(arr.size - finite.size),
            }
        out["layers"] = summary
    return out
