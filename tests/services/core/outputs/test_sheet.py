"""The one-page report is a clean clinical page: identification, no overlapping text, colour bars of their panels.

The sheet is built as a matplotlib Figure (build_sheet_figure), drawn once, and its artists are measured in
pixels at the sheet's own resolution (SHEET_DPI): every visible text box, every panel and colour bar.
"""

from __future__ import annotations

import itertools
import re
from datetime import UTC, datetime

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.text import Text
from matplotlib.transforms import Bbox

from services.core.inputs.study import StudyContext
from services.core.mosaic.canvas import MosaicImage
from services.core.outputs.evaluation import AccuracyReport, evaluate_angles, evaluate_path
from services.core.outputs.plots import SCALEBAR_GID
from services.core.outputs.scan_quality import FrameSummary, scan_warnings
from services.core.outputs.session_report import build_session_report
from services.core.outputs.sheet import NOT_GIVEN, SHEET_DPI, SHEET_TEXT_GID, SheetIdentity, build_sheet_figure
from services.core.path_rows import PathRow
from tests.pdf_text import pdf_text

OVERLAP_TOL_PX = 1.0  # two text boxes may touch (antialiasing, rounding) but not overlap by more than 1 px
BAR_TOL_PX = 1.0  # a colour bar's top and bottom are its panel's within 1 px
PX_PER_MM = 8.0
SESSION = "90817263544536271809192837465564"  # 32 digits, the widest hex glyphs: the longest session id
ACCESSION = "ACC-7731-Q"
STUDY = StudyContext(
    patient_id="MRN-0042317",
    patient_name="Doe^Jane",
    patient_birth_date="1971-04-09",
    patient_sex="F",
    accession_number=ACCESSION,
    laterality="L",
    referring_physician="Smith^Anna^^Dr",
    study_description="NIR vein mapping",
)
LONG_STUDY = StudyContext(  # every field at its longest: the header wraps, never runs into its neighbour
    patient_id=("0123456789ABCDEF" * 4)[:64],
    patient_name="Wolfeschlegelsteinhausenbergerdorff^Maximiliane Wilhelmina^Anna",
    patient_birth_date="1950-12-31",
    patient_sex="O",
    accession_number="W" * 16,
    laterality="R",
    referring_physician="Montgomery-Featherstonehaugh^Bartholomew^^Professor Dr",
    study_description="NIR vein mapping before reconstructive surgery, upper outer WWMM",
)
TISSUE = {
    "kappa_prior_n_per_mm": 18.0,
    "young_modulus_prior_kpa": 16.1,
    "kappa_n_per_mm": 0.1589,
    "kappa_low_n_per_mm": 0.1536,
    "kappa_high_n_per_mm": 0.1644,
    "anisotropy": 0.0193,
    "anisotropy_sigma": 0.0057,
    "anisotropy_angle_deg": 31.6,
    "anisotropy_axis": "tissue",
    "edges": 150,
    "affine_residual_rms": 0.00069,
    "affine_residual_rms_nominal": 0.00173,
    "compliance_per_n": 0.00603,
    "young_modulus_kpa": 17.28,
    "gauge": 1.00007,
    "compliance_residual_rms": 0.0022,
    "drag_kept": True,
    "drag_width_mm": 20.0,
    "drag_gain_mm_per_n": 0.0376,
    "drag_median_mm": 0.267,
}


