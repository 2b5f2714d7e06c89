"""The one-page session report (spec §4): an A4 sheet, as a PDF and a PNG of the same page, identifying the
patient and examination as the caller knows them, with the path over the mosaic, the force and coverage maps
with their colour scales, and the scan's frames, accuracy, tissue and warnings in words.

Laid out in inches from the page's top-left corner (plots.Page), with the drawing pieces of
services.core.outputs.plots; matplotlib's object API with the Agg canvas, no pyplot global state.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from types import MappingProxyType
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

from services.core.inputs.study import StudyContext
from services.core.mosaic.canvas import MosaicImage
from services.core.outputs.evaluation import AccuracyReport
from services.core.outputs.plots import (
    Page,
    check_path,
    check_scale,
    coverage_scale,
    coverage_values,
    draw_map,
    draw_paths,
    extent_aspect,
    fit_box,
    fmt_number,
    force_scale,
    layer_extent,
    scale_bar,
    set_image_limits,
)
from services.core.outputs.scan_quality import FrameSummary

SHEET_TEXT_GID = "sheet-text"  # the gid of the sheet's identification values and summary texts

SHEET_SIZE_IN = (8.27, 11.69)  # A4 portrait
SHEET_DPI = 150  # the PNG: 1240 x 1754 px
SHEET_TITLE = "NIR vein mosaic: scan report"
NOT_GIVEN = "not given"
SEX_NAMES = MappingProxyType({"M": "male", "F": "female", "O": "other"})
LATERALITY_NAMES = MappingProxyType({"L": "left breast", "R": "right breast"})
_MARGIN, _TOP, _BOTTOM = 0.6, 0.45, 0.4  # inches
_CONTENT_W = SHEET_SIZE_IN[0] - 2 * _MARGIN
_MAP_GAP = 0.35  # between the force and the coverage cells
_BAR_PAD, _BAR_W, _BAR_TEXT = 0.07, 0.14, 0.75  # colour bar: gap to its panel, width, its ticks and label
_STACK_ASPECT = 2.2  # force and coverage wider than this (width / height) go one above the other


@dataclass(frozen=True)
class SheetIdentity:
    """What a one-page report is about, as the caller knows it; nothing missing is ever invented."""

    session: str  # the session id (the service) or the scan's label (offline)
    scan_time: datetime | None = None
    results_version: int | None = None
    method: str | None = None
    study: StudyContext | None = None  # the patient and order, when the integrator gave them


def _person_name(pn: str) -> str:
    """Return a DICOM person name 'Family^Given^Middle^Prefix^Suffix' as 'Prefix Family, Given Middle Suffix'."""
    parts = [p.strip() for p in pn.split("=")[0].split("^")] + [""] * 5
    family, given, middle, prefix, suffix = parts[:5]
    rest = " ".join(p for p in (given, middle) if p)
    name = f"{family}, {rest}" if family and rest else family or rest
    return " ".join(p for p in (prefix, name, suffix) if p)


def _when(t: datetime | None) -> str:
    """Return a date and time to the minute with its UTC offset ('' for None)."""
    if t is None:
        return ""
    text = t.strftime("%Y-%m-%d %H:%M")
    offset = t.utcoffset()
    if offset is None:
        return text
    if not offset:
        return text + " UTC"
    minutes = int(offset.total_seconds() // 60)
    sign = "+" if minutes >= 0 else "-"
    return f"{text} UTC{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"


def _identity_fields(identity: SheetIdentity) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """Return the header's (patient, examination) rows of (label, value); '' where not given."""
    s = identity.study or StudyContext()
    patient = [
        ("Patient name", _person_name(s.patient_name)),
        ("Patient ID", s.patient_id),
        ("Birth date", s.patient_birth_date),
        ("Sex", SEX_NAMES.get(s.patient_sex, s.patient_sex)),
        ("Laterality", LATERALITY_NAMES.get(s.laterality, s.laterality)),
        ("Referring physician", _person_name(s.referring_physician)),
    ]
    exam = [
        ("Accession number", s.accession_number),
        ("Session / scan", identity.session),
        ("Scan date and time", _when(identity.scan_time)),
        ("Results version", "" if identity.results_version is None else str(identity.results_version)),
        ("Method", identity.method or ""),
        ("Study description", s.study_description),
    ]
    return patient, exam


