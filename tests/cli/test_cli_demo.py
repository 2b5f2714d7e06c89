"""`veinmosaic demo`'s promises, with the service, the simulator and the HTTP client replaced by fakes.

What is checked is the command's own behaviour, not the pipeline (tests/api/test_viewer_browser.py runs a real
service end to end): the viewer URL printed on a line of its own, a plain statement of whether the demo keeps
serving, and a data dir that is temporary and gone after the run unless --data-dir names one to keep.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import cli.client
import cli.commands_service
import services.core.simulation.scenarios
import services.store.scan_folder
from cli.main import main
from services.core.mosaic.canvas import MosaicImage
from services.store.results_store import ResultsStore

SID = "0123456789abcdef0123456789abcdef"
VIEWER = f"/viewer/{SID}?token=tok"
UPLOAD_BYTES = 2_000_000  # stands for the uploads and results a real run leaves in its data dir


class FakeService:
    """Records the data dir it was given and fills it as a run would; wait() returns at once."""

    def __init__(self, args: Any, log: dict[str, Any]) -> None:
        self.data_dir = Path(args.data_dir or "data")  # as the real one: the settings' data dir when not given
        self.base_url = "http://127.0.0.1:5999"
        self.log = log
        log["data_dir"] = self.data_dir

    def __enter__(self) -> FakeService:
        (self.data_dir / "sessions").mkdir(parents=True, exist_ok=True)
        (self.data_dir / "sessions" / "frames.bin").write_bytes(b"\0" * UPLOAD_BYTES)
        return self

    def __exit__(self, *exc: object) -> None:
        self.log["existed_while_serving"] = (self.data_dir / "sessions" / "frames.bin").is_file()

    def wait(self) -> int:
        """Return at once (a real service serves until Ctrl-C)."""
        self.log["held"] = True
        return 0


class FakeClient:
    """The few client calls the demo makes, answering as a finished 40-frame session."""

    def __init__(self, base_url: str, key: str) -> None:
        self.base_url = base_url

    def wait_done(self, sid: str, timeout_s: float, progress: Any = None) -> dict[str, Any]:
        """Return the finished state."""
        state = self.session(sid)
        if progress:
            progress(state)
        return state

    def session(self, sid: str) -> dict[str, Any]:
        """Return the finished state."""
        return {"status": "done", "frames_processed": 40, "frames_lost": 0, "registered_fraction": 1.0, "warnings": []}

    def post_reference(self, sid: str, text: str) -> dict[str, Any]:
        """Return a report without plots."""
        error = {"scale_pct": 0.25, "turn_deg": -0.1, "after_similarity_mm": 0.2, "after_linear_mm": None}
        return {"accuracy_summary": "RMSE 0.5 mm", "global_error": error, "plots": {}}

    def request(self, method: str, url: str) -> Any:
        """Return a response whose content names the URL."""
        return SimpleNamespace(content=url.encode())


class FakeScan:
    """A simulated scan as far as the demo looks at it: 40 frames, a 50 mm path."""

    def __init__(self) -> None:
        self.truth = {"path_length_mm": 50.0}

    def __len__(self) -> int:
        return 40


def _upload(client: Any, scan_dir: Path, **kw: Any) -> str:
    kw["on_session"]({"id": SID, "viewer_url": VIEWER})
    return SID


@pytest.fixture
def demo(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, Any]:
    """Replace the service, the simulator and the client; run in tmp_path; return the fakes' log."""
    log: dict[str, Any] = {}
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli.commands_service, "_service", lambda args, settings, extra_env=None: FakeService(args, log))
    monkeypatch.setattr(services.core.simulation.scenarios, "simulate", lambda name, seed: FakeScan())
    monkeypatch.setattr(
        services.store.scan_folder,
        "write_scan_folder",
        lambda s, d: (Path(d).mkdir(parents=True), (Path(d) / "reference.csv").write_text("seq,x_mm,y_mm\n")),
    )
    monkeypatch.setattr(cli.client, "VeinmosaicClient", FakeClient)
    monkeypatch.setattr(cli.client, "upload_scan_folder", _upload)
    return log


