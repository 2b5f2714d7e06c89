"""Plots (spec §4): paths over the mosaic, error along the scan, force and coverage maps, method comparison,
and the one-page session report (PNG and PDF), each with units and colour scales.

Uses matplotlib's object API with the Agg canvas, so no pyplot global state and no display is needed.
Axes are the mosaic's: x to the right, y DOWN (image axes), in mm relative to frame 0's centre.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from services.core.evaluation import AccuracyReport, evaluate_path
from services.core.layer_images import COVERAGE_FULL_SCALE
from services.core.mosaic import FORCE_FULL_SCALE_N, MosaicImage
from services.core.scan_quality import FrameSummary

ESTIMATE_COLOR = "#d62728"  # red: the estimated path
REFERENCE_COLOR = "#1f77b4"  # blue: the reference track
UNREGISTERED_COLOR = "#ff7f0e"  # orange crosses: frames not registered
METHOD_COLORS = ("#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
DPI = 100


def _new_figure(width_in: float, height_in: float) -> tuple[Figure, Axes]:
    fig = Figure(figsize=(width_in, height_in), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _check_path(name: str, value: np.ndarray, n: int | None = None) -> np.ndarray:
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


def _set_image_limits(ax: Axes, points: list[np.ndarray], margin_mm: float = 2.0) -> None:
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


def _check_scale(px_per_mm: float) -> None:
    if not (px_per_mm > 0 and math.isfinite(px_per_mm)):
        raise ValueError(f"px_per_mm: must be a positive number, got {px_per_mm}")


def _draw_paths(
    ax: Axes,
    est: np.ndarray,
    reg: np.ndarray,
    ref: np.ndarray | None,
    mosaic: np.ndarray | None,
    px_per_mm: float,
    origin_px: tuple[float, float],
) -> tuple[int, int]:
    """Draw the mosaic, the estimate under the reference (both visible), start/end and unplaced frames."""
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
    if len(est_line):  # the estimate wide and underneath, the reference thin and dashed on top: both show
        ax.plot(est_line[:, 0], est_line[:, 1], "-", color=ESTIMATE_COLOR, lw=3.0, label="estimate")
        extent_pts.append(est_line)
    if ref is not None:
        ref_line = _finite_rows(ref)
        ax.plot(ref_line[:, 0], ref_line[:, 1], "--", color=REFERENCE_COLOR, lw=1.4, label="reference", zorder=3)
        extent_pts.append(ref_line)
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
    _set_image_limits(ax, extent_pts if extent_pts else [np.zeros((1, 2))])
    ax.legend(loc="best", fontsize="small")
    return int(placed.sum()), n


def plot_paths_over_mosaic(
    estimate_mm: np.ndarray,
    registered: np.ndarray,
    reference_mm: np.ndarray | None,
    mosaic: np.ndarray | None,
    px_per_mm: float,
    origin_px: tuple[float, float],
) -> bytes:
    """Return the PNG of the estimated (and reference) path in mm over the mosaic.

    origin_px is the mosaic pixel (x, y) where frame 0's centre, (0, 0) mm, lies (spec §4 mosaic.json).
    """
    est = _check_path("estimate_mm", estimate_mm)
    n = len(est)
    reg = np.asarray(registered, dtype=bool).reshape(-1)
    if len(reg) != n:
        raise ValueError(f"registered: expected {n} entries, got {len(reg)}")
    ref = None if reference_mm is None else _check_path("reference_mm", reference_mm, n)
    _check_scale(px_per_mm)
    fig, ax = _new_figure(8.0, 7.0)
    placed, _ = _draw_paths(ax, est, reg, ref, mosaic, px_per_mm, origin_px)
    rmse = _rmse_or_none(est, reg, ref)
    title = f"Probe path: {placed}/{n} frames registered"
    if rmse is not None and math.isfinite(rmse):
        title += f", RMSE {rmse:.3f} mm"
    ax.set_title(title)
    fig.tight_layout()
    return _png(fig)


def _draw_layer(
    ax: Axes,
    values: np.ndarray,
    px_per_mm: float,
    origin_px: tuple[float, float],
    cmap: str,
    vmin: float,
    vmax: float,
    label: str,
    title: str,
) -> None:
    """Draw a float layer (NaN = not scanned, shown in light grey) in mm with a labelled colour bar."""
    fig = ax.get_figure()
    assert fig is not None
    shown = np.ma.masked_invalid(np.asarray(values, np.float64))
    cm = matplotlib.colormaps[cmap].with_extremes(bad="#d9d9d9")
    left, right, bottom, top = _mosaic_extent(shown.shape, px_per_mm, origin_px)
    im = ax.imshow(
        shown, cmap=cm, vmin=vmin, vmax=vmax, extent=(left, right, bottom, top), origin="upper", interpolation="nearest"
    )
    bar = fig.colorbar(im, ax=ax, shrink=0.85)
    bar.set_label(label)
    _set_image_limits(ax, [np.array([[left, top], [right, bottom]])], margin_mm=0.0)
    ax.set_title(title)


def _coverage_values(coverage: np.ndarray) -> np.ndarray:
    cov = np.nan_to_num(np.asarray(coverage, np.float64))
    return np.where(cov >= 0.5, np.rint(cov), np.nan)


def _draw_force(ax: Axes, force_n: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> None:
    f = np.asarray(force_n, np.float64)
    peak = float(np.nanmax(f)) if np.any(np.isfinite(f)) else float("nan")
    title = "Force layer (grey: not scanned)" + (f", peak {peak:.1f} N" if math.isfinite(peak) else "")
    _draw_layer(ax, f, px_per_mm, origin_px, "turbo", 0.0, FORCE_FULL_SCALE_N, "local load (N)", title)


def _draw_coverage(ax: Axes, coverage: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> None:
    values = _coverage_values(coverage)
    _draw_layer(
        ax, values, px_per_mm, origin_px, "viridis", 1.0, float(COVERAGE_FULL_SCALE),
        f"frames that saw the point ({COVERAGE_FULL_SCALE}+ saturates)", "Coverage (grey: never scanned)",
    )  # fmt: skip


def plot_force_map(force_n: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> bytes:
    """Return the PNG of the force layer in mm with its colour scale in N (grey where not scanned)."""
    _check_scale(px_per_mm)
    fig, ax = _new_figure(8.0, 6.5)
    _draw_force(ax, force_n, px_per_mm, origin_px)
    fig.tight_layout()
    return _png(fig)


def plot_coverage_map(coverage: np.ndarray, px_per_mm: float, origin_px: tuple[float, float]) -> bytes:
    """Return the PNG of the coverage (frames per point) in mm with its colour scale (grey: never scanned)."""
    _check_scale(px_per_mm)
    fig, ax = _new_figure(8.0, 6.5)
    _draw_coverage(ax, coverage, px_per_mm, origin_px)
    fig.tight_layout()
    return _png(fig)


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


def _fmt(v: float) -> str:
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
    drift = _fmt(report.final_drift_mm)
    ax.set_title(f"Error along the scan: max {_fmt(report.max_error_mm)} mm, final drift {drift} mm")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")


def plot_method_comparison(
    results: Mapping[str, tuple[np.ndarray, np.ndarray]],
    reference_mm: np.ndarray | None,
) -> bytes:
    """Return the PNG of several methods' paths (mm) against the reference, RMSE in the legend."""
    if not results:
        raise ValueError("results: no method to plot")
    ref = None if reference_mm is None else _check_path("reference_mm", reference_mm)
    fig, ax = _new_figure(8.0, 7.0)
    pts: list[np.ndarray] = []
    if ref is not None:
        ref_line = _finite_rows(ref)
        ax.plot(ref_line[:, 0], ref_line[:, 1], "-", color="black", lw=2.5, label="reference", zorder=2)
        pts.append(ref_line)
    for i, (name, (estimate, registered)) in enumerate(results.items()):
        est = _check_path(f"results[{name!r}] estimate", estimate, None if ref is None else len(ref))
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
    _set_image_limits(ax, pts)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    fig.tight_layout()
    return _png(fig)


