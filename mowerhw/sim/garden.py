"""A garden of two lawns joined by a path, and the operator's one teach drive that marks all of
it (issue 17; the marks of :mod:`mowerhw.teach.marks`).

Simulator map frame (m). The grass (:data:`mowerhw.sim.lawn.SHAPES` ``"garden"``) is a front
lawn ``[0, 8] × [0, 6]`` and a back lawn ``[12, 20] × [0, 6]`` joined by a 2 m path; the dock
stands in the middle of the path. The operator drives, in one go: from the dock to the path's
end, around the path (``nav path``), around the front lawn (``area front``), around a flower
bed across the front lawn's top edge (``keepout bed``), through the path to the back lawn,
around it (``area back``), and back onto the dock. Each zone is the track driven around it;
between zones the mower drives straight and turns on the spot; it stands still at every mark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import wrap_angle
from mowerhw.sim.lawn import PathLawn
from mowerhw.sim.motion import Truth, cosine_ramp_profile, truth_from_path
from mowerhw.sim.terrain import Terrain

FloatArray = NDArray[np.float64]

TURN_RATE = 0.6  # rad/s, turning on the spot
STAND_S = 1.2  # standing at a mark
RAMP_S = 1.5


@dataclass(frozen=True)
class GardenZone:
    """A zone as driven around: counter-clockwise track corners, the first one halfway along
    an edge (where its loop starts and ends), and the corner radius."""

    kind: str  # "area", "nav" or "keepout" (the teach mark)
    name: str
    corners: tuple[tuple[float, float], ...]
    fillet_m: float

    def track(self) -> PathLawn:
        return PathLawn(np.asarray(self.corners, dtype=np.float64), self.fillet_m)

    @property
    def start(self) -> tuple[float, float]:
        return self.corners[0]


DOCK = (10.0, 3.0, np.pi)  # x, y, heading: in the path, facing the front lawn
ZONES = (
    GardenZone("nav", "path", ((7.0, 3.0), (7.0, 2.2), (13.0, 2.2), (13.0, 3.8), (7.0, 3.8)), 0.5),
    GardenZone("area", "front", ((4.0, 0.5), (7.5, 0.5), (7.5, 5.5), (0.5, 5.5), (0.5, 0.5)), 1.0),
    GardenZone(
        "keepout", "bed", ((3.25, 4.3), (4.5, 4.3), (4.5, 5.9), (2.0, 5.9), (2.0, 4.3)), 0.4
    ),
    GardenZone(
        "area", "back", ((16.0, 0.5), (19.5, 0.5), (19.5, 5.5), (12.5, 5.5), (12.5, 0.5)), 1.0
    ),
)
#: straight legs (waypoints) from the dock to each zone's start, and home after the last
TO_ZONE = {
    "path": [(7.0, 3.0)],
    "front": [(4.0, 0.5)],
    "bed": [(3.25, 4.3)],
    "back": [(6.0, 3.0), (14.0, 3.0), (16.0, 0.5)],
}
HOME = [(14.0, 3.0), (DOCK[0], DOCK[1])]
#: the mower's own controller: where to drive to reach a lawn from the dock or the other lawn
ROUTES = {"front": [(5.5, 3.0)], "back": [(5.5, 3.0), (14.5, 3.0)]}


@dataclass(frozen=True)
class GardenDrive:
    truth: Truth
    marks: list[tuple[float, str, str]]  # (t of the truth, mark kind, name)


class _Path:
    """The drive, sample by sample (t, map xy, unwrapped heading, speed)."""

    def __init__(self, dt: float, xy: tuple[float, float], heading: float) -> None:
        self.dt = dt
        self.t = [0.0]
        self.xy = [np.array(xy, dtype=np.float64)]
        self.h = [heading]
        self.v = [0.0]
        self.marks: list[tuple[float, str, str]] = []

    def _append(self, xy: FloatArray, h: FloatArray, v: FloatArray) -> None:
        t0 = self.t[-1]
        n = len(v)
        self.t += list(t0 + self.dt * np.arange(1, n + 1))
        self.xy += list(xy)
        self.h += list(h)
        self.v += list(v)

    def stand(self, seconds: float, mark: tuple[str, str] | None = None) -> None:
        n = max(1, round(seconds / self.dt))
        if mark is not None:
            self.marks.append((self.t[-1] + 0.5 * seconds, *mark))
        self._append(np.repeat(self.xy[-1][None], n, 0), np.full(n, self.h[-1]), np.zeros(n))

    def turn_to(self, heading: float) -> None:
        h0 = self.h[-1]
        delta = wrap_angle(heading - h0)
        if abs(delta) < 1e-6:
            return
        ramp = min(1.0, abs(delta) / TURN_RATE)
        duration, s_of_t, _ = cosine_ramp_profile(abs(delta), TURN_RATE, ramp, 0.0, 0.0)
        t = np.arange(self.dt, duration + self.dt, self.dt)
        h = h0 + np.sign(delta) * s_of_t(t)
        self._append(np.repeat(self.xy[-1][None], t.size, 0), h, np.zeros(t.size))

    def _drive(self, length: float, speed: float, at: object) -> None:
        ramp = min(RAMP_S, length / speed)
        duration, s_of_t, v_of_t = cosine_ramp_profile(length, speed, ramp, 0.0, 0.0)
        t = np.arange(self.dt, duration + self.dt, self.dt)
        xy, h = at(s_of_t(t))  # type: ignore[operator]
        self._append(xy, h, v_of_t(t))

    def straight_to(self, target: tuple[float, float], speed: float) -> None:
        a = self.xy[-1]
        d = np.asarray(target, dtype=np.float64) - a
        length = float(np.hypot(*d))
        if length < 1e-6:
            return
        heading = float(np.arctan2(d[1], d[0]))
        self.turn_to(heading)
        h = self.h[-1]
        self._drive(
            length,
            speed,
            lambda s: (a + np.outer(s / length, d), np.full(s.size, h)),
        )

    def around(self, track: PathLawn, speed: float) -> None:
        self.turn_to(float(track.heading(np.array([0.0]))[0]))
        turns = self.h[-1] - float(track.heading(np.array([0.0]))[0])

        def at(s: FloatArray) -> tuple[FloatArray, FloatArray]:
            s = np.minimum(s, track.perimeter - 1e-9)
            return track.point(s), track.heading(s) + turns

        self._drive(track.perimeter, speed, at)


def garden_drive(
    speed_mps: float, camera_height_m: float, imu_hz: float = 100.0, standstill_s: float = 2.0
) -> GardenDrive:
    """The teach drive of the module doc, as a :class:`Truth` and the marks to give."""
    path = _Path(1.0 / imu_hz, (DOCK[0], DOCK[1]), DOCK[2])
    path.stand(standstill_s, ("dock", ""))
    for zone in ZONES:
        for point in TO_ZONE[zone.name]:
            path.straight_to(point, speed_mps)
        track = zone.track()
        path.turn_to(float(track.heading(np.array([0.0]))[0]))
        path.stand(STAND_S, (zone.kind, zone.name))
        path.around(track, speed_mps)
        path.stand(STAND_S, ("end", ""))
    for point in HOME:
        path.straight_to(point, speed_mps)
    path.turn_to(DOCK[2])
    path.stand(4.0)
    xy = np.asarray(path.xy)
    return GardenDrive(
        truth_from_path(
            np.asarray(path.t),
            xy,
            np.asarray(path.h),
            np.asarray(path.v),
            Terrain(),
            camera_height_m,
        ),
        path.marks,
    )


def zone_outline(name: str, n: int = 720) -> FloatArray:
    """The track driven around a zone (map frame): what its taught outline should be."""
    zone = next(z for z in ZONES if z.name == name)
    return zone.track().outline(n)
