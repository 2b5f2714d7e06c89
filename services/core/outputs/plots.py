"""Plots (spec §4): paths over the mosaic, error along the scan, force and coverage maps, method comparison,
each with units and colour scales; and the drawing pieces the one-page sheet (services.core.outputs.sheet)
lays out with them: Page, draw_paths, draw_map, scale_bar and the colour scales.

Uses matplotlib's object API with the Agg canvas, so no pyplot global state and no display is needed.
Axes are the mosaic's: x to the right, y DOWN (image axes), in mm relative to frame 0's centre.
"""

from __future__ import annotations

import io
import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colorbar import Colorbar
from matplotlib.colors import Colormap, Normalize
from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.legend import Legend
from matplotlib.lines import Line2D
from matplotlib.text import Text
from matplotlib.ticker import MaxNLocator
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from services.core.mosaic.canvas import FORCE_FULL_SCALE_N
from services.core.outputs.evaluation import AccuracyReport, evaluate_path

ESTIMATE_COLOR = "#d62728"  # red: the estimated path
REFERENCE_COLOR = "#1f77b4"  # blue: the reference track
UNREGISTERED_COLOR = "#ff7f0e"  # orange crosses: frames not registered
METHOD_COLORS = ("#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
DPI = 100
NOT_SCANNED_COLOR = "#d9d9d9"  # light grey: no frame saw the point
OVER_SCANNED_COLOR = "#ff4fa0"  # pink: more frames than the top of the coverage scale
COVERAGE_PERCENTILE = 95.0  # the coverage scale's top: this percentile of the scanned points' frame counts
TICK_GAP_IN = 0.25  # the least distance between a colour bar's integer ticks
SCALEBAR_GID = "scalebar"  # the gid of a scale bar's text (inside its panel)


def _new_figure(width_in: float, height_in: float) -> tuple[Figure, Axes]:
    fig = Figure(figsize=(width_in, height_in), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def check_path(name: str, value: np.ndarray, n: int | None = None) -> np.ndarray:
    """Return a path as an (N, 2) float array (N == n when given); ValueError naming it otherwise."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of x, y in mm, got shape {arr.shape}")
    if n is not None and len(arr) != n:
        raise ValueError(f"{name}: expected {n} rows, got {len(arr)}")
    return arr


def _finite_rows(path: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    ok = np.all(np.isfinite(path), axis=1)
    if keep is not None:
        ok &= keep
    return path[ok]


def _rmse_or_none(estimate: np.ndarray, registered: np.ndarray, reference: np.ndarray | None) -> float | None:
    if reference is None:
        return None
    try:
        return evaluate_path(estimate, registered, reference).rmse_mm
    except ValueError:
        return None


def set_image_limits(ax: Axes, points: list[np.ndarray], margin_mm: float = 2.0) -> None:
    """Set an image panel's limits to the points' finite bounds plus margin_mm, equal aspect, y down."""
    pts = np.concatenate([p.reshape(-1, 2) for p in points if p.size], axis=0) if points else np.zeros((0, 2))
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        pts = np.zeros((1, 2))
    lo, hi = pts.min(axis=0) - margin_mm, pts.max(axis=0) + margin_mm
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(hi[1], lo[1])  # y down, as in image axes
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (mm, right)")
    ax.set_ylabel("y (mm, down)")


def _mosaic_extent(shape: tuple[int, ...], px_per_mm: float, origin_px: tuple[float, float]) -> tuple[float, ...]:
    """Return (left, right, bottom, top) in mm of a mosaic image for imshow (image axes, y down)."""
    h, w = shape[:2]
    ox, oy = float(origin_px[0]), float(origin_px[1])
    return (-0.5 - ox) / px_per_mm, (w - 0.5 - ox) / px_per_mm, (h - 0.5 - oy) / px_per_mm, (-0.5 - oy) / px_per_mm


def check_scale(px_per_mm: float) -> None:
    """Raise ValueError unless px_per_mm is a finite positive number."""
    if not (px_per_mm > 0 and math.isfinite(px_per_mm)):
        raise ValueError(f"px_per_mm: must be a positive number, got {px_per_mm}")


def stroke_lines(points: np.ndarray, keep: np.ndarray, strokes: np.ndarray | None) -> list[np.ndarray]:
    """Return the polylines (each (K, 2) mm) of the kept finite points: one per stroke, never joined between two.

    strokes: (N,) stroke number of each row (spec §4), -1 where a frame is in no stroke; None: one stroke.
    """
    ok = keep & np.all(np.isfinite(points), axis=1)
    if strokes is None:
        return [points[ok]] if ok.any() else []
    ids = np.asarray(strokes, np.int64).reshape(-1)
    return [points[ok & (ids == k)] for k in sorted(set(ids[ok].tolist())) if k >= 0]


def draw_paths(
    ax: Axes,
    est: np.ndarray,
    reg: np.ndarray,
    ref: np.ndarray | None,
    mosaic: np.ndarray | None,
    px_per_mm: float,
    origin_px: tuple[float, float],
    legend: bool = True,
    strokes: np.ndarray | None = None,
) -> tuple[int, int]:
    """Draw the mosaic, the estimate under the reference (both visible), start/end and unplaced frames.

    Each stroke (strokes: (N,) ints, -1 off the skin; None: one) is its own line, never joined through the air.
    Return (frames placed, frames). legend: a legend inside the axes ("best" place), else none (the caller's).
    """
    n = len(est)
    extent_pts: list[np.ndarray] = []
    if mosaic is not None:
        img = np.asarray(mosaic)
        left, right, bottom, top = _mosaic_extent(img.shape, px_per_mm, origin_px)
        ax.imshow(
            img,
            cmap="gray",
            vmin=0 if img.dtype == np.uint8 else None,  # 8-bit mosaics as stored, not contrast-stretched
            vmax=255 if img.dtype == np.uint8 else None,
            extent=(left, right, bottom, top),
            origin="upper",
            interpolation="nearest",
            zorder=0,
        )
        extent_pts.append(np.array([[left, top], [right, bottom]]))
    placed = reg & np.all(np.isfinite(est), axis=1)
    est_line = est[placed]
    for k, line in enumerate(stroke_lines(est, placed, strokes)):  # the estimate wide and underneath, the reference
        label = "estimated path" if k == 0 else None  # thin and dashed on top: both show
        ax.plot(line[:, 0], line[:, 1], "-", color=ESTIMATE_COLOR, lw=3.0, label=label)
        extent_pts.append(line)
    if ref is not None:
        for k, line in enumerate(stroke_lines(ref, np.ones(n, bool), strokes)):
            label = "reference track" if k == 0 else None
            ax.plot(line[:, 0], line[:, 1], "--", color=REFERENCE_COLOR, lw=1.4, label=label, zorder=3)
            extent_pts.append(line)
    if len(est_line):
        ax.plot(*est_line[0], "o", color="#00c000", mec="white", ms=9, label="start", zorder=4)
        ax.plot(*est_line[-1], "s", color="black", mec="white", ms=8, label="end", zorder=4)
    # Unregistered frames: drawn where the reference puts them if known, else where the estimate does.
    unreg = ~placed
    where = np.full((n, 2), np.nan)
    if ref is not None:
        where[unreg] = ref[unreg]
    missing = unreg & ~np.all(np.isfinite(where), axis=1)
    where[missing] = est[missing]
    marks = _finite_rows(where, unreg)
    if len(marks):
        ax.plot(
            marks[:, 0], marks[:, 1], "x", color=UNREGISTERED_COLOR, ms=7, mew=2,
            label=f"not registered ({int(unreg.sum())})", zorder=5,
        )  # fmt: skip
    set_image_limits(ax, extent_pts if extent_pts else [np.zeros((1, 2))])
    if legend:
        ax.legend(loc="best", fontsize="small")
    return int(placed.sum()), n


def plot_paths_over_mosaic(
    estimate_mm: np.ndarray,
    registered: np.ndarray,
    reference_mm: np.ndarray | None,
    mosaic: np.ndarray | None,
    px_per_mm: float,
    origin_px: tuple[float, float],
    strokes: np.ndarray | None = None,
) -> bytes:
    """Return the PNG of the estimated (and reference) path in mm over the mosaic, a line per stroke.

    origin_px is the mosaic pixel (x, y) where frame 0's centre, (0, 0) mm, lies (spec §4 mosaic.json); strokes:
    (N,) stroke numbers, -1 off the skin (stroke_lines).
    """
    est = check_path("estimate_mm", estimate_mm)
    n = len(est)
    reg = np.asarray(registered, dtype=bool).reshape(-1)
    if len(reg) != n:
        raise ValueError(f"registered: expected {n} entries, got {len(reg)}")
    ref = None if reference_mm is None else check_path("reference_mm", reference_mm, n)
    check_scale(px_per_mm)
    fig, ax = _new_figure(8.0, 7.0)
    placed, _ = draw_paths(ax, est, reg, ref, mosaic, px_per_mm, origin_px, strokes=strokes)
    rmse = _rmse_or_none(est, reg, ref)
    title = f"Probe path: {placed}/{n} frames registered"
    stroke_ids = np.zeros(0, np.int64) if strokes is None else np.asarray(strokes).reshape(-1)
    if np.any(stroke_ids >= 0):  # a scan in strokes: frames in the air are rows too, not frames to register
        title = f"Probe path: {placed} frames placed in {len(set(stroke_ids[stroke_ids >= 0].tolist()))} strokes"
    if rmse is not None and math.isfinite(rmse):
        title += f", RMSE {rmse:.3f} mm"
    ax.set_title(title)
    fig.tight_layout()
    return _png(fig)


@dataclass(frozen=True)
class LayerScale:
    """A map layer's colour scale and its wording: colours, range, units, and what the page says about them."""

    cmap: Colormap
    vmin: float
    vmax: float
    extend: Literal["neither", "max"]  # "max": values above vmax in the colour map's "over" colour (a triangle)
    bar_labels: tuple[str, ...]  # the colour bar's label, most explicit first: the first that fits the bar is used
    title: str
    caption: str
    top_tick: str = ""  # integer ticks from vmin to vmax, the top one labelled so (e.g. "35 = P95"); "": automatic


def coverage_values(coverage: np.ndarray) -> np.ndarray:
    """Return the coverage as float frame counts with NaN where no frame saw the point."""
    cov = np.nan_to_num(np.asarray(coverage, np.float64))
    return np.where(cov >= 0.5, np.rint(cov), np.nan)


def coverage_scale_top(coverage: np.ndarray) -> int:
    """Return the top of the coverage colour scale in frames: the 95th percentile of scanned points (at least 2)."""
    seen = coverage_values(coverage)
    seen = seen[np.isfinite(seen)]
    if not seen.size:
        return 2
    return max(2, math.ceil(float(np.percentile(seen, COVERAGE_PERCENTILE))))


def coverage_scale(coverage: np.ndarray) -> LayerScale:
    """Return the coverage's colour scale: linear over 1..the 95th percentile in frames, pink above, grey unseen.

    A fixed top (the tile layer's 10 frames) is one flat colour on a normal scan, where most points are seen by
    tens of frames; the percentile keeps both the under-scanned (dark) and the over-scanned (pink) areas visible.
    """
    values = coverage_values(coverage)
    seen = values[np.isfinite(values)]
    top = coverage_scale_top(coverage)
    over = bool(seen.size) and float(seen.max()) > top
    median = f", median {float(np.median(seen)):g} frames" if seen.size else ", never scanned"
    pct = f"{COVERAGE_PERCENTILE:g}th percentile"
    return LayerScale(
        cmap=matplotlib.colormaps["viridis"].with_extremes(bad=NOT_SCANNED_COLOR, over=OVER_SCANNED_COLOR),
        vmin=1.0,
        vmax=float(top),
        extend="max" if over else "neither",
        bar_labels=("frames (linear scale)", "frames (linear)", "frames"),
        title="Coverage" + median,
        caption=(
            f"Frames that saw each point, linear scale from 1 to {top} frames (the {pct} of the scanned area): "
            f"dark = few frames (under-scanned), pink = more than {top} (over-scanned). Grey: never scanned."
        ),
        top_tick=f"{top} = P{COVERAGE_PERCENTILE:g}",
    )


def force_scale(force_n: np.ndarray) -> LayerScale:
    """Return the force layer's colour scale: TURBO over 0..FORCE_FULL_SCALE_N newtons (as the tile layer)."""
    f = np.asarray(force_n, np.float64)
    finite = f[np.isfinite(f)]
    peak = float(finite.max()) if finite.size else math.nan
    return LayerScale(
        cmap=matplotlib.colormaps["turbo"].with_extremes(bad=NOT_SCANNED_COLOR),
        vmin=0.0,
        vmax=FORCE_FULL_SCALE_N,
        extend="max" if math.isfinite(peak) and peak > FORCE_FULL_SCALE_N else "neither",
        bar_labels=("local load (N)", "load (N)", "N"),
        title="Force map" + (f", peak {peak:.1f} N" if math.isfinite(peak) else ", not scanned"),
        caption=(
            f"Local load under the probe in newtons (N), colour scale 0 to {FORCE_FULL_SCALE_N:g} N. Grey: not scanned."
        ),
    )


def _nice_length(target_mm: float) -> float:
    """Return the largest 1-2-5 length in mm not above target_mm (at least 1 mm)."""
    best = 1.0
    for decade in (1.0, 10.0, 100.0, 1000.0):
        for step in (1.0, 2.0, 5.0):
            if step * decade <= target_mm:
                best = step * decade
    return best


def scale_bar(ax: Axes, width_mm: float, height_mm: float) -> None:
    """Draw a scale bar (mm) in the lower right corner of an image panel width_mm by height_mm."""
    length = _nice_length(0.25 * width_mm)
    bar = AnchoredSizeBar(
        ax.transData, length, f"{length:g} mm", loc="lower right", pad=0.3, borderpad=0.5, sep=2, frameon=True,
        size_vertical=min(0.05 * length, 0.02 * height_mm), color="black", fontproperties=FontProperties(size=7),
    )  # fmt: skip
    bar.patch.set_alpha(0.85)
    for text in bar.findobj(Text):
        text.set_gid(SCALEBAR_GID)
    ax.add_artist(bar)


def fit_box(aspect: float, max_w_in: float, max_h_in: float) -> tuple[float, float]:
    """Return (width, height) in inches of the largest box of that width/height ratio within the limits."""
    w = min(max_w_in, max_h_in * aspect)
    return w, w / aspect


def layer_extent(values: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> tuple[float, ...]:
    """Return (left, right, bottom, top) in mm of a layer image the size of values."""
    return _mosaic_extent(np.shape(values), px_per_mm, origin_px)


def extent_aspect(extent: tuple[float, ...]) -> float:
    """Return an extent's width / height."""
    left, right, bottom, top = extent
    return (right - left) / max(bottom - top, 1e-9)


def draw_map(
    ax: Axes,
    cax: Axes,
    values: np.ndarray,
    scale: LayerScale,
    px_per_mm: float,
    origin_px: tuple[float, float],
    mm_axes: bool,
) -> Colorbar:
    """Draw a float layer (NaN = not scanned, grey) in mm with its colour bar in cax; return the colour bar.

    mm_axes: the axes in mm with labels (a plot of its own), else no ticks and a scale bar (the sheet).
    """
    fig = ax.get_figure()
    assert isinstance(fig, Figure)
    shown = np.ma.masked_invalid(np.asarray(values, np.float64))
    extent = layer_extent(shown, px_per_mm, origin_px)
    left, right, bottom, top = extent
    im = ax.imshow(
        shown, cmap=scale.cmap, norm=Normalize(scale.vmin, scale.vmax), extent=extent, origin="upper",
        interpolation="nearest",
    )  # fmt: skip
    set_image_limits(ax, [np.array([[left, top], [right, bottom]])], margin_mm=0.0)
    if not mm_axes:
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.set_xticks([])
        ax.set_yticks([])
        scale_bar(ax, right - left, bottom - top)
    bar = fig.colorbar(im, cax=cax, extend=scale.extend, extendfrac=0.06)
    if scale.top_tick:  # integer ticks at least TICK_GAP_IN apart, the two ends labelled
        bar_in = max(cax.get_position().height * float(fig.get_size_inches()[1]), 1e-3)
        gap = (scale.vmax - scale.vmin) * min(0.5, TICK_GAP_IN / bar_in)
        inner = MaxNLocator(nbins=max(1, int(bar_in / TICK_GAP_IN)), integer=True).tick_values(scale.vmin, scale.vmax)
        ticks = [scale.vmin, *(t for t in inner if scale.vmin + gap <= t <= scale.vmax - gap)]
        bar.set_ticks([*ticks, scale.vmax], labels=[f"{t:g}" for t in ticks] + [scale.top_tick])
    bar.ax.tick_params(labelsize=9 if mm_axes else 7)
    _fit_bar_label(bar, scale.bar_labels, 10 if mm_axes else 8)
    return bar


def _fit_bar_label(bar: Colorbar, labels: Sequence[str], fontsize: float) -> None:
    """Label a vertical colour bar with the first label no longer than the bar (the last one otherwise)."""
    fig = bar.ax.get_figure()
    assert isinstance(fig, Figure)
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    height = bar.ax.get_window_extent(renderer).height
    for label in labels:
        bar.set_label(label, fontsize=fontsize)
        if bar.ax.yaxis.label.get_window_extent(renderer).height <= height:
            return


def _map_png(values: np.ndarray, scale: LayerScale, px_per_mm: float, origin_px: tuple[float, float]) -> bytes:
    """Return the PNG of one layer in mm: title, image with mm axes, colour bar of its height, caption."""
    check_scale(px_per_mm)
    w, h = fit_box(extent_aspect(layer_extent(values, px_per_mm, origin_px)), 5.9, 5.0)
    fig = Figure(figsize=(8.0, h + 1.6), dpi=DPI)
    FigureCanvasAgg(fig)
    page = Page(fig)
    _, title_h = page.text(0.9, 0.2, scale.title, width=6.8, fontsize=12)
    top = 0.2 + title_h + 0.15
    ax = fig.add_axes(page.rect(0.9, top, w, h))
    cax = fig.add_axes(page.rect(0.9 + w + 0.12, top, 0.18, h))
    draw_map(ax, cax, values, scale, px_per_mm, origin_px, mm_axes=True)
    page.text(0.9, top + h + 0.55, scale.caption, width=6.8, fontsize=9)
    return _png(fig)


def plot_force_map(force_n: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> bytes:
    """Return the PNG of the force layer in mm with its colour scale in N (grey where not scanned)."""
    return _map_png(np.asarray(force_n, np.float64), force_scale(force_n), px_per_mm, origin_px)


def plot_coverage_map(coverage: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> bytes:
    """Return the PNG of the coverage (frames per point) in mm, linear to its 95th percentile (grey: never scanned)."""
    return _map_png(coverage_values(coverage), coverage_scale(coverage), px_per_mm, origin_px)


class Page:
    """Places text and axes on a figure in inches from its top-left corner, measuring as it goes."""

    def __init__(self, fig: Figure) -> None:
        self.fig = fig
        self.w, self.h = (float(v) for v in fig.get_size_inches())
        self.renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]

    def rect(self, x: float, top: float, w: float, h: float) -> tuple[float, float, float, float]:
        """Return the figure-fraction rectangle of a box at x, top (inches from the top-left), w by h inches."""
        return x / self.w, 1.0 - (top + h) / self.h, w / self.w, h / self.h

    def height(self, artist: Text | Legend) -> float:
        """Return an artist's height in inches."""
        return float(artist.get_window_extent(self.renderer).height) / self.fig.dpi

    def move(self, text: Text, x: float, top: float) -> None:
        """Move a text's top-left anchor to x, top (inches)."""
        text.set_position((x / self.w, 1.0 - top / self.h))

    def text(
        self, x: float, top: float, s: str, width: float | None = None, hanging: bool = False, **kw: Any
    ) -> tuple[Text, float]:
        """Return a text with its top-left at x, top (inches), wrapped to width inches, and its height (inches).

        hanging: a wrapped line's continuation is indented (lists), else flush (prose).
        """
        t = self.fig.text(x / self.w, 1.0 - top / self.h, s, va="top", ha=kw.pop("ha", "left"), **kw)
        if width is not None:
            self._wrap(t, s, width, "  " if hanging else "")
        return t, self.height(t)

    def _wrap(self, t: Text, s: str, width: float, hang: str) -> None:
        limit = width * self.fig.dpi
        chars = max(12, int(width * 72.0 / (0.45 * float(t.get_fontsize()))))
        while True:
            lines = []
            for line in s.split("\n"):
                indent = line[: len(line) - len(line.lstrip())]
                lines.append(textwrap.fill(line, chars, subsequent_indent=indent + hang) if line.strip() else "")
            t.set_text("\n".join(lines))
            if t.get_window_extent(self.renderer).width <= limit or chars <= 12:
                return
            chars = max(12, int(chars * 0.93))

    def rule(self, top: float, x0: float, x1: float, lw: float = 0.8, color: str = "#444444") -> None:
        """Draw a horizontal line at top (inches) from x0 to x1 (inches)."""
        y = 1.0 - top / self.h
        self.fig.add_artist(Line2D([x0 / self.w, x1 / self.w], [y, y], lw=lw, color=color))


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Return the [start, stop) index ranges of consecutive True entries."""
    padded = np.concatenate([[False], np.asarray(flags, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def plot_error_along_scan(report: AccuracyReport) -> bytes:
    """Return the PNG of the per-frame error (mm) against frame index with the RMSE line."""
    fig, ax = _new_figure(9.0, 4.0)
    _draw_errors(ax, report)
    fig.tight_layout()
    return _png(fig)


def fmt_number(v: float) -> str:
    """Return v to 3 decimals, "n/a" when not finite."""
    return f"{v:.3f}" if math.isfinite(v) else "n/a"


def _draw_errors(ax: Axes, report: AccuracyReport) -> None:
    errors = np.asarray(report.errors_mm, dtype=np.float64)
    idx = np.arange(len(errors))
    ax.plot(idx, errors, ".-", color=ESTIMATE_COLOR, lw=1.5, ms=4, label="error")
    if math.isfinite(report.rmse_mm):
        ax.axhline(report.rmse_mm, color=REFERENCE_COLOR, ls="--", lw=1.5, label=f"RMSE {report.rmse_mm:.3f} mm")
    for j, (a, b) in enumerate(_runs(~np.isfinite(errors))):  # frames not registered or without a reference
        ax.axvspan(a - 0.5, b - 0.5, color=UNREGISTERED_COLOR, alpha=0.25, lw=0, label=None if j else "not compared")
    ax.set_xlim(-0.5, max(len(errors) - 0.5, 0.5))
    top = np.nanmax(errors) if np.any(np.isfinite(errors)) else 1.0
    ax.set_ylim(0.0, max(float(top) * 1.1, 1e-3))
    ax.set_xlabel("frame index")
    ax.set_ylabel("error (mm)")
    drift = fmt_number(report.final_drift_mm)
    ax.set_title(f"Error along the scan: max {fmt_number(report.max_error_mm)} mm, final drift {drift} mm")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")


def plot_method_comparison(
    results: Mapping[str, tuple[np.ndarray, np.ndarray]],
    reference_mm: np.ndarray | None,
) -> bytes:
    """Return the PNG of several methods' paths (mm) against the reference, RMSE in the legend."""
    if not results:
        raise ValueError("results: no method to plot")
    ref = None if reference_mm is None else check_path("reference_mm", reference_mm)
    fig, ax = _new_figure(8.0, 7.0)
    pts: list[np.ndarray] = []
    if ref is not None:
        ref_line = _finite_rows(ref)
        ax.plot(ref_line[:, 0], ref_line[:, 1], "-", color="black", lw=2.5, label="reference", zorder=2)
        pts.append(ref_line)
    for i, (name, (estimate, registered)) in enumerate(results.items()):
        est = check_path(f"results[{name!r}] estimate", estimate, None if ref is None else len(ref))
        reg = np.asarray(registered, dtype=bool).reshape(-1)
        if len(reg) != len(est):
            raise ValueError(f"results[{name!r}]: registered has {len(reg)} entries for {len(est)} frames")
        line = est[reg & np.all(np.isfinite(est), axis=1)]
        rmse = _rmse_or_none(est, reg, ref)
        label = f"{name} ({len(line)}/{len(est)} reg."
        label += f", RMSE {rmse:.3f} mm)" if rmse is not None else ")"
        color = METHOD_COLORS[i % len(METHOD_COLORS)]
        if len(line):
            ax.plot(line[:, 0], line[:, 1], "-", color=color, lw=1.8, label=label, zorder=3)
            pts.append(line)
        else:
            ax.plot([], [], "-", color=color, label=label)
    ax.set_title("Probe path by method")
    set_image_limits(ax, pts)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    return _png(fig)
