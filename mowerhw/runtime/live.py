"""What the status page shows (issue 19): the ``live`` control command's answer.

The daemon samples the plan-view pose 5 times a second into a bounded trajectory (whether or
not a page is open, so a page opened late still draws the whole drive) and keeps one-second
windows of its sensor counts for the rates. A ``live`` request reads these and the core's
decision; it never touches an estimator beyond its public pose, so answering it costs the
loop a few dictionary lookups. The page's own process asks with ``since`` (the trajectory
points it already has) and gets only the new ones.
"""

from __future__ import annotations

import itertools
import math
import os
from collections import deque
from typing import Any

import numpy as np

from mowerhw.runtime.core import RuntimeCore
from mowerhw.runtime.pipelines import MowPipeline, PlanPose, TeachPipeline, yaw_of

#: trajectory points a second
SAMPLE_PERIOD_S = 0.2
#: sensor rates are counted over this window (s)
RATE_WINDOW_S = 1.0
#: the sensors the page lists, and the core's count of each
SENSOR_COUNTS = {"imu": "imu", "speed": "speed", "camera": "frames"}


class LiveView:
    """The trajectory and sensor rates the status page reads (``live`` command)."""

    def __init__(self, max_points: int = 36000) -> None:
        self.max_points = max_points
        #: names this daemon's run: a restarted daemon starts the page's drawing again
        self.run = os.urandom(4).hex()
        #: a new teach or mow session starts a new epoch (the page clears its drawing)
        self.epoch = 0
        self._session_mode = ""
        self._points: deque[tuple[float, float, float]] = deque(maxlen=max_points)
        self._total = 0  # points appended this epoch (the index after the newest)
        self._next_sample = 0.0
        self._counts: deque[tuple[float, dict[str, int]]] = deque()

    def sample(self, core: RuntimeCore, now: float) -> None:
        """Called by the daemon's ticker: a trajectory point and the counts every 0.2 s."""
        if now < self._next_sample:
            return
        self._next_sample = now + SAMPLE_PERIOD_S
        if core.mode in ("teach", "mow") and core.mode != self._session_mode:
            self._session_mode = core.mode
            self.epoch += 1
            self._points.clear()
            self._total = 0
        self._counts.append((now, {k: core.counts[c] for k, c in SENSOR_COUNTS.items()}))
        while len(self._counts) > 2 and now - self._counts[1][0] >= RATE_WINDOW_S:
            self._counts.popleft()
        pose = plan_pose(core)
        if pose is not None and bool(np.isfinite(pose.position[:2]).all()):
            x, y = (round(float(v), 4) for v in pose.position[:2])
            self._points.append((round(now, 3), x, y))
            self._total += 1

    def rates(self) -> dict[str, float | None]:
        """Samples a second of each sensor over the last second."""
        if len(self._counts) < 2:
            return dict.fromkeys(SENSOR_COUNTS)
        (t0, c0), (t1, c1) = self._counts[0], self._counts[-1]
        dt = t1 - t0
        if dt <= 0:
            return dict.fromkeys(SENSOR_COUNTS)
        return {k: round((c1[k] - c0[k]) / dt, 1) for k in SENSOR_COUNTS}

    def trajectory_since(self, since: int) -> tuple[int, list[tuple[float, float, float]]]:
        """(index of the first point returned, the points from ``since`` on); the oldest
        points kept when ``since`` has already left the buffer."""
        first = max(0, self._total - len(self._points))
        start = min(max(since, first), self._total)
        # from the newest end: a reply costs the points it carries, not the whole drive
        pts = list(itertools.islice(reversed(self._points), self._total - start))[::-1]
        return start, pts

    def snapshot(
        self,
        core: RuntimeCore,
        now: float,
        since: int = 0,
        landmarks: bool = False,
        supervisor: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """The ``live`` reply (strict JSON: no NaN)."""
        d = core.decision
        pose = plan_pose(core)
        start, pts = self.trajectory_since(since)
        rates = self.rates()
        out: dict[str, Any] = {
            "run": self.run,
            "epoch": self.epoch,
            "now": round(now, 3),
            "mode": core.mode,
            "permit": d.permit,
            "state": str(d.state),
            "reason": d.reason,
            "detail": d.detail,
            "signed_distance_m": _finite(d.signed_distance_m),
            "sensors": {name: self._sensor(core, name, now, rates[name]) for name in SENSOR_COUNTS},
            "pose": (_pose_json(pose) or None) if pose is not None else None,
            "trajectory": {"from": start, "points": pts},
            "map_problem": core.map_problem,
            "fault": core.fault,
        }
        pipe = core.pipeline
        if core.mode == "teach" or core.teach_state:
            out["teach"] = {"state": core.teach_state, **core.last_teach}
        if isinstance(pipe, TeachPipeline):
            out["teach"].update(pipe.status())
            lms = pipe.landmarks_xyz()
            out["teach"]["landmarks"] = int(lms.shape[0])
            if landmarks:
                out["landmarks"] = np.round(lms, 3).tolist()
        elif isinstance(pipe, MowPipeline):
            loc = pipe.localizer  # three figures: not the whole status with its copies
            out["localizer"] = {
                "localized": loc.localized,
                "searches": loc.counters.searches,
                "relocalizations": loc.counters.relocalizations,
            }
            if loc.compass is not None:  # the map has a taught field: what it says now
                found = loc.compass_heading()
                out["localizer"]["compass_deg"] = (
                    None if found is None else [round(math.degrees(v), 1) for v in found]
                )
        if supervisor:
            out["supervisor"] = {
                k: supervisor.get(k)
                for k in ("permit", "reason", "detail", "lease_age_s", "can_up", "tilt_deg")
            }
        return out

    @staticmethod
    def _sensor(core: RuntimeCore, name: str, now: float, rate: float | None) -> dict[str, Any]:
        """Age (arrival on the host clock, as ``now``), rate, and whether the permit gate
        counts it late (its limit: the gate is the one judge of staleness)."""
        last = core.last_arrival[name]
        return {
            "age_s": None if last is None else round(now - last, 3),
            "rate_hz": rate,
            "limit_s": core.gate.stale_limits_s.get(name),
            "late": core.gate.late(name, now, last),
        }


def plan_pose(core: RuntimeCore) -> PlanPose | None:
    pipe = core.pipeline
    if isinstance(pipe, TeachPipeline | MowPipeline):
        return pipe.plan_pose()
    return None


def _finite(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), 4)


