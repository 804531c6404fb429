"""``embodied-tactile report``'s options, typed, with their one default each (no heavy
imports): which generated page is regenerated and the results / generalisation generators'
inputs. ``configs/report.yaml`` composes :class:`ReportOptions` and names none of them again."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from embodied_tactile.options.checks import one_of


@dataclass
class ReportOptions:
    """``embodied-tactile report``: ``page=all`` regenerates every page under ``docs`` from what
    it was made from; ``results``, ``generalisation`` and ``active`` run one generator."""

    page: str = field(default="all", metadata=one_of("all", "results", "generalisation", "active"))
    docs: str = "docs/generated"          # the generated pages' folder
    roots: list = field(default_factory=list)  # evaluated population runs (or scores files) for generalisation.md
    evaluation: Optional[str] = None      # page=results: the study's evaluation folder (holds results.json)
    objects: Optional[str] = None         # page=results: an evaluation folder of held-out-object runs (its section)
    extra: Any = None                     # page=results: further evaluations as sections, {TITLE: FOLDER} or [TITLE=FOLDER, ...]
    notes: list = field(default_factory=list)  # page=results: lines for "What was run"
    out: Optional[str] = None             # results: the page (null: printed); generalisation: its folder (null: docs)
    paper_units: Optional[str] = None     # page=results: rewrite this results page with its Table 2 also in the authors' code's units
    records: list = field(default_factory=list)  # page=active: the records to rewrite (empty: every one under docs/active)


__all__ = ["ReportOptions"]
