"""The shared, bounded, time-ordered sensor buffer (docs/design.md §8).

Device tasks ``push`` timestamped samples as they arrive; the estimator loop takes them out
in time order across all streams (``pop_ready``). Each stream also keeps a bounded history
for range queries. (The ground speed's model — hold, extrapolation, interpolation — is
:class:`mowerhw.estimation.odometry.SpeedTrack`'s alone.)

Nothing here blocks or does I/O; it is used from one thread (the event loop) at a time.
"""

from __future__ import annotations

import bisect
import heapq
import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.samples import Stream

FloatArray = NDArray[np.float64]


@dataclass
class StreamStats:
    """Counters of one stream; they only ever grow."""

    pushed: int = 0
    dropped_full: int = 0  # oldest history entries evicted because the stream was full
    out_of_order: int = 0  # arrived with a timestamp older than the newest already held
    dropped_pending: int = 0  # never delivered: the consumer fell too far behind
    rejected: int = 0  # non-finite timestamps


class StreamBuffer:
    """Bounded history of one stream, kept sorted by timestamp."""

    def __init__(self, name: str, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"stream {name}: capacity must be at least 1, got {capacity}")
        self.name = name
        self.capacity = capacity
        self._times: list[float] = []
        self._items: list[Any] = []
        self.stats = StreamStats()

    def __len__(self) -> int:
        return len(self._items)

    def push(self, sample: Any) -> bool:
        """Insert ``sample`` (needs ``.t``) in time order; False if its time is not finite."""
        t = float(sample.t)
        if not np.isfinite(t):
            self.stats.rejected += 1
            return False
        self.stats.pushed += 1
        if self._times and t < self._times[-1]:
            self.stats.out_of_order += 1
            i = bisect.bisect_right(self._times, t)
            self._times.insert(i, t)
            self._items.insert(i, sample)
        else:
            self._times.append(t)
            self._items.append(sample)
        excess = len(self._items) - self.capacity
        if excess > 0:
            del self._times[:excess]
            del self._items[:excess]
            self.stats.dropped_full += excess
        return True

    def range(self, t0: float, t1: float) -> list[Any]:
        """Samples with ``t0 ≤ t ≤ t1``, oldest first."""
        lo = bisect.bisect_left(self._times, t0)
        hi = bisect.bisect_right(self._times, t1)
        return self._items[lo:hi]

    def at_or_before(self, t: float) -> Any | None:
        """The newest sample with time ≤ ``t``, or None."""
        i = bisect.bisect_right(self._times, t)
        return self._items[i - 1] if i else None

    def latest(self) -> Any | None:
        return self._items[-1] if self._items else None

    def oldest(self) -> Any | None:
        return self._items[0] if self._items else None

    def times(self) -> FloatArray:
        return np.asarray(self._times, dtype=np.float64)

    def items(self) -> list[Any]:
        return list(self._items)

    def clear(self) -> None:
        self._times.clear()
        self._items.clear()


#: Default history per stream: 60 s of 100 Hz IMU, 60 s of 10 Hz speed, a few frames.
DEFAULT_CAPACITY: dict[str, int] = {
    Stream.IMU: 6000,
    Stream.SPEED: 600,
    Stream.FRAME: 8,
    Stream.BEARINGS: 240,
}


class SensorBuffer:
    """Per-stream bounded histories plus one time-ordered queue of not-yet-consumed samples."""

    def __init__(
        self,
        capacity: dict[str, int] | None = None,
        default_capacity: int = 1000,
        pending_capacity: int = 20000,
    ) -> None:
        self._capacity = {**DEFAULT_CAPACITY, **(capacity or {})}
        self._default_capacity = default_capacity
        self._streams: dict[str, StreamBuffer] = {}
        self._pending: list[tuple[float, int, str, Any]] = []
        self._pending_capacity = pending_capacity
        self._seq = itertools.count()

    def stream(self, name: str) -> StreamBuffer:
        """The history of one stream (created empty on first use)."""
        buf = self._streams.get(name)
        if buf is None:
            buf = StreamBuffer(name, self._capacity.get(name, self._default_capacity))
            self._streams[name] = buf
        return buf

    @property
    def streams(self) -> dict[str, StreamBuffer]:
        return dict(self._streams)

    def push(self, stream: str, sample: Any) -> bool:
        """Record ``sample`` in its stream's history and queue it for the consumer."""
        if not self.stream(stream).push(sample):
            return False
        heapq.heappush(self._pending, (float(sample.t), next(self._seq), stream, sample))
        while len(self._pending) > self._pending_capacity:
            _, _, dropped_stream, _ = heapq.heappop(self._pending)
            self.stream(dropped_stream).stats.dropped_pending += 1
        return True

    def pop_ready(self, until: float | None = None) -> list[tuple[str, Any]]:
        """Queued samples with ``t ≤ until`` (all when None), in time order (ties: arrival)."""
        out: list[tuple[str, Any]] = []
        while self._pending and (until is None or self._pending[0][0] <= until):
            _, _, stream, sample = heapq.heappop(self._pending)
            out.append((stream, sample))
        return out

    def pending(self) -> int:
        return len(self._pending)

    def range(self, stream: str, t0: float, t1: float) -> list[Any]:
        return self.stream(stream).range(t0, t1)

    def stats(self) -> dict[str, dict[str, int]]:
        """Counters per stream, for status output and logs."""
        return {name: vars(buf.stats).copy() for name, buf in self._streams.items()}
