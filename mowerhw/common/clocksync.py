"""Map a device clock onto the host monotonic clock (docs/design.md §3; after Klipper's clocksync).

A device stamps each sample with its own clock (VN-100 ``TimeStartup`` in ns, a V4L2 buffer
time); the host sees the same sample later, after a transport delay that is never negative
and jitters (USB polling, scheduler). The device time is the better *measure of when* the
sample happened; the host clock is the *time base* everything else uses. This module keeps

* the **rate** of the device clock against the host: the slope of the lower envelope of the
  (device, host) points over a sliding window (the linear-programming estimate, which delay
  spikes cannot tilt), clamped to the nominal rate ± ``max_drift_ppm``, the way Klipper bounds
  its frequency estimate with ``MAX_CLOCK_DRIFT``, and
* the **offset** as the *lower envelope* of the arrivals: every arrival is an upper bound on
  when the sample happened (delay ≥ 0), so the mapping is anchored at the smallest
  ``host − rate·device`` in the window. Delay spikes never pull it; a sample that arrives
  *earlier* than the mapping predicts lowers it at once (it cannot have happened after it
  arrived).

What remains is the constant minimum transport latency, which no one-way scheme can observe.
A device clock that jumps (reboot, counter reset) is detected and starts a fresh window.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class ClockSyncStats:
    samples: int = 0
    resets: int = 0  # device clock jumped: a fresh window was started
    last_delay_s: float = 0.0  # arrival − mapped device time of the newest sample
    max_delay_s: float = 0.0


class ClockSync:
    """Device timestamps → host seconds, robust to jitter, bounded in drift.

    ``device_unit_s`` is the length of one device tick in seconds (1e-9 for VN-100
    ``TimeStartup`` ns, 1e-3 for V4L2 ``CAP_PROP_POS_MSEC``).
    """

    def __init__(
        self,
        device_unit_s: float = 1e-9,
        window_s: float = 30.0,
        max_drift_ppm: float = 500.0,
        reset_threshold_s: float = 1.0,
        min_rate_span_s: float = 2.0,
        block_s: float = 0.25,
        refit_every_s: float = 1.0,
    ) -> None:
        self.device_unit_s = device_unit_s
        self.window_s = window_s
        self.max_drift = max_drift_ppm * 1e-6
        self.reset_threshold_s = reset_threshold_s
        self.min_rate_span_s = min_rate_span_s
        self.block_s = block_s
        # the refit (a hull over the window) every 10 samples and at most once a device
        # second: the rate moves by ppm, and an early arrival lowers the offset at once anyway
        self.refit_every_s = refit_every_s
        # host seconds per device second, for a device clock ± max_drift off the host
        self._rate_min = 1.0 / (1.0 + self.max_drift)
        self._rate_max = 1.0 / (1.0 - self.max_drift)
        self.stats = ClockSyncStats()
        self._pairs: deque[tuple[float, float]] = deque()
        self._dev0: float | None = None  # device origin (s) of the current window
        self._rate = 1.0  # host seconds per device second
        self._offset = 0.0  # host = offset + rate · (device − dev0)
        self._since_fit = 0
        self._fit_x = 0.0  # window device time (s) of the last refit

    @property
    def synced(self) -> bool:
        return self._dev0 is not None

    @property
    def drift_ppm(self) -> float:
        """How much faster (ppm) the device clock runs than the host clock."""
        return (1.0 / self._rate - 1.0) * 1e6

    def _device_s(self, device_ticks: float) -> float:
        return float(device_ticks) * self.device_unit_s

    def _reset(self, dev_s: float, host_s: float) -> None:
        self._pairs.clear()
        self._dev0 = dev_s
        self._rate = 1.0
        self._offset = host_s
        self._since_fit = 0
        self._fit_x = 0.0

    def update(self, device_ticks: float, host_s: float) -> float:
        """Add one (device time, host arrival) pair; return the sample's host time."""
        dev_s = self._device_s(device_ticks)
        if self._dev0 is None:
            self._reset(dev_s, host_s)
        else:
            predicted = self._map(dev_s)
            last_dev = self._pairs[-1][0] if self._pairs else dev_s
            # Backwards, or so far ahead that it would have arrived before it happened:
            # the device clock jumped. A late arrival (delay spike) is never a reason.
            if dev_s < last_dev or host_s - predicted < -self.reset_threshold_s:
                self.stats.resets += 1
                self._reset(dev_s, host_s)
        x = dev_s - self._dev0  # type: ignore[operator]
        self._pairs.append((x, host_s))
        while self._pairs and self._pairs[-1][0] - self._pairs[0][0] > self.window_s:
            self._pairs.popleft()
        # An arrival earlier than the mapping: the envelope is too high, lower it now.
        if host_s < self._offset + self._rate * x:
            self._offset = host_s - self._rate * x
        self._since_fit += 1
        if self._since_fit >= 10 and x - self._fit_x >= self.refit_every_s:
            self._fit()
        self.stats.samples += 1
        mapped = self._offset + self._rate * x
        delay = host_s - mapped
        self.stats.last_delay_s = delay
        self.stats.max_delay_s = max(self.stats.max_delay_s, delay)
        return mapped

    def _fit(self) -> None:
        """Refit rate and offset over the window: the lower-envelope (LP) estimate.

        The line below every (device, host) point that is highest at the window's mean
        device time — the linear-programming skew estimate of Moon, Skelly & Towsley (1999) —
        is the edge of the points' lower convex hull above that mean. Only the least
        delayed point of each ``block_s`` block can be a hull vertex (to within the drift
        over one block), so the hull is built over those few points.
        """
        self._since_fit = 0
        arr = np.asarray(self._pairs, dtype=np.float64)
        x, h = arr[:, 0], arr[:, 1]
        self._fit_x = float(x[-1])
        if x[-1] - x[0] >= self.min_rate_span_s:
            block = np.floor((x - x[0]) / self.block_s).astype(np.int64)
            order = np.lexsort((h - x, block))  # by block, least delayed first
            firsts = order[np.r_[True, np.diff(block[order]) > 0]]
            hx, hh = _lower_hull(x[firsts], h[firsts])
            if hx.size >= 2:
                k = int(np.clip(np.searchsorted(hx, x.mean()) - 1, 0, hx.size - 2))
                slope = (hh[k + 1] - hh[k]) / (hx[k + 1] - hx[k])
                self._rate = min(max(slope, self._rate_min), self._rate_max)
        self._offset = float(np.min(h - self._rate * x))

    def _map(self, dev_s: float) -> float:
        return self._offset + self._rate * (dev_s - self._dev0)  # type: ignore[operator]

    def to_host(self, device_ticks: float) -> float:
        """Host seconds of a device timestamp (needs at least one ``update``)."""
        if self._dev0 is None:
            raise RuntimeError("clock not synchronised yet: call update() with a sample first")
        return self._map(self._device_s(device_ticks))


