"""What the commands show besides their result: progress bars (stderr) and the result's warnings (stdout)."""

from __future__ import annotations

import sys
from collections.abc import Callable

from tqdm import tqdm


def sized(bar: tqdm) -> Callable[[int, int], None]:
    """Return a progress callback (done, total) that drives a tqdm bar."""

    def update(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    return update


def bar(desc: str, total: int = 0) -> tqdm:
    """Return a tqdm bar of frames on stderr."""
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, dynamic_ncols=True)


def print_warnings(warnings: list[dict[str, str]]) -> None:
    """Print each warning on its own line, to stdout (it is part of the result) and flagged WARNING."""
    for w in warnings:
        print(f"WARNING: {w['message']}")


def print_global_error(doc: dict[str, float | None] | None) -> None:
    """Print where a report's error lies (report.json's global_error: scale %, turn deg, mm left), if it has one."""
    if not doc or any(doc.get(k) is None for k in ("scale_pct", "turn_deg", "after_similarity_mm")):
        return
    from dataclasses import fields

    from services.core.outputs.evaluation import GlobalError

    names = {f.name for f in fields(GlobalError)}
    figures = {k: float("nan") if v is None else float(v) for k, v in doc.items() if k in names}
    print(GlobalError(**{"after_linear_mm": float("nan"), **figures}).summary())
