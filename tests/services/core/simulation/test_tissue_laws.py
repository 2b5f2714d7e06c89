"""A patient as on the shared scans (a hand's tilt, tissue laws of several shapes): what `best` learns and keeps.

One tolerance table, each band measured on `short` seed 1 (40 frames, tilts up to 7 deg, true kappa 0.108 N/mm)
with its margin: tilt RMS 0.19-0.29 deg per axis (target 1 deg; 0.63-0.91 when the view model's evidence was
the affine on the similarity's inliers, which understates the stretch); kappa fitted within 1.5 % (17-21 % high
before); path RMSE 0.335 (linear), 0.343 (stiffening), 0.379 (toe), 0.364 (saturating, its anisotropy fixed
in the tissue and the probe yawing +-15 deg; 0.490 with tissue_axis=true) and 0.532 mm (power law: over these
40 frames' 3-12 N its curvature is at the noise, so the fit keeps the linear law). Every law's secant compliance
at the scan's mean load is the simulator's true one, 4-10 % off the calibration's; the 5 % prior holds the level
back, so the path is 0.6-1.1 % too large on this seed: the level, not the shape, is what these bands measure.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.core.methods import method_options
from services.core.outputs.evaluation import evaluate_angles, evaluate_path
from services.core.outputs.session_report import path_angles_deg
from services.core.pipeline import reconstruct
from services.core.simulation.renderer import TissueLaw
from services.core.simulation.scenarios import TRUE_KAPPA_N_PER_MM
from tests.sim_cache import simulated

TOL = {  # law: (max path RMSE mm, max tilt RMS deg per axis, max |log(kappa / true kappa)|)
    "linear": (0.40, 0.5, 0.10),
    "stiffening": (0.42, 0.5, 0.10),
    "power": (0.65, 0.5, 0.10),
    "toe": (0.46, 0.5, 0.10),
    "saturating": (0.45, 0.5, 0.10),
}


@pytest.mark.parametrize("law", sorted(TOL))
def test_best_learns_the_tilt_of_a_hand_on_each_tissue_law(law: str) -> None:
    scan = simulated("short", 1, tissue=law)
    truth = scan.truth
    assert TRUE_KAPPA_N_PER_MM[0] <= truth["hooke_n_per_mm"] <= TRUE_KAPPA_N_PER_MM[1]
    assert truth["tissue"]["kind"] == law and scan.reference_angles_deg is not None
    true_tilt = np.abs(scan.reference_angles_deg[:, 1:]).max()
    assert true_tilt > 3.0  # degrees, as a hand tilts (the phantom default stays under 0.3)
    recon = reconstruct(scan, method_options("best"))
    max_rmse, max_tilt, max_kappa = TOL[law]
    report = evaluate_path(recon.estimate_mm, recon.registered, scan.reference_mm)
    assert report.n_registered == len(scan)
    assert report.rmse_mm <= max_rmse, report.rmse_mm
    angles = evaluate_angles(path_angles_deg(recon.rows), recon.registered, scan.reference_angles_deg)
    assert angles["tilt_x_rmse_deg"] <= max_tilt and angles["tilt_y_rmse_deg"] <= max_tilt, angles
    kappa = recon.learned["kappa_n_per_mm"]
    assert abs(math.log(kappa / truth["hooke_n_per_mm"])) <= max_kappa, kappa
    assert recon.learned["kappa_low_n_per_mm"] < kappa < recon.learned["kappa_high_n_per_mm"]
    assert recon.learned["anisotropy_axis"] == "probe"  # the tissue axis is tried only on request (below)


def test_the_tissue_axis_is_chosen_on_request_where_the_tissue_has_it() -> None:
    # tissue_axis=true on the saturating tissue (its axis fixed in the tissue, the probe yawing by up to 15 deg):
    # both axes are fitted and reported, and the scan's evidence chooses the tissue's (without yaw the tissue axis
    # is not fitted at all: tests/services/core/physics/test_tissue_model.py)
    scan = simulated("short", 1, tissue="saturating")
    recon = reconstruct(scan, method_options("best").with_overrides({"tissue_axis": True}))
    assert recon.learned["anisotropy_axis"] == "tissue" == scan.truth["tissue"]["anisotropy_axis"]
    probe, tissue = (recon.learned[f"affine_residual_rms_{axis}_axis"] for axis in ("probe", "tissue"))
    assert probe is not None and tissue is not None and tissue < probe


def test_without_the_view_model_tilts_are_the_calibrations_hundredths() -> None:
    scan = simulated("short", 1, tissue="linear")
    recon = reconstruct(scan, method_options("best").with_overrides({"fit_tilt": False}))
    angles = evaluate_angles(path_angles_deg(recon.rows), recon.registered, scan.reference_angles_deg)
    assert angles["tilt_x_rmse_deg"] > 1.5  # the feature is what brings it under 1 deg (test above)
    assert "kappa_n_per_mm" not in recon.learned


def test_best_fits_a_stiffening_law_to_a_tissue_of_another_shape() -> None:
    # Fung's toe law (strain logarithmic in load, not the fit's hyperbola) on short seed 7, whose scales show the
    # curvature over 3-12 N. Measured RMSE 0.135 mm; tilts are not asserted here (0.45 / 0.25 deg; this seed's
    # kappa is fitted 11 % high, the view model's matter, tested above on seed 1)
    scan = simulated("short", 7, tissue="toe")
    recon = reconstruct(scan, method_options("best"))
    report = evaluate_path(recon.estimate_mm, recon.registered, scan.reference_mm)
    assert report.rmse_mm <= 0.30, report.rmse_mm
    assert recon.compliance is not None and recon.learned["compliance_law"] == "stiffening"
    assert recon.learned["half_strain_load_low_n"] < recon.learned["half_strain_load_n"]
    truth = TissueLaw(**scan.truth["tissue"])
    loads = np.array([2.0, 5.0, 10.0])
    np.testing.assert_allclose(recon.compliance.strain(loads), truth.strain(loads), rtol=0.2)


def test_an_imu_pins_kappa_and_the_tilts() -> None:
    # short seed 3 (tilts to 7 deg) with an IMU stream (imu.csv): kappa from the IMU's tilts against the force
    # differences is the view fit's prior. Measured: kappa 1 % off (11 % without), tilt RMS 0.18 / 0.39 deg against
    # 0.48 / 0.61 from the images alone; the sensors' offsets keep the force-based tilt from being exact
    with_imu = simulated("short", 3, tissue="stiffening", imu=True)
    truth = with_imu.truth["hooke_n_per_mm"]
    tilts = {}
    for name, scan in (("imu", with_imu), ("images", simulated("short", 3, tissue="stiffening"))):
        recon = reconstruct(scan, method_options("best"))
        assert recon.learned["kappa_source"] == ("imu+images" if name == "imu" else "images")
        angles = evaluate_angles(path_angles_deg(recon.rows), recon.registered, scan.reference_angles_deg)
        tilts[name] = max(angles["tilt_x_rmse_deg"], angles["tilt_y_rmse_deg"])
        if name == "imu":
            assert abs(math.log(recon.learned["kappa_n_per_mm"] / truth)) <= 0.03
            assert recon.learned["kappa_imu_samples"] >= 10
    assert tilts["imu"] <= 0.45 and tilts["imu"] < tilts["images"] - 0.1, tilts