def session_sheet(
    mosaic: MosaicImage,
    estimate_mm: np.ndarray,
    registered: np.ndarray,
    reference_mm: np.ndarray | None,
    report: AccuracyReport | None,
    frames: FrameSummary,
    warnings: Sequence[Mapping[str, str]],
    heading: str,
) -> tuple[bytes, bytes]:
    """Return the one-page session report as (PNG bytes, PDF bytes): mosaic with path, force, coverage, summary."""
    est = _check_path("estimate_mm", estimate_mm)
    reg = np.asarray(registered, dtype=bool).reshape(-1)
    if len(reg) != len(est):
        raise ValueError(f"registered: expected {len(est)} entries, got {len(reg)}")
    ref = None if reference_mm is None else _check_path("reference_mm", reference_mm, len(est))
    _check_scale(mosaic.px_per_mm)
    fig = Figure(figsize=(16.5, 11.7), dpi=DPI)  # A3 landscape: readable when printed on A4 too
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(2, 3, height_ratios=(1.35, 1.0))
    ax_path = fig.add_subplot(grid[0, 0])
    placed, n = _draw_paths(ax_path, est, reg, ref, mosaic.vein, mosaic.px_per_mm, mosaic.origin_px)
    ax_path.set_title(f"Mosaic and probe path ({placed}/{n} frames placed)")
    _draw_force(fig.add_subplot(grid[0, 1]), mosaic.force_n, mosaic.px_per_mm, mosaic.origin_px)
    _draw_coverage(fig.add_subplot(grid[0, 2]), mosaic.coverage, mosaic.px_per_mm, mosaic.origin_px)
    ax_err = fig.add_subplot(grid[1, 0:2])
    if report is not None:
        _draw_errors(ax_err, report)
    else:
        ax_err.axis("off")
        ax_err.text(0.5, 0.5, "no reference track: accuracy not measured", ha="center", va="center", fontsize=13)
    ax_text = fig.add_subplot(grid[1, 2])
    ax_text.axis("off")
    lines = [
        f"frames: {frames.n_frames}, placed {frames.n_ok} ({100 * frames.registered_fraction:.1f} %)",
        f"lost: {frames.n_lost}" + "".join(f"\n    {k.replace('_', ' ')}: {v}" for k, v in frames.lost_reasons.items()),
        f"rejected: {frames.n_rejected}"
        + "".join(f"\n    {k.replace('_', ' ')}: {v}" for k, v in frames.rejected_reasons.items()),
    ]
    if report is not None:
        lines.append("accuracy: " + report.summary().replace(" — ", "\n    ").replace("; ", "\n    "))
    ax_text.text(0.0, 1.0, "\n".join(lines), va="top", ha="left", fontsize=11, family="monospace", wrap=True)
    if warnings:
        text = "\n".join("WARNING: " + w["message"] for w in warnings)
        ax_text.text(0.0, 0.0, text, va="bottom", ha="left", fontsize=10, color="#b00000", wrap=True)
    fig.suptitle(heading, fontsize=15)
    fig.tight_layout()
    png, pdf = io.BytesIO(), io.BytesIO()
    fig.savefig(png, format="png", dpi=DPI)
    fig.savefig(pdf, format="pdf")
    return png.getvalue(), pdf.getvalue()
