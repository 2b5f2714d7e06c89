"""The accuracy plots render real PNGs (bytes) that actually show the paths."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.core.outputs.evaluation import evaluate_path
from services.core.outputs.plots import (
    ESTIMATE_COLOR,
    METHOD_COLORS,
    OVER_SCANNED_COLOR,
    REFERENCE_COLOR,
    coverage_scale,
    coverage_scale_top,
    plot_coverage_map,
    plot_error_along_scan,
    plot_force_map,
    plot_method_comparison,
    plot_paths_over_mosaic,
)


def _bgr(hex_color: str) -> np.ndarray:
    h = hex_color.lstrip("#")
    r, g, b = (int(h[i : i + 2], 16) for i in (0, 2, 4))
    return np.array([b, g, r], dtype=np.int16)


def _colour_mask(img: np.ndarray, hex_color: str, tol: int = 12) -> np.ndarray:
    # Line centres are drawn in the exact colour; antialiased edges blend, hence a small tolerance.
    return np.all(np.abs(img.astype(np.int16) - _bgr(hex_color)) <= tol, axis=2)


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"{path} is not a readable PNG"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return img


def _paths(n: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.linspace(0, 1, n)
    reference = np.stack([40 * t, 10 * np.sin(2 * np.pi * t)], axis=1)
    estimate = reference + np.stack([0.5 * t, 0.3 * t], axis=1)
    registered = np.ones(n, bool)
    registered[[10, 11, 25]] = False
    estimate[~registered] = np.nan
    return estimate, registered, reference


def test_paths_over_mosaic_draws_both_paths(tmp_path: Path) -> None:
    estimate, registered, reference = _paths()
    mosaic = np.random.default_rng(0).integers(0, 60, size=(200, 420), dtype=np.uint8)  # dark, no red/blue
    out = tmp_path / "paths.png"
    out.write_bytes(
        plot_paths_over_mosaic(estimate, registered, reference, mosaic, px_per_mm=8.0, origin_px=(40.0, 100.0))
    )
    img = _read(out)
    assert img.shape[0] >= 300 and img.shape[1] >= 300
    # Each path is a long line of several hundred pixels of its own colour.
    assert _colour_mask(img, ESTIMATE_COLOR).sum() > 200
    assert _colour_mask(img, REFERENCE_COLOR).sum() > 200


def test_path_goes_right_and_y_axis_points_down(tmp_path: Path) -> None:
    # A straight path heading to +x and +y (down-right in image axes): its pixels must run from the
    # upper-left to the lower-right of the PNG, i.e. y is drawn downward.
    n = 30
    est = np.stack([np.linspace(0, 30, n), np.linspace(0, 30, n)], axis=1)
    out = tmp_path / "diag.png"
    out.write_bytes(plot_paths_over_mosaic(est, np.ones(n, bool), None, None, px_per_mm=8.0, origin_px=(0.0, 0.0)))
    red = _colour_mask(_read(out), ESTIMATE_COLOR).astype(np.uint8)
    # The path is the largest red component (the legend holds a short red sample too).
    _, labels, stats, _ = cv2.connectedComponentsWithStats(red, connectivity=8)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    ys, xs = np.nonzero(labels == biggest)
    assert len(xs) > 100
    assert np.corrcoef(xs, ys)[0, 1] > 0.9  # image rows grow with columns: down-right


def test_mosaic_is_placed_in_mm_extent(tmp_path: Path) -> None:
    # A mosaic that is black with one white square; with no path the plot still shows the mosaic pixels.
    mosaic = np.zeros((100, 100), np.uint8)
    mosaic[40:60, 40:60] = 255
    out = tmp_path / "mosaic_only.png"
    est = np.array([[0.0, 0.0]])
    out.write_bytes(plot_paths_over_mosaic(est, np.array([True]), None, mosaic, px_per_mm=10.0, origin_px=(50.0, 50.0)))
    img = _read(out)
    white = np.all(img >= 250, axis=2)
    black = np.all(img <= 5, axis=2)
    assert black.sum() > 1000  # the mosaic's black area is drawn
    assert white.sum() > 0


def test_error_along_scan(tmp_path: Path) -> None:
    estimate, registered, reference = _paths()
    report = evaluate_path(estimate, registered, reference)
    out = tmp_path / "err.png"
    out.write_bytes(plot_error_along_scan(report))
    img = _read(out)
    assert img.shape[1] > img.shape[0]  # wide figure
    assert _colour_mask(img, ESTIMATE_COLOR).sum() > 100  # error curve
    assert _colour_mask(img, REFERENCE_COLOR).sum() > 50  # RMSE line


def test_method_comparison(tmp_path: Path) -> None:
    estimate, registered, reference = _paths()
    worse = reference + 3.0
    results = {"ours": (estimate, registered), "sfm": (worse, np.ones(len(reference), bool))}
    out = tmp_path / "cmp.png"
    out.write_bytes(plot_method_comparison(results, reference))
    img = _read(out)
    assert _colour_mask(img, METHOD_COLORS[0]).sum() > 200
    assert _colour_mask(img, METHOD_COLORS[1]).sum() > 200


def test_bad_input_is_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="registered"):
        plot_paths_over_mosaic(np.zeros((3, 2)), np.ones(2, bool), None, None, 8.0, (0, 0))
    with pytest.raises(ValueError, match="no method"):
        plot_method_comparison({}, None)


def test_reference_stays_visible_on_a_perfect_estimate(tmp_path: Path) -> None:
    # estimate == reference: before, the estimate was drawn over the reference and hid it entirely
    reference = _paths()[2]
    out = tmp_path / "paths.png"
    out.write_bytes(
        plot_paths_over_mosaic(reference.copy(), np.ones(len(reference), bool), reference, None, 8.0, (0.0, 0.0))
    )
    img = _read(out)
    assert _colour_mask(img, REFERENCE_COLOR).sum() > 150
    assert _colour_mask(img, ESTIMATE_COLOR).sum() > 150


def test_force_and_coverage_maps_have_colour_scales(tmp_path: Path) -> None:
    force = np.full((80, 120), np.nan, np.float32)
    force[10:70, 10:110] = np.linspace(0, 30, 100, dtype=np.float32)
    coverage = np.where(np.isfinite(force), 3.0, 0.0).astype(np.float32)
    (tmp_path / "force_map.png").write_bytes(plot_force_map(force, 8.0, (60.0, 40.0)))
    (tmp_path / "coverage_map.png").write_bytes(plot_coverage_map(coverage, 8.0, (60.0, 40.0)))
    for name in ("force_map.png", "coverage_map.png"):
        img = _read(tmp_path / name)
        # a colour bar: a tall, narrow, strongly coloured column right of the image
        colourful = np.ptp(img.astype(np.int16), axis=2) > 60
        right = colourful[:, int(0.75 * img.shape[1]) :]
        assert right.any(axis=1).sum() > 0.5 * img.shape[0], name


def test_coverage_scale_shows_under_and_over_scanned_areas_on_a_normal_scan(tmp_path: Path) -> None:
    # a normal scan: most points seen by 10 to 45 frames, the edges by a few; the tile layer's fixed 10-frame
    # top made all of it one flat colour
    yy, xx = np.mgrid[0:80, 0:120]
    coverage = np.rint(3 + 42 * np.exp(-((xx - 60) ** 2 + (yy - 40) ** 2) / 1500.0)).astype(np.float32)
    coverage[:10, :15] = 0  # never scanned
    seen = coverage[coverage > 0]
    assert np.mean(seen >= 10) > 0.5  # a fixed 10-frame top would saturate most of the area
    top = coverage_scale_top(coverage)
    assert top == math.ceil(np.percentile(seen, 95)) and top > 10
    scale = coverage_scale(coverage)
    assert (scale.vmin, scale.vmax, scale.extend) == (1.0, top, "max")
    assert np.mean(seen > top) <= 0.05  # only the most scanned 5 % beyond the top (in the "over" colour)
    assert "95th percentile" in scale.caption and "linear" in scale.bar_labels[0] and scale.top_tick == f"{top} = P95"
    assert coverage_scale_top(np.zeros((4, 4))) == 2  # nothing seen: still a scale
    (tmp_path / "coverage_map.png").write_bytes(plot_coverage_map(coverage, 8.0, (60.0, 40.0)))
    img = _read(tmp_path / "coverage_map.png")
    assert _colour_mask(img, OVER_SCANNED_COLOR, tol=3).sum() > 100  # the over-scanned centre shows, in pink


def test_each_stroke_is_its_own_line_never_joined_through_the_air() -> None:
    from services.core.outputs.plots import stroke_lines

    points = np.array([[0.0, 0.0], [1.0, 0.0], [np.nan, np.nan], [5.0, 3.0], [6.0, 3.0], [7.0, 3.0], [2.0, 0.0]])
    strokes = np.array([0, 0, -1, 1, 1, 1, -1])  # row 2 in the air; row 6 placed but in no stroke (not drawn)
    lines = stroke_lines(points, np.ones(7, bool), strokes)
    assert [line.tolist() for line in lines] == [[[0.0, 0.0], [1.0, 0.0]], [[5.0, 3.0], [6.0, 3.0], [7.0, 3.0]]]
    keep = np.array([True, True, True, True, False, True, True])  # an unplaced frame drops out of its stroke's line
    assert [len(line) for line in stroke_lines(points, keep, strokes)] == [2, 2]
    assert [len(line) for line in stroke_lines(points, np.ones(7, bool), None)] == [6]  # no strokes known: one line