def test_demo_prints_the_viewer_url_alone_and_says_it_stops(
    demo: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "--out", str(tmp_path / "out")]) == 0
    lines = capsys.readouterr().out.splitlines()
    url = "http://127.0.0.1:5999" + VIEWER
    assert lines.count(url) == 2, lines  # once when the session starts, once at the end: each alone on its line
    assert lines[-2] == url and lines[-3] == "viewer:"
    assert "stops the service" in lines[-1] and "--hold keeps it serving" in lines[-1], lines[-1]
    assert "held" not in demo  # and it did not wait
    assert any("deleted when the demo ends" in line for line in lines)  # says what happens to its data
    assert any("+0.25 % in scale" in line and "turned -0.100 deg" in line for line in lines)  # where the error lies
    for name in ("mosaic.png", "sheet.pdf", "vein.dcm", "force.dcm", "coverage.dcm"):
        assert (tmp_path / "out" / name).is_file(), name


def test_demo_leaves_no_data_behind(demo: dict[str, Any], tmp_path: Path) -> None:
    assert main(["demo", "--out", str(tmp_path / "out")]) == 0
    assert demo["existed_while_serving"]
    assert not demo["data_dir"].exists()  # the temporary data dir is deleted with what the run wrote in it
    assert not (tmp_path / "data").exists()  # and nothing went to ./data
    assert main(["demo", "--out", str(tmp_path / "out")]) == 0  # a second run: still nothing left
    assert not demo["data_dir"].exists() and not (tmp_path / "data").exists()


def test_demo_data_dir_is_kept_and_reused_when_named(
    demo: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    named = tmp_path / "mydata"
    assert main(["demo", "--data-dir", str(named), "--out", str(tmp_path / "out")]) == 0
    assert demo["data_dir"] == named and (named / "sessions" / "frames.bin").is_file()
    assert f"data in {named}, kept" in capsys.readouterr().out


def test_demo_hold_says_it_keeps_serving(
    demo: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["demo", "--hold", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "--hold: serving until Ctrl-C" in out and demo["held"]
    assert "stops the service" not in out


def test_demo_says_when_a_download_fails(
    demo: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def refuse(self: FakeClient, method: str, url: str) -> Any:
        if "sheet.pdf" in url:
            raise cli.client.ApiError(404, "not_ready", "no finished mosaic yet")
        return SimpleNamespace(content=url.encode())

    monkeypatch.setattr(FakeClient, "request", refuse)
    assert main(["demo", "--out", str(tmp_path / "out")]) == 0
    assert "could not fetch sheet.pdf: HTTP 404 not_ready" in capsys.readouterr().out  # said, not skipped silently
    assert not (tmp_path / "out" / "sheet.pdf").exists() and (tmp_path / "out" / "sheet.png").is_file()


def test_demo_writes_the_force_and_coverage_maps_with_their_scales(
    demo: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    named, out = tmp_path / "mydata", tmp_path / "out"
    assert main(["demo", "--data-dir", str(named), "--out", str(out)]) == 0  # no finished layers yet: said
    assert "could not draw force_map.png and coverage_map.png" in capsys.readouterr().out
    assert not (out / "force_map.png").exists()
    coverage = np.tile(np.arange(40, dtype=np.float32) % 30, (24, 1))  # 0 (never scanned) to 29 frames
    force = np.where(coverage > 0, 0.5 * coverage, np.nan).astype(np.float32)
    (named / "sessions" / SID).mkdir()
    rs = ResultsStore(named)  # the finished results a worker leaves in the demo's data dir
    rs.ensure_version(SID, 1, {"method": "best"})
    rs.write_mosaic_images(SID, 1, MosaicImage(np.zeros((24, 40), np.uint8), force, coverage, 8.0, (5.0, 12.0)))
    assert main(["demo", "--data-dir", str(named), "--out", str(out)]) == 0
    for name in ("force_map.png", "coverage_map.png"):  # the maps in mm with colour bars (N; frames)
        assert (out / name).read_bytes().startswith(b"\x89PNG"), name
    assert (out / "force.png").read_bytes() == f"/v1/sessions/{SID}/mosaic.png?layer=force".encode()  # as served
