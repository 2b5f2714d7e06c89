"""End-to-end reconstruction of the simulator's short scan (accuracy bands, method ordering, determinism), of it
over a photograph's vessels, and of the shared short_veins_21 scan when ../shared is there."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.outputs.evaluation import AccuracyReport, evaluate_path
from services.core.path_rows import PATH_COLUMNS
from services.core.physics.compliance import STIFFENING_MIN_CHI2
from services.core.pipeline import Reconstruction, reconstruct
from services.core.simulation.scenarios import simulate
from services.store.scan_folder import read_scan_folder
from tests.services.core.synthetic_veins import vessel_photo
from tests.shared_scans import SHARED_CLINICAL, SHARED_SCANS, clinical_until
from tests.sim_cache import simulated
from tests.tolerances import TOL

pytestmark = pytest.mark.slow

# Measured on simulate("short", 1) (40 frames, 106 mm path) at commit 63e1382: best 0.016 mm (0.0125 one
# revision earlier; the lead measured 0.034 mm), best without refinement 0.020 mm, sift-chain 1.77 mm
# (lead: 1.556), paper 0.218 (lead: 0.171; 44 s, too slow for this suite). The bands are two-sided so a
# simulator or pipeline change that makes the task too easy shows as well as one that breaks it:
# - best: TOL.best_short_rmse_mm (its reasons are in tests/tolerances.py).
# - sift-chain: in [0.5, 5] mm: unrectified, frame-to-frame chaining must drift by around a millimetre
#   or more; below 0.5 mm the simulated deformation would no longer be a challenge.
BEST_RMSE_MM = TOL.best_short_rmse_mm
SIFT_CHAIN_RMSE_MM = (0.5, 5.0)


@pytest.fixture(scope="module")
def scan() -> Scan:
    return simulated("short", 1)


@pytest.fixture(scope="module")
def best(scan: Scan) -> Reconstruction:
    return reconstruct(scan, method_options("best"))


def test_the_scale_prior_holds_the_frames_to_the_tissue_law(scan: Scan, best: Reconstruction) -> None:
    # at the end every frame's scale is held to what the fitted law says (scale_prior, 0.5 %): the frames'
    # log-scales scatter less about the law than when they are free, and the path stays in its band
    free = reconstruct(scan, method_options("best").with_overrides({"scale_prior": 0.0}))

    def scatter(recon: Reconstruction) -> float:  # of log |a_k| (output units) about (1 - eps(F)) / (1 - c_n F)
        assert recon.compliance is not None
        loads = [r.fz_n for r in recon.rows]  # one row per frame, in index order
        c_n = scan.calibration.compliance_per_n
        law = recon.compliance
        dev = [
            math.log(abs(p.a)) - math.log((1 - float(law.strain(loads[i]))) / (1 - c_n * loads[i]))
            for i, p in recon.poses.items()
        ]
        return float(np.std(dev))

    assert scatter(best) < 0.8 * scatter(free)  # measured 0.0014 against 0.0020
    # frame 0, the origin, is set to the law's scale at its own load, not left at the gauge's 1 / g (to 1e-9: the
    # law's formula against the held pose, only rounding between them)
    assert best.compliance is not None and free.compliance is not None
    load_0, c_n = best.rows[0].fz_n, scan.calibration.compliance_per_n
    law_0 = (1 - float(best.compliance.strain(load_0))) / (1 - c_n * load_0)
    assert abs(best.poses[0].a) == pytest.approx(law_0, rel=1e-9)
    assert best.poses[0].t == 0j and best.poses[0].a.imag == 0.0
    assert abs(free.poses[0].a) == pytest.approx(1 / free.compliance.gauge, rel=1e-9)
    assert BEST_RMSE_MM[0] <= _report(scan, free).rmse_mm <= BEST_RMSE_MM[1]


def _report(scan: Scan, recon: Reconstruction) -> AccuracyReport:
    return evaluate_path(recon.estimate_mm, recon.registered, scan.reference_mm)


def test_best_rmse_in_band_and_everything_registered(scan: Scan, best: Reconstruction) -> None:
    report = _report(scan, best)
    assert BEST_RMSE_MM[0] <= report.rmse_mm <= BEST_RMSE_MM[1], report.rmse_mm
    assert report.registered_fraction == 1.0
    assert best.registered.all()
    assert best.seconds < 30.0


def test_best_beats_sift_chain(scan: Scan, best: Reconstruction) -> None:
    chain = _report(scan, reconstruct(scan, method_options("sift-chain")))
    assert SIFT_CHAIN_RMSE_MM[0] <= chain.rmse_mm <= SIFT_CHAIN_RMSE_MM[1], chain.rmse_mm
    assert _report(scan, best).rmse_mm * 5 < chain.rmse_mm  # measured 7.8x better (0.24 against 1.86 mm)


def test_refinement_does_no_harm(scan: Scan, best: Reconstruction) -> None:
    unrefined = reconstruct(scan, method_options("best").with_overrides({"refine": False}))
    with_refine, without = _report(scan, best), _report(scan, unrefined)
    assert without.registered_fraction == with_refine.registered_fraction == 1.0
    # measured 0.016 (refined) vs 0.020 mm: refinement may help or be neutral, never cost more than 10%
    assert with_refine.rmse_mm <= 1.1 * without.rmse_mm
    assert with_refine.final_drift_mm <= 1.1 * without.final_drift_mm + 0.01


def test_two_runs_are_identical(scan: Scan, best: Reconstruction) -> None:
    again = reconstruct(scan, method_options("best"))
    np.testing.assert_array_equal(again.estimate_mm, best.estimate_mm)
    np.testing.assert_array_equal(again.mosaic.vein, best.mosaic.vein)
    assert [r.inliers for r in again.rows] == [r.inliers for r in best.rows]


def test_path_rows_follow_the_spec(scan: Scan, best: Reconstruction) -> None:
    assert len(best.rows) == len(scan) == 40
    row0 = best.rows[0]
    assert (row0.seq, row0.x_mm, row0.y_mm, row0.yaw_deg) == (0, 0.0, 0.0, 0.0)  # frame 0 is the origin
    assert [r.seq for r in best.rows] == list(range(40))
    assert tuple(vars(row0)) == PATH_COLUMNS
    truth_fz = np.array(scan.truth["fz_n"])
    fz = np.array([r.fz_n for r in best.rows])
    # interpolated sensor forces: 4 sensors x (0.03 N noise + up to 0.1 N offset) -> within 0.5 N
    np.testing.assert_allclose(fz, truth_fz, atol=0.5)
    truth_yaw = np.array([p[2] for p in scan.truth["poses"]])
    # 0.15 deg: measured worst 0.106 deg on the realistic short scan (vein-map keypoints are less precise
    # than on textured skin); 0.15 deg over a 40 mm half-window is 0.1 mm at the frame's edge
    np.testing.assert_allclose([r.yaw_deg for r in best.rows], truth_yaw, atol=0.15)
    for r in best.rows:
        assert r.stretch == pytest.approx(scan.calibration.compliance_per_n * r.fz_n, rel=1e-9)
        assert r.inliers >= method_options("best").min_inliers or r.seq == 0


def test_self_calibration_moves_e_toward_the_truth(scan: Scan, best: Reconstruction) -> None:
    assert best.compliance is not None
    calib = scan.calibration
    fitted = best.compliance.young_modulus_kpa(calib.poisson_ratio, calib.scanner_area_m2)
    true_e = scan.truth["young_modulus_kpa"]
    assert abs(fitted - true_e) < abs(calib.young_modulus_kpa - true_e)
    assert math.isfinite(best.compliance.gauge) and abs(best.compliance.gauge - 1) < 0.02


def test_mosaic_geometry(best: Reconstruction) -> None:
    m = best.mosaic
    assert m.vein.dtype == np.uint8 and m.vein.ndim == 2
    h, w = m.vein.shape
    ox, oy = m.origin_px
    assert 0 <= ox < w and 0 <= oy < h  # frame 0's centre lies on the mosaic
    # the mosaic spans the path (~106 mm long) plus a window: far larger than one 400 x 320 frame
    assert w * h > 3 * 400 * 320
    covered = np.isfinite(m.force_n)
    assert covered.mean() > 0.3
    assert np.nanmax(m.force_n) < 40.0 and np.nanmin(m.force_n) >= 0.0


SHARED_SHORT = SHARED_SCANS / "short_veins_21"


@pytest.mark.skipif(not SHARED_SHORT.is_dir(), reason="the shared reference scans are not on this machine")
def test_the_shared_short_scan_keeps_the_linear_law_its_weak_curvature_does_not_pass() -> None:
    # the scales of short_veins_21 curve a little (the stiffening law gains chi2 4.8, above BIC's ln 40 = 3.7):
    # the law must pass chi-square's 1 % point too (STIFFENING_MIN_CHI2) before the path follows it
    scan = read_scan_folder(SHARED_SHORT)
    recon = reconstruct(scan, method_options("best"))
    assert recon.compliance is not None
    assert math.log(recon.compliance.n_frames) < recon.compliance.stiffening_chi2 < STIFFENING_MIN_CHI2
    assert recon.compliance.law == "linear"
    rmse = _report(scan, recon).rmse_mm
    assert TOL.shared_short_rmse_mm[0] <= rmse <= TOL.shared_short_rmse_mm[1], rmse


def test_veins_from_a_photograph_are_registered_as_well_as_procedural_ones() -> None:
    # issue 14's hidden rasters include "real retinal vessel texture": the simulator can take any photograph's
    # vessels as the world (simulate(..., texture=photo)); the pipeline must not depend on its own network's look
    photo, _ = vessel_photo()
    scan = simulate("short", 1, tissue="linear", texture=photo)
    procedural = simulated("short", 1, tissue="linear")
    assert scan.truth["texture"] == "photograph" and procedural.truth["texture"] == "procedural"
    assert not np.array_equal(scan.frame(0), procedural.frame(0))
    np.testing.assert_array_equal(scan.reference_mm, procedural.reference_mm)  # the same probe, other skin
    recon = reconstruct(scan, method_options("best"))
    report = _report(scan, recon)
    assert report.registered_fraction == 1.0
    assert TOL.photo_short_rmse_mm[0] <= report.rmse_mm <= TOL.photo_short_rmse_mm[1], report.rmse_mm


@pytest.fixture(scope="module")
def clinical() -> tuple[Scan, Reconstruction]:
    """The shared clinical scan's first three strokes (lifts, frames in the air, dropped frames) and `best`'s
    reconstruction of them."""
    scan = clinical_until(160)
    return scan, reconstruct(scan, method_options("best"))


@pytest.mark.skipif(not SHARED_CLINICAL.is_dir(), reason="the shared reference scans are not on this machine")
def test_a_scan_in_strokes_places_every_frame_on_the_skin_and_none_from_the_air(
    clinical: tuple[Scan, Reconstruction],
) -> None:
    scan, recon = clinical
    reference = scan.by_seq(scan.reference_track)
    touched = np.all(np.isfinite(reference[:, :2]), axis=1)  # reference.csv: every frame that touched the skin
    present = np.zeros(scan.n_seqs, bool)
    present[scan.frame_seq] = True
    rows = recon.rows
    assert [r.seq for r in rows] == list(range(scan.n_seqs))  # dropped seqs are rows too: missing
    assert all(r.status == "lost" and r.reason == "missing" for r in rows if not present[r.seq])
    placed = recon.registered
    assert placed[touched].all()  # every frame on the skin
    assert not placed[present & ~touched].any()  # no frame from the air ...
    assert all(rows[i].reason == "no_contact" for i in np.flatnonzero(present & ~touched))  # ... each rejected so
    # strokes: runs of contact numbered from 0, a new one after each lift (reference.csv's runs of rows)
    expected, stroke, before = {}, -1, False
    for seq in scan.frame_seq:
        stroke += int(touched[seq] and not before)
        if touched[seq]:
            expected[int(seq)] = stroke
        before = bool(touched[seq])
    assert {r.seq: r.stroke for r in rows if r.stroke is not None} == expected
    assert stroke == 2
    report = evaluate_path(recon.estimate_mm, placed, reference[:, :2])
    assert report.registered_fraction == 1.0 and report.n_registered_without_reference == 0
    assert TOL.clinical_strokes_rmse_mm[0] <= report.rmse_mm <= TOL.clinical_strokes_rmse_mm[1], report.rmse_mm
