"""Bad frames a source skips: counted by kind, logged once per kind, or refused with ``strict``.

A camera or a long recording with one unreadable image should not cost the run: the readers
(TUM folders, bags) and the player skip such a frame, count it under a kind
(``unreadable_image``, ``size_mismatch``, ``stamp_backwards``...) and go on; ``strict`` keeps
the stop-on-first-error behaviour (a ``DataError``).
"""
from __future__ import annotations

import logging
from collections import Counter

from memgs_ros.errors import DataError

logger = logging.getLogger(__name__)


class SkipLog:
    """Counts of skipped frames by kind (``counts``), one log line per kind. ``where`` names the
    source in messages; ``strict``: ``skip`` raises DataError instead of counting."""

    def __init__(self, where: str, strict: bool = False) -> None:
        self.where = where
        self.strict = strict
        self.counts: Counter[str] = Counter()

    def skip(self, kind: str, detail: str = "", n: int = 1, level: int = logging.WARNING) -> None:
        if self.strict:
            raise DataError(f"{self.where}: {kind}{f': {detail}' if detail else ''}")
        if kind not in self.counts:
            logger.log(level, "%s: skipping %s%s (logged once; counted in skipped)", self.where, kind,
                       f": {detail}" if detail else "")
        self.counts[kind] += n
