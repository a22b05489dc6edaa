"""False-colour pictures of scalar and categorical maps, with a labelled scale.

Pictures are drawn with matplotlib's Agg renderer (imported lazily, no pyplot, no global
state touched) straight into an ``(H', W', 3)`` uint8 RGB array that
:func:`stages.formats.images.write_display_image` can store. The map keeps (about) its
native resolution: one map pixel is one picture pixel, or an integer block of them for
maps smaller than :data:`MIN_MAP_PIXELS` on their short side; margins around it hold the
title and the scale.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping
from typing import Any

import numpy as np

#: Maps whose short side is smaller than this are enlarged by an integer factor.
MIN_MAP_PIXELS = 256
#: Maps whose long side is larger than this are reduced by an integer factor.
MAX_MAP_PIXELS = 4096
#: Resolution of the drawing: points to pixels (matplotlib's 72 pt per inch).
_DPI = 100
#: Colour map for exposure times (perceptually uniform, readable in greyscale).
EXPOSURE_TIME_CMAP = "viridis"
#: Colour of map pixels with no value (NaN).
NO_DATA_COLOR = "#ff00ff"

#: Colours given to mask codes in increasing order: the first (normally 0, "valid") is a
#: neutral grey so that the flagged pixels stand out.
MASK_PALETTE: tuple[str, ...] = (
    "#4d4d4d",
    "#ff7f0e",
    "#d62728",
    "#1f77b4",
    "#2ca02c",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#bcbd22",
    "#17becf",
    "#ffffff",
    "#000000",
)


def render_exposure_time_map(
    T: np.ndarray,
    frame_s: float,
    subframe_s: float,
    *,
    title: str = "Exposure time T",
) -> np.ndarray:
    """Picture of an exposure time image in log-scaled false colour, with a colourbar.

    The colour scale runs logarithmically from one subframe (the shortest exposure the
    rig can give) to the frame length (pixels that never closed); the colourbar is
    labelled in milliseconds, with the subframe and frame lengths marked.

    Parameters
    ----------
    T : ndarray of shape (H, W) or (H, W, 1)
        Exposure time per pixel, seconds. NaN is drawn in :data:`NO_DATA_COLOR`; values
        outside ``[subframe_s, frame_s]`` are drawn at the ends of the scale.
    frame_s : float
        Frame length Tf, seconds.
    subframe_s : float
        Subframe length, seconds; positive and shorter than ``frame_s``.
    title : str, optional
        Title drawn above the map.

    Returns
    -------
    ndarray of shape (H', W', 3), uint8
        The picture, RGB. The map occupies ``s*H x s*W`` pixels of it, with ``s`` an
        integer (or ``1/s``) chosen to keep it between :data:`MIN_MAP_PIXELS` and
        :data:`MAX_MAP_PIXELS`.
    """
    t = _as_map(T, "Exposure time map")
    frame_s = float(frame_s)
    subframe_s = float(subframe_s)
    if not (math.isfinite(subframe_s) and subframe_s > 0):
        raise ValueError(f"Subframe length must be a positive number of seconds; got {subframe_s}.")
    if not (math.isfinite(frame_s) and frame_s > subframe_s):
        raise ValueError(
            f"Frame length ({frame_s} s) must be longer than the subframe length ({subframe_s} s)."
        )
    if t.dtype.kind not in "fiu":
        raise ValueError(f"Exposure time map must be numeric, not {t.dtype}.")
    t = t.astype(np.float64)
    t[np.isinf(t)] = np.nan
    shown, block = _resample(t, nearest=True)

    from matplotlib import colormaps
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullLocator

    h, w = shown.shape
    margin = 12
    bar_w, bar_gap, label_w = 18, 14, 120
    fig_w = margin + w + bar_gap + bar_w + label_w
    closed = np.isfinite(t) & (t < frame_s * (1 - 1e-6))
    finite = max(int(np.count_nonzero(np.isfinite(t))), 1)
    subtitle = (
        f"subframe {_format_ms(subframe_s)} ms, frame {_format_ms(frame_s)} ms; "
        f"{100.0 * np.count_nonzero(closed) / finite:.1f}% of pixels closed early"
    )
    header = _header_lines(subtitle, block, fig_w)
    title_h = _header_height(header)
    fig_h = title_h + h + margin
    fig = _figure(fig_w, fig_h)
    ax = _axes_px(fig, margin, margin, w, h)
    cmap = colormaps[EXPOSURE_TIME_CMAP].with_extremes(bad=NO_DATA_COLOR)
    norm = LogNorm(vmin=subframe_s, vmax=frame_s, clip=True)
    image = ax.imshow(
        np.ma.masked_invalid(shown), cmap=cmap, norm=norm, interpolation="nearest", aspect="auto"
    )
    ax.set_axis_off()
    cax = _axes_px(fig, margin + w + bar_gap, margin, bar_w, h)
    bar = fig.colorbar(image, cax=cax)
    ticks = _ms_ticks(subframe_s, frame_s)
    bar.ax.yaxis.set_major_locator(FixedLocator(ticks))
    bar.ax.yaxis.set_minor_locator(NullLocator())
    bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: _format_ms(v)))
    bar.ax.tick_params(labelsize=9)
    bar.set_label("exposure time (ms)", fontsize=9)
    _title(fig, title, header)
    return _rasterise(fig)


def render_mask(
    mask: np.ndarray,
    codes: Mapping[int, str],
    *,
    title: str = "Quality mask",
) -> np.ndarray:
    """Picture of a categorical mask with a legend naming each code.

    Parameters
    ----------
    mask : ndarray of shape (H, W) or (H, W, 1)
        Integer codes per pixel (e.g. :data:`stages.formats.hdr.MASK_CODES`).
    codes : mapping of int to str
        Meaning of each code. Every code listed gets a legend entry (with its share of
        the pixels), and so does every code found in ``mask`` but not listed.
    title : str, optional
        Title drawn above the map.

    Returns
    -------
    ndarray of shape (H', W', 3), uint8
        The picture, RGB; the map at (about) native resolution, the legend below it.
    """
    m = _as_map(mask, "Mask")
    if m.dtype.kind == "f":
        if not np.isfinite(m).all() or not np.array_equal(m, np.round(m)):
            raise ValueError("Mask must hold integer codes; found non-integer values.")
    elif m.dtype.kind not in "iub":
        raise ValueError(f"Mask must hold integer codes, not {m.dtype}.")
    m = m.astype(np.int64)
    try:
        listed = {int(k): str(v) for k, v in codes.items()}
    except (TypeError, ValueError):
        raise ValueError("Mask codes must map integer codes to names.") from None
    present, counts = np.unique(m, return_counts=True)
    share = dict(zip(present.tolist(), counts.tolist(), strict=True))
    all_codes = sorted(set(listed) | set(share))
    if len(all_codes) > len(MASK_PALETTE):
        raise ValueError(
            f"Mask has {len(all_codes)} distinct codes; at most {len(MASK_PALETTE)} can be "
            "told apart in one legend."
        )
    colours = {code: MASK_PALETTE[i] for i, code in enumerate(all_codes)}
    lookup = np.searchsorted(np.asarray(all_codes), m)
    shown, block = _resample(lookup.astype(np.float64), nearest=True)

    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    h, w = shown.shape
    margin = 12
    fig_w = max(w + 2 * margin, 520)
    header = _header_lines(None, block, fig_w)
    title_h = _header_height(header)
    wrap = max(30, (fig_w - 2 * margin - 40) // 7)
    total = m.size
    labels = []
    for code in all_codes:
        name = listed.get(code, "code not described in the file")
        count = share.get(code, 0)
        labels.append(textwrap.fill(f"{code}: {name} ({_format_share(count, total)})", wrap))
    legend_lines = sum(label.count("\n") + 1 for label in labels)
    legend_h = 16 * legend_lines + 6 * len(labels) + 16
    fig_h = title_h + h + margin + legend_h
    fig = _figure(fig_w, fig_h)
    left = (fig_w - w) // 2
    ax = _axes_px(fig, left, legend_h + margin // 2, w, h)
    cmap = ListedColormap([colours[c] for c in all_codes])
    norm = BoundaryNorm(np.arange(len(all_codes) + 1) - 0.5, len(all_codes))
    ax.imshow(shown, cmap=cmap, norm=norm, interpolation="nearest", aspect="auto")
    ax.set_xticks([])
    ax.set_yticks([])
    handles = [
        Patch(facecolor=colours[c], edgecolor="black", label=label)
        for c, label in zip(all_codes, labels, strict=True)
    ]
    fig.legend(
        handles=handles,
        loc="lower left",
        bbox_to_anchor=(margin / fig_w, 2 / fig_h),
        frameon=False,
        fontsize=9,
        handlelength=1.5,
        borderaxespad=0.0,
    )
    _title(fig, title, header)
    return _rasterise(fig)


# --------------------------------------------------------------------------- helpers


def _as_map(values: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2:
        raise ValueError(f"{what} must have shape (H, W) or (H, W, 1); got {arr.shape}.")
    if arr.size == 0:
        raise ValueError(f"{what} is empty (shape {arr.shape}).")
    return arr


def _resample(values: np.ndarray, *, nearest: bool) -> tuple[np.ndarray, float]:
    """Enlarge small maps / reduce huge ones by an integer factor; return it (or 1/it)."""
    h, w = values.shape
    if min(h, w) < MIN_MAP_PIXELS:
        factor = max(1, min(MIN_MAP_PIXELS // min(h, w), MAX_MAP_PIXELS // max(h, w)))
        if factor > 1:
            return np.repeat(np.repeat(values, factor, axis=0), factor, axis=1), float(factor)
    if max(h, w) > MAX_MAP_PIXELS:
        step = math.ceil(max(h, w) / MAX_MAP_PIXELS)
        return values[::step, ::step], 1.0 / step
    return values, 1.0


def _figure(width_px: int, height_px: int) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / _DPI, height_px / _DPI), dpi=_DPI, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def _axes_px(fig: Any, left: float, bottom: float, width: float, height: float) -> Any:
    """Axes placed in pixels from the figure's bottom-left corner."""
    fw, fh = fig.get_size_inches() * fig.dpi
    return fig.add_axes((left / fw, bottom / fh, width / fw, height / fh))


