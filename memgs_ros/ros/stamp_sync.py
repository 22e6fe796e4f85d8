"""Pairing messages by header stamp, with bounded memory (no rclpy import).

``StampBundler`` collects the parts of a bundle that share one exact stamp (the
tracker publishes a keyframe as colour, depth, pose and keypoints with one stamp).
``NearestPairer`` pairs two streams (colour, depth) whose stamps differ by at most
``max_dt_ns``, as message_filters' approximate policy does for two inputs.
Both drop the oldest pending items when full and count what they dropped.
``RgbdPairing`` is the tracker's colour/depth input: a ``NearestPairer`` whose unpaired colour is
counted and, after a while, explained (``UnpairedWatch``).
"""
from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class StampBundler:
    """Assemble bundles of ``parts`` keyed by exact stamp.

    add() returns the finished bundle ({part: payload}) once every part for that
    stamp has arrived, else None. At most ``max_pending`` incomplete bundles are kept.
    """

    def __init__(self, parts: set[str] | frozenset[str], max_pending: int = 8) -> None:
        if not parts:
            raise ValueError("a bundle needs at least one part")
        self.parts = frozenset(parts)
        self.max_pending = max_pending
        self._pending: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self.dropped = 0

    def add(self, part: str, stamp_ns: int, payload: Any) -> dict[str, Any] | None:
        if part not in self.parts:
            raise KeyError(f"unknown bundle part {part!r}; expected one of {sorted(self.parts)}")
        bundle = self._pending.setdefault(stamp_ns, {})
        bundle[part] = payload
        if bundle.keys() == self.parts:
            return self._pending.pop(stamp_ns)
        while len(self._pending) > self.max_pending:
            self._pending.popitem(last=False)
            self.dropped += 1
        return None

    @property
    def pending(self) -> int:
        return len(self._pending)


@dataclass
class NearestPairer(Generic[T]):
    """Pair items of streams ``a`` and ``b`` whose stamps are within ``max_dt_ns``.

    ``max_dt_ns = 0`` demands exact stamps. Each item is used at most once; items that
    can no longer be paired (older than the newest pair) are dropped and counted (``dropped``;
    ``dropped_a`` of them from stream a).
    """

    max_dt_ns: int
    queue_size: int = 5
    dropped: int = 0
    dropped_a: int = 0
    _a: OrderedDict[int, T] = field(default_factory=OrderedDict)
    _b: OrderedDict[int, T] = field(default_factory=OrderedDict)

    def add_a(self, stamp_ns: int, item: T) -> tuple[int, T, T] | None:
        return self._add(self._a, self._b, stamp_ns, item, a_first=True)

    def add_b(self, stamp_ns: int, item: T) -> tuple[int, T, T] | None:
        return self._add(self._b, self._a, stamp_ns, item, a_first=False)

    def _add(self, mine: OrderedDict[int, T], other: OrderedDict[int, T], stamp_ns: int, item: T,
             a_first: bool) -> tuple[int, T, T] | None:
        best = None
        for s in other:
            d = abs(s - stamp_ns)
            if d <= self.max_dt_ns and (best is None or d < abs(best - stamp_ns)):
                best = s
        if best is None:
            mine[stamp_ns] = item
            while len(mine) > self.queue_size:
                mine.popitem(last=False)
                self.dropped += 1
                self.dropped_a += a_first
            return None
        match = other.pop(best)
        # Anything older than this pair on either side can only pair out of order now.
        for q in (mine, other):
            for s in [s for s in q if s < min(best, stamp_ns)]:
                del q[s]
                self.dropped += 1
                self.dropped_a += q is self._a
        a, b = (item, match) if a_first else (match, item)
        return (stamp_ns if a_first else best), a, b