def _pose_json(p: PlanPose) -> dict[str, Any]:
    """x, y, heading for the page; position, q_wb and the full covariance for Foxglove's
    pose and state topics (the same messages a recording holds)."""
    out: dict[str, Any] = {
        "t": _finite(p.t),  # NaN before the first IMU sample
        "x": round(float(p.position[0]), 4),
        "y": round(float(p.position[1]), 4),
        "z": round(float(p.position[2]), 4),
        "heading": round(yaw_of(p.quaternion), 5),
        "q_wxyz": [round(float(v), 6) for v in p.quaternion],
        "cov_xy": None,
        "sigma_heading": None,
        "sigma_xy_m": (
            round(p.sigma_xy, 5) if p.sigma_xy is not None and math.isfinite(p.sigma_xy) else None
        ),
        "covariance": None,
    }
    cov = p.covariance
    if cov is not None and bool(np.isfinite(cov).all()):
        out["cov_xy"] = [[float(f"{v:.4g}") for v in row] for row in cov[:2, :2].tolist()]
        out["sigma_heading"] = round(math.sqrt(max(float(cov[5, 5]), 0.0)), 6)
        out["covariance"] = [float(f"{v:.4g}") for v in cov.ravel().tolist()]
    if not all(math.isfinite(v) for v in (out["x"], out["y"], out["z"], out["heading"])):
        return {}
    return out
