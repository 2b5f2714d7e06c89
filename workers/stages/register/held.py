"""A session whose registration lease this worker holds: its reconstruction, its cursor, what is not published.

The bottom of the register stage: plain data that every other module of the package reads and writes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from services.core.inputs.calibration import Calibration
from services.core.methods import MethodOptions
from services.core.mosaic.deepzoom import DziGeometry, TilePyramid
from services.core.session_reconstruction import SessionReconstruction
from services.jobs.leases import Lease
from services.store.session_version import SessionVersion


@dataclass
class RegisterCost:
    """The register stage's CPU seconds on the frames it handled since the last flush, and their count, by kind
    (SessionReconstruction.frame_kind)."""

    cpu_s: dict[str, float] = field(default_factory=dict)
    frames: dict[str, int] = field(default_factory=dict)

    def add(self, kind: str, cpu_s: float) -> None:
        """Count one frame of `kind` that took cpu_s CPU seconds."""
        self.cpu_s[kind] = self.cpu_s.get(kind, 0.0) + cpu_s
        self.frames[kind] = self.frames.get(kind, 0) + 1


@dataclass
class Pending:
    """What changed since the last flush: the next flush writes it and announces it in one event."""

    touched: set[tuple[int, int]] = field(default_factory=set)  # canvas tiles the reconstruction changed
    deferred: set[tuple[int, int, int]] = field(default_factory=set)  # whole-canvas levels, rendered with images
    seqs: list[int] = field(default_factory=list)  # frames handled (added, lost or rejected)
    path_reset: bool = False  # an earlier frame moved (refinement): clients should re-read the path
    dirty: bool = False  # the cursor moved: state.json is behind
    cost: RegisterCost = field(default_factory=RegisterCost)  # of the frames added (not replayed) since the flush


@dataclass
class Clocks:
    """When (time.monotonic) the lease was renewed, the cursor last moved, the last flush, image render and finish
    run ahead ran."""

    renewed: float = 0.0
    progressed: float = field(default_factory=time.monotonic)
    flushed: float = 0.0
    flush_interval: float = 0.0  # max(flush_every_s, 2 x the last flush's duration): flushing stays <= 1/3
    images: float = 0.0
    images_s: float = 0.0  # how long the last whole images took (s): the next wait longer (flush.images_every_s)
    ahead: float = field(default_factory=time.monotonic)  # the last finish run ahead ended (or the session was taken)
    ahead_interval: float = 0.0  # AHEAD_COST_FACTOR x the last run's duration: runs wait at least that long
    ahead_placed: int = 0  # frames on the main map at the last run ahead: the next one waits for new frames


@dataclass
class HeldSession:
    """A session version this worker holds the lease of, with its in-memory reconstruction and publishing state."""

    sv: SessionVersion
    lease: Lease
    recon: SessionReconstruction
    geometry: DziGeometry
    pyramid: TilePyramid
    cursor: int = 0  # frames [0, cursor) are registered (added, lost or rejected)
    lost: list[int] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)
    times: dict[int, float] = field(default_factory=dict)  # t_s of frames registered without a PreparedFrame
    replayed: bool = False  # taken over mid-session: tiles another worker wrote may not have reached the disk
    behind: bool = False  # the last flush found it behind its uploads (flush.is_behind): moved frames wait to re-paste
    tracking: bool = False  # the last flush marked its next frames to be prepared for tracking (queue.set_tracking)
    taken_at: float = field(default_factory=time.time)  # when this worker took it (Unix s, as the frames' uploads)
    pending: Pending = field(default_factory=Pending)
    clocks: Clocks = field(default_factory=Clocks)

    @property
    def sid(self) -> str:
        """Return the session id."""
        return self.sv.sid

    @property
    def version(self) -> int:
        """Return the results version."""
        return self.sv.v

    @property
    def key(self) -> tuple[str, int]:
        """Return (session id, version): the key of the stage's held sessions."""
        return self.sv.sid, self.sv.v

    @property
    def calib(self) -> Calibration:
        """Return the version's calibration."""
        return self.sv.calibration

    @property
    def options(self) -> MethodOptions:
        """Return the version's method options."""
        return self.sv.method_options