def _field(page: Page, x: float, top: float, label: str, value: str, label_w: float, value_w: float) -> float:
    """Draw one 'label  value' row of the header; return its height in inches."""
    _, h_label = page.text(x, top + 0.015, label, width=label_w - 0.06, fontsize=7, color="#555555")
    style: dict[str, Any] = {"fontsize": 8.5, "gid": SHEET_TEXT_GID}
    if not value:
        value, style = NOT_GIVEN, {**style, "color": "#888888", "style": "italic"}
    _, h_value = page.text(x + label_w, top, value, width=value_w, **style)
    return max(h_label, h_value)


def _draw_header(page: Page, identity: SheetIdentity) -> float:
    """Draw the title and the identification block; return the top of what follows (inches)."""
    right = _MARGIN + _CONTENT_W
    _, h = page.text(_MARGIN, _TOP, SHEET_TITLE, fontsize=15, fontweight="bold", color="#1a1a1a")
    y = _TOP + h + 0.08
    page.rule(y, _MARGIN, right, lw=1.4, color="#1a1a1a")
    y += 0.1
    # (x, label width, value width, heading): the examination's values are wider (a 32-digit session id)
    exam_x = _MARGIN + 3.2 + 0.25
    cols = ((_MARGIN, 1.15, 3.2 - 1.15, "Patient"), (exam_x, 1.1, right - exam_x - 1.1, "Examination"))
    heads = [page.text(x, y, name, fontsize=9, fontweight="bold", color="#1f3d7a")[1] for x, _, _, name in cols]
    y += max(heads) + 0.06
    patient, exam = _identity_fields(identity)
    for row in zip(patient, exam, strict=True):
        heights = [
            _field(page, x, y, label, value, label_w, value_w)
            for (x, label_w, value_w, _), (label, value) in zip(cols, row, strict=True)
        ]
        y += max(heights) + 0.045
    y += 0.04
    page.rule(y, _MARGIN, right, lw=0.6, color="#888888")
    return y + 0.12


def _frames_lines(frames: FrameSummary) -> list[str]:
    def reasons(counts: Mapping[str, int]) -> str:
        text = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counts.items())
        return f" ({text})" if text else ""

    air = [f"taken off the skin (not counted): {frames.n_no_contact}"] if frames.n_no_contact else []
    return [
        f"received: {frames.n_frames}",
        *air,
        f"placed (registered): {frames.n_ok} ({100 * frames.registered_fraction:.1f} %)",
        f"lost: {frames.n_lost}{reasons(frames.lost_reasons)}",
        f"rejected: {frames.n_rejected}{reasons(frames.rejected_reasons)}",
    ]


def _number(doc: Mapping[str, Any] | None, key: str) -> float | None:
    value = (doc or {}).get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def _accuracy_lines(report: AccuracyReport | None, angles: Mapping[str, Any] | None) -> list[str]:
    if report is None:
        return ["no reference track: not measured"]
    if not report.meaningful:
        return [f"not measurable: {report.n_compared} frame(s) compared with the reference"]
    lines = [
        f"RMSE {report.rmse_mm:.3f} mm",
        f"max error {fmt_number(report.max_error_mm)} mm",
        f"final drift {fmt_number(report.final_drift_mm)} mm",
    ]
    if math.isfinite(report.error_ratio_pct):
        lines.append(f"drift / path length {report.error_ratio_pct:.3f} % of {report.path_length_mm:.0f} mm")
    lines.append(f"compared: {report.n_compared} of {report.n_frames} frames")
    yaw, tx, ty = (_number(angles, f"{k}_rmse_deg") for k in ("yaw", "tilt_x", "tilt_y"))
    if yaw is not None:
        lines.append(f"yaw RMS error {yaw:.2f}°")
    if tx is not None or ty is not None:
        tilts = ", ".join(f"{v:.2f}° ({k})" for k, v in (("x", tx), ("y", ty)) if v is not None)
        lines.append(f"tilt RMS error {tilts}")
    return lines