def _mosaic(h_mm: float, w_mm: float) -> MosaicImage:
    """Return a mosaic h_mm x w_mm: stripes, a force ramp 2..24 N, coverage 1..60 frames, an unscanned corner."""
    h, w = int(h_mm * PX_PER_MM), int(w_mm * PX_PER_MM)
    yy, xx = np.mgrid[0:h, 0:w]
    vein = (120 + 60 * np.sin(xx / 9.0) * np.cos(yy / 13.0)).astype(np.uint8)
    coverage = (1 + 59 * np.exp(-(((xx - w / 2) / (0.3 * w)) ** 2 + ((yy - h / 2) / (0.3 * h)) ** 2))).astype(
        np.float32
    )
    coverage[: h // 5, : w // 6] = 0
    force = np.where(coverage > 0, 2.0 + 22.0 * xx / w, np.nan).astype(np.float32)
    return MosaicImage(vein, force, np.rint(coverage), PX_PER_MM, (w / 4, h / 2))


def _path(mosaic: MosaicImage, n: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (estimate, registered, reference) in mm: a loop inside the mosaic, frames 10, 11, 40 and 41 not placed."""
    h, w = mosaic.vein.shape
    ox, oy = mosaic.origin_px
    t = np.linspace(0.0, 2.0 * np.pi, n)
    cx, cy = (w / 2 - ox) / PX_PER_MM, (h / 2 - oy) / PX_PER_MM
    reference = np.stack([cx + 0.3 * w / PX_PER_MM * np.sin(t), cy + 0.3 * h / PX_PER_MM * np.sin(2 * t)], axis=1)
    reference -= reference[0]
    estimate = reference + np.stack([0.01 * t, -0.02 * t], axis=1)
    registered = np.ones(n, bool)
    registered[[10, 11, 40, 41]] = False
    estimate[~registered] = np.nan
    return estimate, registered, reference


def _frames(n: int = 60) -> FrameSummary:
    return FrameSummary(n, n - 4, 3, 1, {"few_inliers": 3}, {"blur": 1})  # 6.7 %: a warning


def _sheet(
    study: StudyContext | None, with_reference: bool, size_mm: tuple[float, float] = (60.0, 110.0)
) -> tuple[Figure, AccuracyReport | None]:
    mosaic = _mosaic(*size_mm)
    estimate, registered, reference = _path(mosaic)
    report = evaluate_path(estimate, registered, reference) if with_reference else None
    angles = None
    if with_reference:
        est_deg = np.zeros((len(estimate), 3))
        ref_deg = est_deg + np.array([0.05, 0.7, -0.8])
        angles = evaluate_angles(est_deg, registered, ref_deg)
    identity = SheetIdentity(SESSION, datetime(2025, 11, 23, 14, 5, tzinfo=UTC), 3, "best", study)
    frames = _frames(len(estimate))
    fig = build_sheet_figure(
        mosaic, estimate, registered, reference if with_reference else None, report, frames, scan_warnings(frames),
        identity, angles=angles, tissue=TISSUE if with_reference else None,
    )  # fmt: skip
    fig.canvas.draw()
    return fig, report


def _drawn_tick_labels(ax: Axes) -> tuple[list[Text], set[int]]:
    """Return (the tick labels drawn: ticks inside the view interval, ids of every tick label of the axes)."""
    drawn, every = [], set()
    for axis in (ax.xaxis, ax.yaxis):
        lo, hi = sorted(axis.get_view_interval())
        eps = 1e-9 * max(hi - lo, 1.0)
        for tick in axis.get_major_ticks() + axis.get_minor_ticks():
            labels = (tick.label1, tick.label2)
            every.update(id(label) for label in labels)
            loc = tick.get_loc()
            if loc is not None and lo - eps <= loc <= hi + eps:
                drawn += [label for label in labels if label.get_visible()]
    return drawn, every


def _texts(fig: Figure) -> list[Text]:
    """Return every visible, non-empty text the figure draws (tick labels only where a tick is drawn)."""
    ticks, tick_ids = [], set()
    for ax in fig.axes:
        drawn, every = _drawn_tick_labels(ax)
        ticks += drawn
        tick_ids |= every
    others = [t for t in fig.findobj(Text) if id(t) not in tick_ids]
    return [t for t in others + ticks if t.get_visible() and t.get_text().strip()]


def _box(artist: Text | Axes | Legend, fig: Figure) -> Bbox:
    return artist.get_window_extent(fig.canvas.get_renderer())  # type: ignore[attr-defined]


def _overlap_px(a: Bbox, b: Bbox) -> tuple[float, float]:
    return min(a.x1, b.x1) - max(a.x0, b.x0), min(a.y1, b.y1) - max(a.y0, b.y0)


def _sheet_axes(fig: Figure, name: str) -> Axes:
    (ax,) = [a for a in fig.axes if a.get_label() == f"sheet:{name}"]
    return ax


CASES = [
    pytest.param(None, False, id="no-study-no-reference"),
    pytest.param(None, True, id="no-study-reference"),
    pytest.param(STUDY, False, id="study-no-reference"),
    pytest.param(STUDY, True, id="study-reference"),
    pytest.param(LONG_STUDY, True, id="longest-study-fields"),
]


@pytest.mark.parametrize("size_mm", [(60.0, 110.0), (140.0, 45.0), (30.0, 220.0)], ids=["wide", "tall", "strip"])
@pytest.mark.parametrize(("study", "with_reference"), CASES)
def test_no_text_overlaps_another_and_all_is_on_the_page(
    study: StudyContext | None, with_reference: bool, size_mm: tuple[float, float]
) -> None:
    fig, _ = _sheet(study, with_reference, size_mm)
    texts = _texts(fig)
    assert len(texts) > 40  # the header, titles, captions, summaries, ticks: the test sees the page
    boxes = [(t, _box(t, fig)) for t in texts]
    page = fig.bbox
    for t, b in boxes:  # nothing cut off at the page's edges
        assert b.x0 >= page.x0 - OVERLAP_TOL_PX and b.x1 <= page.x1 + OVERLAP_TOL_PX, t.get_text()
        assert b.y0 >= page.y0 - OVERLAP_TOL_PX and b.y1 <= page.y1 + OVERLAP_TOL_PX, t.get_text()
    for (t1, b1), (t2, b2) in itertools.combinations(boxes, 2):
        w, h = _overlap_px(b1, b2)
        assert not (w > OVERLAP_TOL_PX and h > OVERLAP_TOL_PX), f"{t1.get_text()!r} overlaps {t2.get_text()!r}"
    # no text over a panel or a colour bar, the scale bars' own labels (inside their panels) apart
    panels = [(a.get_label(), _box(a, fig)) for a in fig.axes]
    for t, b in boxes:
        if t.get_gid() == SCALEBAR_GID:
            continue
        for name, p in panels:
            w, h = _overlap_px(b, p)
            assert not (w > OVERLAP_TOL_PX and h > OVERLAP_TOL_PX), f"{t.get_text()!r} is over {name}"
    # the legend is outside the path's panel (below it), not over the path
    (legend,) = fig.legends
    w, h = _overlap_px(_box(legend, fig), _box(_sheet_axes(fig, "mosaic"), fig))
    assert not (w > 0 and h > 0)


@pytest.mark.parametrize("size_mm", [(60.0, 110.0), (140.0, 45.0)], ids=["wide", "tall"])
@pytest.mark.parametrize(("study", "with_reference"), CASES)
def test_colour_bars_are_their_panels_height_with_units(
    study: StudyContext | None, with_reference: bool, size_mm: tuple[float, float]
) -> None:
    fig, _ = _sheet(study, with_reference, size_mm)
    for name, unit in (("force", "(N)"), ("coverage", "frames")):
        ax = _sheet_axes(fig, name)
        bar = ax.images[0].colorbar
        assert bar is not None and bar.ax is _sheet_axes(fig, f"{name}:bar")
        panel = _box(ax, fig)
        shown = bar.outline.get_window_extent(fig.canvas.get_renderer())  # the bar with its extension triangle
        assert panel.height > 50
        assert abs(shown.y0 - panel.y0) <= BAR_TOL_PX and abs(shown.y1 - panel.y1) <= BAR_TOL_PX, (name, shown, panel)
        assert unit in bar.ax.get_ylabel()
    coverage_bar = _sheet_axes(fig, "coverage").images[0].colorbar
    assert coverage_bar is not None and "linear" in coverage_bar.ax.get_ylabel()  # which scale, said on the bar
    top = coverage_bar.ax.get_yticklabels()[-1].get_text()
    assert top.endswith("= P95") and coverage_bar.extend == "max"  # its top: the 95th percentile, more in pink


@pytest.mark.parametrize(("study", "with_reference"), CASES)
def test_no_line_is_repeated(study: StudyContext | None, with_reference: bool) -> None:
    fig, _ = _sheet(study, with_reference)
    ticks = {id(t) for ax in fig.axes for t in _drawn_tick_labels(ax)[0]}
    lines = [
        line.strip()
        for t in _texts(fig)
        if id(t) not in ticks and t.get_gid() != SCALEBAR_GID
        for line in t.get_text().split("\n")
        if line.strip() and line.strip() != NOT_GIVEN
    ]
    repeated = sorted({line for line in lines if lines.count(line) > 1})
    assert not repeated, repeated


def _all_text(fig: Figure) -> str:
    """Return the figure's texts with wrapped lines joined again (whitespace runs as one space)."""
    return re.sub(r"\s+", " ", "\n".join(t.get_text() for t in _texts(fig)))


def test_identification_is_shown_when_given() -> None:
    fig, report = _sheet(STUDY, True)
    text = _all_text(fig)
    for shown in (ACCESSION, "MRN-0042317", "Doe, Jane", "1971-04-09", "female", "left breast", "Dr Smith, Anna"):
        assert shown in text, shown
    assert SESSION in text and "2025-11-23 14:05 UTC" in text and "NIR vein mapping" in text
    values = [t.get_text() for t in _texts(fig) if t.get_gid() == SHEET_TEXT_GID]
    assert "3" in values and "best" in values  # results version and method
    assert SESSION in values  # the session id on one line, never broken
    # accuracy, angles, tissue, lost frames: each figure once, in its units
    assert report is not None and f"RMSE {report.rmse_mm:.3f} mm" in text
    assert "yaw RMS error 0.05°" in text and "0.70° (x)" in text
    assert "effective kappa 0.159 N/mm" in text and "68 % range 0.154 to 0.164 N/mm" in text
    assert "anisotropy 0.019 ± 0.006" in text and "axis +32° fixed in the tissue" in text
    assert "skin drag 0.038 mm/N along the strokes" in text and "median 0.27 mm at the centre, width 20 mm" in text
    assert "lost: 3 (few inliers 3)" in text and "rejected: 1 (blur 1)" in text
    assert "WARNING: 4 of 60 frames" in text


def test_identification_is_never_invented() -> None:
    fig, _ = _sheet(None, False)
    texts = _texts(fig)
    text = _all_text(fig)
    assert ACCESSION not in text and "MRN" not in text and "breast" not in text and "Doe" not in text
    assert sum(t.get_text() == NOT_GIVEN for t in texts) == 8  # the study's eight fields; session, time, method given
    assert "no reference track: not measured" in text and "not in this report" in text


def test_sheet_renders_one_a4_portrait_page_through_the_report_builder() -> None:
    mosaic = _mosaic(60.0, 110.0)
    estimate, registered, _ = _path(mosaic)
    nan = float("nan")
    rows = [
        PathRow(i, 0.1 * i, float(x), float(y), 0.0, 5.0, 0.0, 0.0, 1.0, 80, "ok", "")
        if ok
        else PathRow(i, 0.1 * i, nan, nan, nan, 5.0, 0.0, 0.0, 1.0, 0, "lost", "few_inliers")
        for i, ((x, y), ok) in enumerate(zip(estimate, registered, strict=True))
    ]
    session = "5ffa0e91c2d84b7fb1e0c3d2a4f6e8ff"  # "ff": no ligature glyph in an id, the PDF's text has it whole
    identity = SheetIdentity(session, None, None, "best", StudyContext(accession_number=ACCESSION))
    report = build_session_report(rows, None, mosaic, {"tissue": TISSUE}, identity=identity)
    png, pdf = report.images["sheet.png"], report.images["sheet.pdf"]
    assert png.startswith(b"\x89PNG")
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert abs(width - 8.27 * SHEET_DPI) <= 1 and abs(height - 11.69 * SHEET_DPI) <= 1  # A4 portrait
    assert pdf.startswith(b"%PDF") and len(re.findall(rb"/Type\s*/Page\b", pdf)) == 1
    media = re.search(rb"/MediaBox\s*\[\s*0\s+0\s+([\d.]+)\s+([\d.]+)\s*\]", pdf)
    assert media is not None and abs(float(media[1]) - 595.4) < 1 and abs(float(media[2]) - 841.7) < 1  # A4 pt
    assert ACCESSION in pdf_text(pdf) and session in pdf_text(
        pdf
    )  # the identification is in the PDF's text, not only its image
