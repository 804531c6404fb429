"""Known-harmless third-party messages, silenced in one place at the entry points.

``train.py`` and ``evaluate.py`` call :func:`silence_third_party` before they build
anything. Each entry below matches one message of one library by its text (and category /
logger), so a new or different message of the same library, and every warning of this
project, still shows. Add a message here only once it is understood to be harmless, with
the reason.
"""

from __future__ import annotations

import logging
import warnings

#: (message regex, warning category, reason) -- matched with ``warnings.filterwarnings``.
WARNINGS: tuple[tuple[str, type[Warning], str], ...] = (
    # Lightning's own _pytree helper still builds torch's deprecated LeafSpec (torch >= 2.10);
    # nothing of ours uses it and Lightning will change it, not us.
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning, "Lightning internals vs torch"),
    # umap-learn: a fixed random_state (we always seed) forces n_jobs=1; that is the intent.
    (r"n_jobs value .* overridden to 1 by setting random_state", UserWarning, "seeded UMAP is single-threaded"),
    # Lightning's DataLoader tip: num_workers is a deliberate setting (0 on small machines).
    (r".*does not have many workers.*", Warning, "num_workers is chosen in the data config"),
)

#: Substrings of Lightning's rank-zero info lines that are advertisements, not information.
LOG_MESSAGES: tuple[str, ...] = (
    "try installing [litlogger]",  # "Tip: For seamless cloud logging ... LitLogger"
    "try installing [litmodels]",  # "Tip: For seamless cloud uploads ... LitModelCheckpoint"
)
#: Loggers that emit them (lightning.pytorch and lightning.fabric each set up their own).
LOGGERS = ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero")


class _DropKnown(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        try:
            msg = record.getMessage()
        except Exception:  # a malformed record is not ours to judge
            return True
        return not any(s in msg for s in LOG_MESSAGES)


_FILTER = _DropKnown()


def silence_third_party() -> None:
    """Install the filters above (idempotent). Project warnings are untouched."""
    for pattern, category, _reason in WARNINGS:
        warnings.filterwarnings("ignore", message=pattern, category=category)
    for name in LOGGERS:
        lg = logging.getLogger(name)
        if _FILTER not in lg.filters:
            lg.addFilter(_FILTER)