def _tissue_lines(tissue: Mapping[str, Any] | None) -> list[str]:
    if not tissue:
        return ["not in this report"]
    lines = []
    kappa, prior = _number(tissue, "kappa_n_per_mm"), _number(tissue, "kappa_prior_n_per_mm")
    low, high = _number(tissue, "kappa_low_n_per_mm"), _number(tissue, "kappa_high_n_per_mm")
    if kappa is not None:
        lines.append(f"effective kappa {kappa:.3g} N/mm")
        if low is not None and high is not None:
            lines.append(f"  68 % range {low:.3g} to {high:.3g} N/mm")
        if prior is not None:
            lines.append(f"  calibration prior {prior:.3g} N/mm")
    elif prior is not None:
        lines.append(f"kappa not fitted (calibration {prior:.3g} N/mm)")
    anisotropy, sigma = _number(tissue, "anisotropy"), _number(tissue, "anisotropy_sigma")
    if anisotropy is not None:
        lines.append(f"anisotropy {anisotropy:.3f}" + (f" ± {sigma:.3f}" if sigma is not None else ""))
        angle, axis = _number(tissue, "anisotropy_angle_deg"), tissue.get("anisotropy_axis")
        if angle is not None and axis in ("probe", "tissue"):
            lines.append(f"  axis {angle:+.0f}° " + ("in the probe" if axis == "probe" else "fixed in the tissue"))
    residual, nominal = _number(tissue, "affine_residual_rms"), _number(tissue, "affine_residual_rms_nominal")
    if residual is not None:
        edges = _number(tissue, "edges")
        lines.append(f"affine residual {100 * residual:.3f} %" + (f" ({edges:.0f} matches)" if edges else ""))
        if nominal is not None:
            lines.append(f"  with the calibration's kappa {100 * nominal:.3f} %")
    modulus, modulus_prior = _number(tissue, "young_modulus_kpa"), _number(tissue, "young_modulus_prior_kpa")
    if modulus is not None:
        lines.append(f"Young's modulus {modulus:.1f} kPa" + (f" (prior {modulus_prior:.1f})" if modulus_prior else ""))
    compliance, gauge = _number(tissue, "compliance_per_n"), _number(tissue, "gauge")
    if compliance is not None:
        lines.append(f"compliance {compliance:.4f} /N" + (f", gauge {gauge:.3f}" if gauge is not None else ""))
    lines.extend(_drag_lines(tissue))
    return lines or ["not fitted"]


def _drag_lines(tissue: Mapping[str, Any]) -> list[str]:
    """Return the skin drag's lines (physics.drag's fit: "tissue" drag_*), or none when it was not fitted."""
    if "drag_kept" not in tissue:
        return []
    if not tissue["drag_kept"]:
        return ["skin drag: none found"]
    gain, median, width = (_number(tissue, k) for k in ("drag_gain_mm_per_n", "drag_median_mm", "drag_width_mm"))
    if gain is None or median is None or width is None:
        return []
    return [
        f"skin drag {gain:.3f} mm/N along the strokes",
        f"  median {median:.2f} mm at the centre, width {width:.0f} mm",
    ]


def _text_blocks(page: Page, blocks: Sequence[tuple[str, list[str]]]) -> tuple[list[tuple[Text, Text]], float]:
    """Create the bottom columns (heading, body) at the page's top; return them and their height (inches)."""
    gap = 0.25
    col_w = (_CONTENT_W - gap * (len(blocks) - 1)) / len(blocks)
    out, height = [], 0.0
    for k, (heading, lines) in enumerate(blocks):
        x = _MARGIN + k * (col_w + gap)
        head, h_head = page.text(x, 0.0, heading, width=col_w, fontsize=9, fontweight="bold", color="#1f3d7a")
        body, h_body = page.text(x, 0.0, "\n".join(lines), width=col_w, hanging=True, fontsize=8, gid=SHEET_TEXT_GID)
        out.append((head, body))
        height = max(height, h_head + 0.06 + h_body)
    return out, height


