"""Trusting a pose again (issue 18): the search's two-frame acceptance through the odometry,
the consistency check after a re-localization, a lift that drops the pose."""

from __future__ import annotations

import math

import numpy as np

from mowerhw.common.geometry import yaw_rotation
from mowerhw.map import Landmark, LawnMap
from mowerhw.mow import Localizer, Reason
from mowerhw.mow.recovery import PROBATION_S, Pose2D, RelocalizationSearch
from mowerhw.mow.relocalize import Relocalization


def _map() -> LawnMap:
    rng = np.random.default_rng(11)
    ang = rng.uniform(0, 2 * np.pi, 30)
    r = rng.uniform(6.0, 12.0, 30)
    pts = np.c_[r * np.cos(ang), r * np.sin(ang), rng.uniform(-0.5, 1.7, 30)]
    lms = [Landmark(i, pts[i], np.eye(3) * 1e-6) for i in range(len(pts))]
    ring = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    boundary = np.c_[5 * np.cos(ring), 4 * np.sin(ring)]
    return LawnMap(boundary=boundary, landmarks=lms, camera=None, teach={})


def _answer(x: float, y: float, yaw: float) -> Relocalization:
    return Relocalization(True, yaw_rotation(yaw), np.array([x, y, 0.0]), [(0, 0)] * 12)


def _bearings(m: LawnMap, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    pts = m.landmark_positions()
    b = (pts - np.array([x, y, 0.0])) @ yaw_rotation(yaw)
    return m.landmark_ids(), b / np.linalg.norm(b, axis=1, keepdims=True)


def _stand(loc: Localizer, t0: float, t1: float, frame: object = None) -> None:
    """IMU at 100 Hz and speed 0 from t0 to t1; ``frame(t)`` at each 0.25 s."""
    for k in range(round((t1 - t0) * 100)):
        t = t0 + (k + 1) / 100
        loc.imu(t, np.zeros(3))
        if k % 10 == 0:
            loc.speed(t, 0.0)
        if frame is not None and (k + 1) % 25 == 0:
            frame(t)  # type: ignore[operator]


def test_planar_poses_compose_and_invert() -> None:
    a, b = Pose2D(1.0, -2.0, 0.7), Pose2D(0.3, 0.5, -2.9)
    back = a.compose(a.between(b))
    assert math.isclose(back.x, b.x, abs_tol=1e-12) and math.isclose(back.y, b.y, abs_tol=1e-12)
    assert back.turn(b) < 1e-12


def test_two_answers_are_accepted_only_when_the_odometry_between_them_agrees() -> None:
    search = RelocalizationSearch("since the start", 0.0)
    odo0, odo1 = Pose2D(0.0, 0.0, 0.0), Pose2D(1.0, 0.0, math.pi / 2)  # drove 1 m, turned left
    assert search.offer(0.0, _answer(2.0, 3.0, math.pi / 2), odo0) is None  # one is not enough
    # the true pose after that motion: 1 m along +y from (2, 3), now facing −x
    assert search.offer(0.5, _answer(2.0, 4.0, math.pi), odo1) is not None
    # the same answer twice, though the odometry says it drove a metre: refused
    search = RelocalizationSearch("since the start", 0.0)
    search.offer(0.0, _answer(2.0, 3.0, 0.0), odo0)
    assert search.offer(0.5, _answer(2.0, 3.0, 0.0), odo1) is None
    assert "disagree" in search.describe()
    # a refusal in between breaks nothing, answers too far apart in time do not pair
    search = RelocalizationSearch("since the start", 0.0)
    search.offer(0.0, _answer(2.0, 3.0, 0.0), odo0)
    assert search.offer(0.25, Relocalization(False, why="ambiguous"), odo0) is None
    assert search.offer(4.0, _answer(2.0, 3.0, 0.0), odo0) is None


def test_a_localizer_with_no_prior_halts_until_a_checked_relocalization() -> None:
    m = _map()
    loc = Localizer(m)
    loc.lose("since the start (no prior pose)")
    truth = (1.0, -1.5, 2.0)
    seen = []

    def frame(t: float) -> None:
        seen.append(t)
        if loc.searching:
            loc.relocalization(t, _answer(*truth))
        loc.bearings(t, *_bearings(m, *truth))

    _stand(loc, 0.0, 0.3)
    c = loc.containment()
    assert not c.permit and c.reason == Reason.NOT_LOCALIZED and "searching" in c.detail
    _stand(loc, 0.3, 6.0, frame)
    assert loc.counters.relocalizations == 1 and loc.counters.checks_passed == 1
    assert loc.localized and np.linalg.norm(loc.pose().position[:2] - truth[:2]) < 0.01
    assert loc.containment().permit


def test_a_wrong_relocalization_never_permits() -> None:
    """Two frames agree on a pose 0.3 m off (a look-alike place, say). When the bearings
    that follow are right, they pull the filter to the truth and the check passes there;
    when they cannot fix it (here every bearing names the wrong landmark), the check fails
    and the search starts again. Either way the deck never runs while the pose is wrong."""
    m = _map()
    truth, wrong = (1.0, -1.5, 2.0), (1.3, -1.5, 2.0)
    for mixed_up in (False, True):
        loc = Localizer(m)
        loc.lose("since the start (no prior pose)")
        wrong_permits: list[bool] = []

        def frame(
            t: float,
            loc: Localizer = loc,
            mixed_up: bool = mixed_up,
            wrong_permits: list[bool] = wrong_permits,
        ) -> None:
            if loc.searching and loc.counters.relocalizations == 0:
                loc.relocalization(t, _answer(*wrong))
            ids, b = _bearings(m, *truth)
            loc.bearings(t, np.roll(ids, 1) if mixed_up else ids, b)
            off = np.linalg.norm(loc.pose().position[:2] - truth[:2])
            wrong_permits.append(loc.containment().permit and off > 0.15)

        _stand(loc, 0.0, 2.0 + PROBATION_S, frame)
        assert loc.counters.relocalizations == 1 and not any(wrong_permits)
        if not mixed_up:
            assert loc.counters.checks_passed == 1 and loc.localized
            assert np.linalg.norm(loc.pose().position[:2] - truth[:2]) < 0.05
        else:
            assert loc.counters.checks_failed == 1 and loc.searching
            assert "did not check out" in loc.containment().detail


def test_a_lift_drops_the_pose_and_no_answer_pairs_across_it() -> None:
    m = _map()
    loc = Localizer(m)
    loc.relocalizes = True  # as MowVision makes it
    _stand(loc, 0.0, 0.5)
    loc.lifted()
    assert loc.searching and "lifted" in loc.containment().detail
    loc.relocalization(1.0, _answer(1.0, 1.0, 0.0))
    loc.lifted()  # still in the air: the answer before cannot pair with one after
    assert not loc.relocalization(1.25, _answer(1.0, 1.0, 0.0))
    assert loc.counters.searches == 1
    plain = Localizer(m)  # bearing level, no relocalizer: the lock-out path recovers
    plain.lifted()
    assert not plain.searching