def _header_lines(subtitle: str | None, block: float, width_px: int) -> list[str]:
    """Subtitle and resampling note, wrapped to the figure's width (8 pt: < 6.8 px/char)."""
    text = subtitle or ""
    if block > 1:
        text += f"{'; ' if text else ''}each map pixel drawn as {int(block)}x{int(block)}"
    elif block < 1:
        text += f"{'; ' if text else ''}every {round(1 / block)}th map pixel shown"
    return textwrap.wrap(text, max(20, int((width_px - 16) / 6.8))) if text else []


def _header_height(lines: list[str]) -> int:
    return 30 + 12 * len(lines)


def _title(fig: Any, title: str, lines: list[str]) -> None:
    fh = fig.get_size_inches()[1] * fig.dpi
    top = fh - 6
    fig.text(0.5, top / fh, title, ha="center", va="top", fontsize=11, weight="bold")
    if lines:
        fig.text(0.5, (top - 19) / fh, "\n".join(lines), ha="center", va="top", fontsize=8)


def _format_share(count: int, total: int) -> str:
    pct = 100.0 * count / total
    if count == 0:
        pct_text = "0%"
    elif pct < 0.1:
        pct_text = "<0.1%"
    elif pct > 99.9 and count < total:
        pct_text = ">99.9%"
    else:
        pct_text = f"{pct:.1f}%"
    return f"{count} px, {pct_text}"


def _rasterise(fig: Any) -> np.ndarray:
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[:, :, :3], dtype=np.uint8)


def _ms_ticks(lo_s: float, hi_s: float) -> list[float]:
    """Tick positions (seconds): the ends plus 1-2-5 steps in ms that do not crowd them."""
    ticks = [lo_s, hi_s]
    span = math.log10(hi_s / lo_s)
    mantissas = (1, 2, 5) if span < 2.5 else (1, 3) if span < 4 else (1,)
    for exponent in range(math.floor(math.log10(lo_s)) - 1, math.ceil(math.log10(hi_s)) + 1):
        for m in mantissas:
            v = m * 10.0**exponent
            if lo_s < v < hi_s and all(abs(math.log10(v / t)) > 0.12 * span / 2 for t in ticks):
                ticks.append(v)
    return sorted(ticks)


def _format_ms(seconds: float) -> str:
    """Seconds as a millisecond label of at most 5 significant digits: 0.0075 -> "7.5"."""
    return f"{seconds * 1e3:.5g}"