def _lower_hull(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower convex hull (monotone chain) of points sorted by strictly increasing x (the
    tests on Python floats: the same IEEE products as on numpy's scalars, without them)."""
    xs, ys = x.tolist(), y.tolist()
    hull: list[int] = []
    for i in range(len(xs)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            # Drop b if it lies on or above the segment a → i.
            if (ys[b] - ys[a]) * (xs[i] - xs[a]) >= (ys[i] - ys[a]) * (xs[b] - xs[a]):
                hull.pop()
            else:
                break
        hull.append(i)
    idx = np.asarray(hull)
    return x[idx], y[idx]


#: where a camera's frame times come from (``camera.timestamps``)
FRAME_CLOCKS = ("auto", "monotonic", "device", "arrival")


@dataclass
class FrameClockStats:
    #: the clock the frame times come from now: monotonic (the buffer times as they are),
    #: device (buffer times mapped by :class:`ClockSync`) or arrival (the host's reading)
    source: str = ""
    frames: int = 0
    unstamped: int = 0  # frames without a buffer time: their arrival used
    future_stamps: int = 0  # host-clock buffer times after their frame's arrival
    #: arrival − frame time of the newest frame, and its smallest (the delivery latency)
    latency_s: float = 0.0
    min_latency_s: float = 0.0


class FrameClock:
    """A camera frame's host time from its buffer time and its arrival (docs/design.md §3).

    V4L2 drivers stamp buffers on the host's own ``CLOCK_MONOTONIC``, the clock
    ``time.monotonic()`` reads (``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``; uvcvideo at the start
    of the exposure): such a stamp *is* the frame's time. Mapped like a device clock
    (:class:`ClockSync`), every frame would be moved late by the smallest delivery latency —
    the exposure's end and the frame's transfer, tens of ms for a large frame — which no
    one-way scheme can see. Older drivers stamp on the wall clock, and a camera may count
    its own: those are mapped by :class:`ClockSync`.

    ``mode`` (``camera.timestamps``): ``monotonic`` takes buffer times as host times;
    ``device`` maps them; ``arrival`` ignores them; ``auto`` decides on the first stamped
    frame — a buffer time at most :attr:`SAME_CLOCK_S` before its arrival, and not after
    it, is on the host's clock — and maps from the first one that comes after its arrival
    (which a host-clock stamp never does), saying so once; under ``monotonic`` such a frame
    has its arrival. In every mode a frame without a buffer time has its arrival.
    """

    #: a buffer time this close before its arrival is on the host's monotonic clock (the
    #: other clocks a driver uses are the wall clock, decades away, or a device's own)
    SAME_CLOCK_S = 10.0
    #: a host-clock buffer time may be this far after its arrival (the two read at
    #: different moments, in ms with µs digits): more means it is not on the host's clock
    FUTURE_TOLERANCE_S = 0.002

    def __init__(self, mode: str = "auto", sync: ClockSync | None = None) -> None:
        if mode not in FRAME_CLOCKS:
            raise ValueError(f"frame clock {mode!r} is not one of {', '.join(FRAME_CLOCKS)}")
        self.mode = mode
        self.sync = sync or ClockSync(device_unit_s=1.0, reset_threshold_s=2.0)
        self.stats = FrameClockStats(source="" if mode == "auto" else mode)

    def time(self, stamp_s: float | None, arrival_s: float) -> float:
        """The host time (s) of a frame stamped ``stamp_s`` (None or ≤ 0: no stamp) that
        arrived at ``arrival_s`` (host monotonic s)."""
        self.stats.frames += 1
        if stamp_s is None or not stamp_s > 0.0 or self.mode == "arrival":
            if self.mode != "arrival":
                self.stats.unstamped += 1
            return self._seen(arrival_s, arrival_s)
        ahead = stamp_s - arrival_s
        if self.stats.source == "":  # auto, first stamp
            same = -self.SAME_CLOCK_S <= ahead <= self.FUTURE_TOLERANCE_S
            self.stats.source = "monotonic" if same else "device"
            log.info(
                "camera: buffer times %s (the first %.3f s %s its arrival): %s",
                "on this computer's monotonic clock" if same else "on a clock of their own",
                abs(ahead),
                "after" if ahead > 0 else "before",
                "used as they are" if same else "mapped onto the host clock",
            )
        if self.stats.source == "monotonic":
            if ahead <= self.FUTURE_TOLERANCE_S:
                return self._seen(stamp_s, arrival_s)
            self.stats.future_stamps += 1
            if self.mode == "monotonic":  # the user's word: this one stamp is not believed
                return self._seen(arrival_s, arrival_s)
            self.stats.source = "device"
            log.warning(
                "camera: a buffer time %.3f s after its frame arrived: not this "
                "computer's clock after all; mapping buffer times from now on",
                ahead,
            )
        return self._seen(self.sync.update(stamp_s, arrival_s), arrival_s)

    def _seen(self, t: float, arrival_s: float) -> float:
        latency = arrival_s - t
        st = self.stats
        st.min_latency_s = latency if st.frames == 1 else min(st.min_latency_s, latency)
        st.latency_s = latency
        return t
