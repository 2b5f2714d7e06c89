"""Simulated scans and offline reconstructions made once per pytest run, shared by every module that needs them.

`simulate(scenario, seed, imaging)` is deterministic, so modules that each simulated the same scan got identical
arrays anyway; here it is made once. The shared scan's frames and arrays are read-only: a test that wrote into
one would change what the next module sees, so that raises instead. Tests that need a modified scan make it with
dataclasses.replace (a new frame_loader, mask=None, ...), as they already do.
"""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np

from services.core.inputs.scan import Scan, in_memory_loader
from services.core.methods import method_options
from services.core.pipeline import Reconstruction, reconstruct
from services.core.simulation.scenarios import simulate


def _frozen(a: np.ndarray | None) -> np.ndarray | None:
    if a is not None:
        a.flags.writeable = False
    return a


@cache
def simulated(
    scenario: str, seed: int, imaging: str = "realistic", tissue: str | None = None, imu: bool = False
) -> Scan:
    """Return simulate(scenario, seed, imaging, tissue=tissue, imu=imu), made once per run, with read-only frames
    and arrays."""
    scan = simulate(scenario, seed, imaging, tissue=tissue, imu=imu)
    frames = [_frozen(scan.frame(i)) for i in range(len(scan))]
    for name in ("frame_seq", "frame_t_s", "force_t_s", "forces_n", "mask", "imu_t_s", "imu_tilt_deg", "reference_mm"):
        _frozen(getattr(scan, name))
    return dataclasses.replace(scan, frame_loader=in_memory_loader(frames))


@cache
def live_short(seed: int, tissue: str | None = None, imu: bool = False) -> Scan:
    """The simulated "short" scan (40 frames) without its mask, as a live session has it (the window is estimated
    from the frames): what the workers and the HTTP service get."""
    return dataclasses.replace(simulated("short", seed, tissue=tissue, imu=imu), mask=None)


@cache
def offline_best(seed: int, tissue: str | None = None, imu: bool = False) -> Reconstruction:
    """The offline pipeline's "best" reconstruction of live_short(seed, tissue, imu): what a live run must
    reproduce."""
    return reconstruct(live_short(seed, tissue, imu), method_options("best"))
