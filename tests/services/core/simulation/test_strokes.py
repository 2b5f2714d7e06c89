"""The simulated scan in strokes (lifts, frames in the air, an island, dropped frames, a skewed force clock) and
`best` on it: every frame on the skin placed, none from the air, the force clock's offset found."""

from __future__ import annotations

import numpy as np
import pytest

from services.core.inputs.scan import Scan
from services.core.methods import method_options
from services.core.outputs.evaluation import evaluate_path
from services.core.pipeline import Reconstruction, reconstruct
from services.core.simulation.scenarios import simulate
from services.core.simulation.strokes import CLOCK_SKEW_S, ROWS
from tests.tolerances import TOL

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def strokes() -> tuple[Scan, Reconstruction]:
    """The strokes scenario (seed 1, a patient with the linear law) and `best`'s reconstruction of it."""
    scan = simulate("strokes", 1, tissue="linear")
    return scan, reconstruct(scan, method_options("best"))


def test_the_scan_is_scanned_in_strokes(strokes: tuple[Scan, Reconstruction]) -> None:
    scan, _ = strokes
    truth = scan.truth
    air, dropped = set(truth["in_air"]), set(truth["dropped"])
    assert set(scan.frame_seq.tolist()).isdisjoint(dropped) and len(dropped) >= 5  # a burst at least
    assert scan.n_seqs == len(scan) + len(dropped)
    on_skin = np.all(np.isfinite(scan.reference_mm), axis=1)
    assert not on_skin[np.isin(scan.frame_seq, sorted(air))].any()  # no reference row for a frame in the air
    # a run of frames in the air between every two strokes: the rows and the island
    kept_air = np.isin(scan.frame_seq, sorted(air))
    lifts = np.count_nonzero(np.diff(kept_air.astype(int)) == 1)
    assert lifts == ROWS  # 7 rows and the island: 8 strokes, 7 carries
    assert CLOCK_SKEW_S[0] <= abs(truth["clock_skew_s"]) <= CLOCK_SKEW_S[1]
    # frames in the air read no load beyond the sensors' offsets and noise; frames on the skin do
    fz = np.interp(scan.frame_t_s, scan.force_t_s, scan.forces_n.sum(axis=1))
    assert np.median(fz[kept_air]) < 0.5 < np.median(fz[~kept_air])


def test_best_places_every_frame_on_the_skin_and_none_from_the_air(strokes: tuple[Scan, Reconstruction]) -> None:
    scan, recon = strokes
    report = evaluate_path(recon.estimate_mm, recon.registered, scan.by_seq(scan.reference_mm))
    assert report.registered_fraction >= 0.99 and report.n_registered_without_reference == 0
    assert TOL.sim_strokes_rmse_mm[0] <= report.rmse_mm <= TOL.sim_strokes_rmse_mm[1], report.rmse_mm
    assert max(r.stroke for r in recon.rows if r.stroke is not None) == ROWS  # 8 strokes, numbered 0..7
    assert {r.reason for r in recon.rows if r.status != "ok"} == {"no_contact", "missing"}


def test_the_force_clock_offset_is_found(strokes: tuple[Scan, Reconstruction]) -> None:
    scan, recon = strokes
    found = recon.learned["force_clock_offset_s"]
    # measured -29.3 +- 3.2 ms against the true -27.8 ms: 10 ms fails a wrong sign (the offsets are 20-50 ms)
    assert found == pytest.approx(scan.truth["clock_skew_s"], abs=0.010)
