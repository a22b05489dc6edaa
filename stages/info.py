"""Describe a vet file: its metadata and a summary of its layers.

A capture holds one measuring image per subframe (``M00`` .. ``M130`` at the defaults)
and per-image metadata lists (``measure_times``, ``measure_subframes``, their
``channel_order``). By default they are summarised: the measuring images as one entry
(count, time span, statistics over them all, their size where the measurement camera
has its own), each list by its count and ends. ``full`` lists every layer and keeps the
metadata as stored. Either way, names sort in natural order (``M2`` before ``M10``
before ``M100``: time order for measuring images).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from .formats.capture import resolve_capture_path
from .formats.layered import read_layered

_MEASURING = re.compile(r"M\d{2,}")


def natural_key(name: str) -> list[Any]:
    """Sort key of ``name`` with its runs of digits compared as numbers."""
    return [(0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"(\d+)", name) if p]


def _natural(value: Any) -> Any:
    """``value`` with the keys of every dict in it in natural order."""
    if isinstance(value, dict):
        return {k: _natural(value[k]) for k in sorted(value, key=lambda k: natural_key(str(k)))}
    if isinstance(value, list):
        return [_natural(v) for v in value]
    return value


def _stats(arrays: list[np.ndarray]) -> dict[str, Any]:
    """Finite min, max and mean over ``arrays`` (each counted by its finite pixels), and
    how many values are not finite."""
    finite = [a[np.isfinite(a)] for a in arrays]
    n = sum(f.size for f in finite)
    total = sum(a.size for a in arrays)
    if not n:
        return {"min": None, "max": None, "mean": None, "nonfinite": int(total)}
    return {
        "min": float(min(f.min() for f in finite if f.size)),
        "max": float(max(f.max() for f in finite if f.size)),
        "mean": float(sum(f.sum(dtype=np.float64) for f in finite) / n),
        "nonfinite": int(total - n),
    }


def _span(names: list[str]) -> str:
    return names[0] if len(names) == 1 else f"{names[0]}..{names[-1]}"


def _summarise_meta(meta: dict[str, Any], measuring: list[str]) -> dict[str, Any]:
    """``meta`` with its per-measuring-image lists summarised (see the module docstring)."""
    out = dict(meta)
    times = meta.get("measure_times")
    if isinstance(times, list) and times:
        try:
            ends = np.asarray(times, dtype=float).reshape(len(times), -1)
            out["measure_times"] = {
                "count": len(times),
                "span_s": [float(ends[0, 0]), float(ends[-1, -1])],
            }
        except (TypeError, ValueError):
            pass  # not the stored form: left as it is
    counts = meta.get("measure_subframes")
    if isinstance(counts, list) and counts and all(isinstance(c, int) for c in counts):
        out["measure_subframes"] = {
            "count": len(counts),
            "total": int(sum(counts)),
            "min": int(min(counts)),
            "max": int(max(counts)),
        }
    order = meta.get("channel_order")
    if isinstance(order, dict) and measuring:
        groups = [order.get(m) for m in measuring]
        if all(g == groups[0] for g in groups):
            rest = {k: v for k, v in order.items() if not _MEASURING.fullmatch(k)}
            out["channel_order"] = {**rest, _span(measuring): groups[0]}
    trajectory = meta.get("truth_trajectory")
    if isinstance(trajectory, dict):
        try:
            t = np.asarray(trajectory["times"], dtype=float)
            disp = np.asarray(trajectory["disp"], dtype=float)
            out["truth_trajectory"] = {
                "samples": int(t.size),
                "span_s": [float(t.min()), float(t.max())],
                "layers": int(disp.shape[0]),
                "max_disp_px": np.abs(disp).max(axis=(1, 2)).round(3).tolist(),
            }
        except (KeyError, TypeError, ValueError, IndexError):
            pass
    return out


def describe(path: str | Path, layers: bool = True, full: bool = False) -> dict[str, Any]:
    """Metadata plus, per layer, channels and finite min/max/mean (module docstring).

    Parameters
    ----------
    path : str or Path
        A vet file, a capture folder, or ``-`` (standard input).
    layers : bool
        Include the layers' statistics.
    full : bool
        Every layer on its own and the metadata as stored; by default the measuring
        images are one entry and the per-image metadata lists are summarised.

    Returns
    -------
    dict
        ``file``, ``size``, ``metadata`` and (``layers``) ``layers``, dict keys in
        natural order, ready for ``json.dumps`` without ``sort_keys``.
    """
    real = resolve_capture_path(path) if Path(str(path)).is_dir() else str(path)
    data = read_layered(real)
    names = sorted(data.layers, key=natural_key)
    measuring = [] if full else [n for n in names if _MEASURING.fullmatch(n)]
    h, w = data.shape
    out: dict[str, Any] = {"file": str(path), "size": {"width": int(w), "height": int(h)}}
    meta = data.meta if full else _summarise_meta(data.meta, measuring)
    out["metadata"] = _natural(meta)
    if layers:
        summary: dict[str, Any] = {}
        for name in names:
            if name in measuring:
                if name == measuring[0]:
                    summary[_span(measuring)] = _measuring_entry(data, measuring)
                continue
            summary[name or "(image)"] = {
                "channels": data.channels[name],
                **_own_size(data.layers[name], (h, w)),
                **_stats([data.layers[name]]),
            }
        out["layers"] = summary
    if measuring:
        out["summarised"] = (
            f"the {len(measuring)} measuring images {_span(measuring)} and their metadata "
            "lists; vet info --full lists each"
        )
    return out


def _measuring_entry(data: Any, measuring: list[str]) -> dict[str, Any]:
    """One entry for the measuring images: count, channels, time span, statistics."""
    entry: dict[str, Any] = {"count": len(measuring)}
    channels = [data.channels[m] for m in measuring]
    entry["channels"] = channels[0] if all(c == channels[0] for c in channels) else channels
    times = data.meta.get("measure_times")
    try:
        ends = np.asarray(times, dtype=float).reshape(len(measuring), -1)
        entry["times_s"] = [float(ends[0, 0]), float(ends[-1, -1])]
    except (TypeError, ValueError):
        pass
    entry.update(_own_size(data.layers[measuring[0]], data.shape))
    entry.update(_stats([data.layers[m] for m in measuring]))
    return entry


def _own_size(layer: np.ndarray, size: tuple[int, int]) -> dict[str, Any]:
    """``{"size": ...}`` for a layer of another size than the file's (measuring images
    from a measurement camera of its own size), else nothing."""
    h, w = layer.shape[:2]
    return {} if (h, w) == tuple(size) else {"size": {"width": int(w), "height": int(h)}}
