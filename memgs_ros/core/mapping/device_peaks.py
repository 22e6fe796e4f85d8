"""Which kind of work set the GPU's allocation peak: the mapper's answer to "where does the CUDA
peak come from" in a real run, not a reconstruction of it.

``torch.cuda.max_memory_allocated`` only ever rises; work that raises it held the new peak while
it ran. ``PeakAttribution.work(name)`` wraps a kind of work (a step's forward, its backward, a
merge pass, a keyframe's upload...) and keeps, per kind, the highest peak it raised the device
to. The kind with the largest value set the run's peak. On a CPU (no allocator statistics) it
does nothing.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch

__all__ = ["PeakAttribution"]


class PeakAttribution:
    """Per kind of work, the highest allocation peak (bytes) it raised the device to. One thread
    uses it (the mapper's). ``read_peak`` defaults to the device's max_memory_allocated."""

    def __init__(self, device: torch.device, read_peak: Callable[[], int] | None = None) -> None:
        if read_peak is None and torch.device(device).type == "cuda":
            dev = torch.device(device)

            def read_peak() -> int:
                return int(torch.cuda.max_memory_allocated(dev))
        self._read = read_peak
        self.by_work: dict[str, int] = {}

    @property
    def enabled(self) -> bool:
        return self._read is not None

    @contextmanager
    def work(self, name: str) -> Iterator[None]:
        if self._read is None:
            yield
            return
        before = self._read()
        try:
            yield
        finally:
            after = self._read()
            if after > before:
                self.by_work[name] = max(after, self.by_work.get(name, 0))

    def peak_setter(self) -> str | None:
        """The kind of work that set the highest peak so far (None before any)."""
        return max(self.by_work, key=self.by_work.__getitem__) if self.by_work else None