def build_sheet_figure(
    mosaic: MosaicImage,
    estimate_mm: np.ndarray,
    registered: np.ndarray,
    reference_mm: np.ndarray | None,
    report: AccuracyReport | None,
    frames: FrameSummary,
    warnings: Sequence[Mapping[str, str]],
    identity: SheetIdentity,
    angles: Mapping[str, Any] | None = None,
    tissue: Mapping[str, Any] | None = None,
    strokes: np.ndarray | None = None,
) -> Figure:
    """Return the one-page report as an A4 portrait matplotlib Figure (not yet rendered).

    Header with identification (identity: the study's fields, "not given" where absent), the mosaic with the
    path and a scale bar, the force map (N) and the coverage (frames) with colour bars of their panels' height,
    frames placed and lost, accuracy (with a reference; angles: evaluate_angles' dict), the fitted tissue and
    probe model (tissue: report.json's "tissue"), warnings.
    """
    est = check_path("estimate_mm", estimate_mm)
    reg = np.asarray(registered, dtype=bool).reshape(-1)
    if len(reg) != len(est):
        raise ValueError(f"registered: expected {len(est)} entries, got {len(reg)}")
    ref = None if reference_mm is None else check_path("reference_mm", reference_mm, len(est))
    check_scale(mosaic.px_per_mm)
    fig = Figure(figsize=SHEET_SIZE_IN, dpi=SHEET_DPI)
    FigureCanvasAgg(fig)
    page = Page(fig)
    page_w, page_h = SHEET_SIZE_IN
    y = _draw_header(page, identity)

    # What goes below the images is measured first: the images take the space left.
    blocks, blocks_h = _text_blocks(
        page,
        [
            ("Frames", _frames_lines(frames)),
            ("Accuracy (reference track)", _accuracy_lines(report, angles)),
            ("Tissue and probe (fitted)", _tissue_lines(tissue)),
        ],
    )
    warn_text, warn_h = None, 0.0
    if warnings:
        text = "\n".join("WARNING: " + w["message"] for w in warnings)
        warn_text, warn_h = page.text(_MARGIN, 0.0, text, width=_CONTENT_W, fontsize=8, color="#b00000")
        warn_h += 0.15
    footer = (
        "Positions and lengths in mm of undeformed tissue (force-rectified), from the first frame's centre: "
        "x to the right, y down."
    )
    foot, foot_h = page.text(_MARGIN, 0.0, footer, width=_CONTENT_W - 1.5, fontsize=7, color="#555555")
    foot_top = page_h - _BOTTOM - foot_h
    page.move(foot, _MARGIN, foot_top)
    page.text(_MARGIN + _CONTENT_W, foot_top, "veinmosaic, page 1 of 1", fontsize=7, color="#555555", ha="right")
    page.rule(foot_top - 0.07, _MARGIN, _MARGIN + _CONTENT_W, lw=0.6, color="#888888")

    # The panels and their wording, sized to the space left; maps much wider than tall go one above the other.
    scales = (force_scale(mosaic.force_n), coverage_scale(mosaic.coverage))
    map_aspect = extent_aspect(layer_extent(mosaic.coverage, mosaic.px_per_mm, mosaic.origin_px))
    stacked = map_aspect > _STACK_ASPECT
    cell_w = _CONTENT_W if stacked else (_CONTENT_W - _MAP_GAP) / 2
    xs = (_MARGIN, _MARGIN) if stacked else (_MARGIN, _MARGIN + cell_w + _MAP_GAP)
    titles = [
        page.text(x, 0.0, scale.title, width=cell_w, fontsize=9.5, fontweight="bold")
        for x, scale in zip(xs, scales, strict=True)
    ]
    captions = [
        page.text(x, 0.0, scale.caption, width=cell_w, fontsize=7.5) for x, scale in zip(xs, scales, strict=True)
    ]
    ax_path = fig.add_axes(page.rect(_MARGIN, y, 1.0, 1.0), label="sheet:mosaic")
    draw_paths(ax_path, est, reg, ref, mosaic.vein, mosaic.px_per_mm, mosaic.origin_px, legend=False, strokes=strokes)
    left, right, bottom, top = layer_extent(mosaic.vein, mosaic.px_per_mm, mosaic.origin_px)
    set_image_limits(
        ax_path, [np.array([[left, top], [right, bottom]]), est[reg], *([] if ref is None else [ref])], 0.0
    )
    path_title, path_title_h = page.text(
        _MARGIN, y, "Vein mosaic and probe path", width=_CONTENT_W, fontsize=10, fontweight="bold"
    )
    handles, labels = ax_path.get_legend_handles_labels()
    legend = fig.legend(handles, labels, loc="upper center", ncol=len(handles), frameon=False, fontsize=8)
    legend_h = page.height(legend)
    titles_h = max(h for _, h in titles)
    captions_h = max(h for _, h in captions)
    rows = 2 if stacked else 1
    map_row_fixed = titles_h + 0.08 + 0.08 + captions_h + 0.25  # title, gap, panel, gap, caption, gap
    fixed = path_title_h + 0.08 + 0.06 + legend_h + 0.22 + rows * map_row_fixed
    room = max(page_h - _BOTTOM - (blocks_h + warn_h + foot_h + 0.3) - y - fixed, 2.0)
    xlim, ylim = ax_path.get_xlim(), ax_path.get_ylim()
    path_aspect = abs(xlim[1] - xlim[0]) / max(abs(ylim[0] - ylim[1]), 1e-9)
    path_box = fit_box(path_aspect, _CONTENT_W, 4.4)
    map_box = fit_box(map_aspect, cell_w - _BAR_PAD - _BAR_W - _BAR_TEXT, 2.2 if stacked else 3.0)
    if path_box[1] + rows * map_box[1] > room:  # all panels shrink in proportion
        shrink = room / (path_box[1] + rows * map_box[1])
        path_box = (path_box[0] * shrink, path_box[1] * shrink)
        map_box = (map_box[0] * shrink, map_box[1] * shrink)

    # Mosaic with the path: title, panel (centred), legend below it (never over the path).
    page.move(path_title, _MARGIN, y)
    y += path_title_h + 0.08
    ax_path.set_position(page.rect(_MARGIN + (_CONTENT_W - path_box[0]) / 2, y, *path_box))
    ax_path.set_xlabel("")
    ax_path.set_ylabel("")
    ax_path.set_xticks([])
    ax_path.set_yticks([])
    scale_bar(ax_path, abs(xlim[1] - xlim[0]), abs(ylim[0] - ylim[1]))
    y += path_box[1] + 0.06
    legend.set_bbox_to_anchor((0.5, 1.0 - y / page_h), transform=fig.transFigure)
    y += legend_h + 0.22

    # Force and coverage: title, panel with its colour bar of the same height, caption.
    layers = (mosaic.force_n, coverage_values(mosaic.coverage))
    for k, (x, scale, (title, _), (caption, _), values, name) in enumerate(
        zip(xs, scales, titles, captions, layers, ("force", "coverage"), strict=True)
    ):
        row_top = y + k * (map_row_fixed + map_box[1]) if stacked else y
        page.move(title, x, row_top)
        top = row_top + titles_h + 0.08
        ax = fig.add_axes(page.rect(x, top, *map_box), label=f"sheet:{name}")
        cax = fig.add_axes(page.rect(x + map_box[0] + _BAR_PAD, top, _BAR_W, map_box[1]), label=f"sheet:{name}:bar")
        draw_map(ax, cax, values, scale, mosaic.px_per_mm, mosaic.origin_px, mm_axes=False)
        page.move(caption, x, top + map_box[1] + 0.08)
    y += rows * (map_row_fixed + map_box[1])

    # Frames, accuracy, tissue; then the warnings.
    page.rule(y - 0.12, _MARGIN, _MARGIN + _CONTENT_W, lw=0.6, color="#888888")
    for head, body in blocks:
        x = head.get_position()[0] * page_w
        page.move(head, x, y)
        page.move(body, x, y + page.height(head) + 0.06)
    y += blocks_h + 0.15
    if warn_text is not None:
        page.move(warn_text, _MARGIN, y)
    _without_ligatures(fig)
    return fig


def _without_ligatures(fig: Figure) -> None:
    """Draw single-line texts letter by letter: an id with "ff" stays two f's in the PDF's text (copy, search).

    matplotlib >= 3.11 shapes text with ligatures; it passes a text's features for single-line texts only (the
    PDF's ToUnicode map still gives "fi" for a ligature in a paragraph).
    """
    for text in fig.findobj(Text):
        if hasattr(text, "set_fontfeatures") and "\n" not in text.get_text():
            text.set_fontfeatures(["-liga"])


def render_sheet(fig: Figure) -> tuple[bytes, bytes]:
    """Return a sheet figure rendered as (PNG bytes at SHEET_DPI, one-page PDF bytes)."""
    png, pdf = io.BytesIO(), io.BytesIO()
    fig.savefig(png, format="png", dpi=fig.dpi)
    fig.savefig(pdf, format="pdf", metadata={"Title": SHEET_TITLE, "Creator": "veinmosaic"})
    return png.getvalue(), pdf.getvalue()