class KeyframeIntake:
    """A mapper's keyframe parts by stamp: complete bundles out, replays and losses counted.

    Keyframe topics replay their recent samples to a (re)started reader, so parts of a keyframe
    already seen complete (or ``known`` from a checkpoint) are ignored and counted
    (``duplicate_parts``). ``announce`` remembers keyframes the tracker announced; ``missed``
    counts those whose parts have not all arrived ``missed_after_s`` later (lost on the way:
    under CPU overload parts can arrive more than 10 s late, hence 60 s). The last
    ``remember`` complete stamps are kept (bounded memory).
    """

    def __init__(self, parts: set[str], known: Iterable[int] = (), remember: int = 4096,
                 missed_after_s: float = 60.0, max_pending: int = 16) -> None:
        self._bundler = StampBundler(parts, max_pending=max_pending)
        self._complete: deque[int] = deque(maxlen=remember)
        self._complete_set: set[int] = set()
        self._announced: deque[tuple[float, int]] = deque(maxlen=10_000)
        self._missed_after_s = missed_after_s
        self.duplicate_parts = 0
        for stamp in sorted(known)[-remember:]:
            self._remember(stamp)

    @property
    def dropped(self) -> int:
        """Incomplete bundles pushed out by newer ones (``max_pending``)."""
        return self._bundler.dropped

    def seen(self, stamp_ns: int) -> bool:
        return stamp_ns in self._complete_set

    def add(self, part: str, stamp_ns: int, payload: Any) -> dict[str, Any] | None:
        """The complete bundle once its last part arrives, else None."""
        if stamp_ns in self._complete_set:
            self.duplicate_parts += 1
            return None
        bundle = self._bundler.add(part, stamp_ns, payload)
        if bundle is not None:
            self._remember(stamp_ns)
        return bundle

    def announce(self, stamp_ns: int, now_s: float) -> None:
        self._announced.append((now_s, stamp_ns))

    def missed(self, now_s: float) -> int:
        """Announced keyframes newly found incomplete ``missed_after_s`` after their announcement."""
        n = 0
        while self._announced and now_s - self._announced[0][0] > self._missed_after_s:
            n += self._announced.popleft()[1] not in self._complete_set
        return n

    def _remember(self, stamp_ns: int) -> None:
        if len(self._complete) == self._complete.maxlen:
            self._complete_set.discard(self._complete[0])
        self._complete.append(stamp_ns)
        self._complete_set.add(stamp_ns)


class UnpairedWatch:
    """Colour waiting for depth (RGB-D): ``waiting`` says why once colour has found no depth for
    ``warn_s`` (then again after each further ``warn_s``), else None; ``paired`` resets it. A
    camera without depth maps nothing, and says so."""

    def __init__(self, warn_s: float) -> None:
        self.warn_s = warn_s
        self.depth_seen = False  # any depth message at all
        self._since: float | None = None  # monotonic s of the first colour since the last pair

    def paired(self) -> None:
        self._since = None

    def waiting(self, now_s: float, color: str, depth: str, max_sync_dt_s: float) -> str | None:
        if self._since is None:
            self._since = now_s
            return None
        waited = now_s - self._since
        if waited < self.warn_s:
            return None
        self._since = now_s  # said again after another window
        if not self.depth_seen:
            return (f"colour on {color} for {waited:.0f} s but no depth on {depth}: is the depth topic right, "
                    "and is the RealSense's align_depth.enable on? (tracker.mode mono maps colour alone)")
        return (f"no depth on {depth} within {max_sync_dt_s * 1e3:.0f} ms of colour for {waited:.0f} s: "
                "do colour and depth share a clock (max_sync_dt_s, sync)?")


class RgbdPairing:
    """Colour and depth paired by stamp (``NearestPairer``, ``max_dt_ns``; each pair goes to ``handle``);
    the colour frames it dropped unpaired go to ``unpaired(n)`` (with each message, n >= 0), and the
    reason to ``problem(why)`` once colour has found no depth for ``warn_s`` (``UnpairedWatch``).
    ``where``: (colour topic, depth topic, pairing tolerance s), for that reason."""

    def __init__(self, max_dt_ns: int, warn_s: float, where: tuple[str, str, float],
                 handle: Callable[[tuple[int, Any, Any]], None], unpaired: Callable[[int], None],
                 problem: Callable[[str], None]) -> None:
        self.pairer: NearestPairer[Any] = NearestPairer(max_dt_ns=max_dt_ns, queue_size=5)
        self.watch = UnpairedWatch(warn_s)
        self._where, self._handle, self._unpaired, self._problem = where, handle, unpaired, problem

    def color(self, stamp_ns: int, msg: Any, now_s: float) -> None:
        """A colour message at monotonic time ``now_s``."""
        self._done(self.pairer.dropped_a, self.pairer.add_a(stamp_ns, msg), now_s)

    def depth(self, stamp_ns: int, msg: Any) -> None:
        self.watch.depth_seen = True
        self._done(self.pairer.dropped_a, self.pairer.add_b(stamp_ns, msg), None)

    def _done(self, dropped_before: int, pair: tuple[int, Any, Any] | None, now_s: float | None) -> None:
        self._unpaired(self.pairer.dropped_a - dropped_before)
        if pair is not None:
            self.watch.paired()
            self._handle(pair)
        elif now_s is not None and (why := self.watch.waiting(now_s, *self._where)) is not None:
            self._problem(why)
