"""Trusting a pose again (issue 18): the search's two-frame acceptance through the odometry,
the consistency check after a re-localization, a lift that drops the pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mowerhw.common.geometry import yaw_rotation
from mowerhw.map import Landmark, LawnMap
from mowerhw.mow import Localizer, Reason
from mowerhw.mow.recovery import PAIR_S, PROBATION_S, Pose2D, RelocalizationSearch
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


def test_a_doubted_place_needs_a_run_of_answers_with_no_doubt_between() -> None:
    """A frame that saw a rival place or pose breaks the pair across it, and after it the
    place needs CLEAR_ANSWERS answers in a row (stop 75: a standing look-alike start whose
    answers flickered with "not pinned down" was accepted 0.25 m off)."""
    from mowerhw.mow.recovery import CLEAR_ANSWERS

    odo = Pose2D(0.0, 0.0, 0.0)
    doubt = Relocalization(False, why="not pinned down: …", rival=True)
    blind = Relocalization(False, why="3 bearings, 30 landmarks")  # cannot tell: no doubt
    # no doubt: two answers that agree are enough, a frame that cannot tell breaks nothing
    search = RelocalizationSearch("since the start", 0.0)
    search.offer(0.0, _answer(2.0, 3.0, 0.0), odo)
    assert search.offer(0.25, blind, odo) is None
    assert search.offer(0.5, _answer(2.0, 3.0, 0.0), odo) is not None
    # an answer, a doubt, an answer: not paired across the doubt
    search = RelocalizationSearch("since the start", 0.0)
    search.offer(0.0, _answer(2.0, 3.0, 0.0), odo)
    search.offer(0.25, doubt, odo)
    t = 0.5
    for k in range(1, CLEAR_ANSWERS):  # then answers in a row: not enough until the last
        assert search.offer(t, _answer(2.0, 3.0, 0.0), odo) is None, k
        t += 0.25
    assert "a frame doubted the place" in search.describe()
    assert search.offer(t, _answer(2.0, 3.0, 0.0), odo) is not None
    # a doubt inside the run starts it again
    search = RelocalizationSearch("since the start", 0.0)
    search.offer(0.0, doubt, odo)
    answers = [True] * (CLEAR_ANSWERS - 1) + [False] + [True] * (CLEAR_ANSWERS - 1)
    for k, ok in enumerate(answers):
        got = search.offer(0.25 * (k + 1), _answer(2.0, 3.0, 0.0) if ok else doubt, odo)
        assert got is None, k
    # an answer too old to pair with the next starts no run either: after a doubt, an
    # answer, a gap over PAIR_S, then answers in a row: the one before the gap does not count
    search = RelocalizationSearch("since the start", 0.0)
    search.offer(0.0, doubt, odo)
    search.offer(0.25, _answer(2.0, 3.0, 0.0), odo)
    t = 0.25 + PAIR_S + 0.5
    for k in range(1, CLEAR_ANSWERS):
        assert search.offer(t, _answer(2.0, 3.0, 0.0), odo) is None, k
        t += 0.25
    assert search.offer(t, _answer(2.0, 3.0, 0.0), odo) is not None


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


def test_a_frame_after_a_lift_asks_the_front_end_for_new_tracks() -> None:
    """Every frame searched after the mower was lifted (the supervisor says so at every IMU
    sample while it is) tells the front end to forget its tracks; the frames after it, with
    the mower standing, keep theirs."""
    from mowerhw.sim import make_world
    from mowerhw.vision.mow import MowVision

    world = make_world("paper", 1)
    loc = Localizer(_map())
    vision = MowVision(loc, world.camera, world.q_bc)
    first = vision.wants_search()
    assert first is not None and not first.carried  # searching from the start, never lifted
    loc.lifted()
    loc.lifted()
    after = vision.wants_search()
    assert after is not None and after.carried
    again = vision.wants_search()
    assert again is not None and not again.carried


def test_an_accepted_answer_hands_its_landmark_cross_covariance_to_the_filter() -> None:
    """The filter restarts from an accepted answer knowing which map errors it shares with
    it: the answer's cross-covariance lands in the filter's consider terms, in the columns
    of the landmarks the answer names (map ids, not the answer's own order)."""
    import dataclasses

    base = _map()
    lms = [Landmark(100 + lm.id, lm.xyz, lm.covariance) for lm in base.landmarks]
    m = LawnMap(boundary=base.boundary, landmarks=lms, camera=None, teach={})
    loc = Localizer(m)
    loc.lose("since the start (no prior pose)")
    truth = (1.0, -1.5, 2.0)
    rows = [17, 3, 8]
    cross = np.arange(1.0, 28.0).reshape(3, 9) * 1e-9
    answer = dataclasses.replace(
        _answer(*truth), inliers=[(k, 100 + r) for k, r in enumerate(rows)], landmark_cross=cross
    )
    accepted = False
    _stand(loc, 0.0, 0.3)
    for t in (0.3, 0.55):
        accepted = loc.relocalization(t, answer) or accepted
        _stand(loc, t, t + 0.25)
    assert accepted and loc.counters.relocalizations == 1
    pxl = loc.ekf.snapshot().pxl
    for k, r in enumerate(rows):
        got = pxl[np.ix_([0, 1, 5], range(3 * r, 3 * r + 3))]
        assert np.allclose(got, cross[:, 3 * k : 3 * k + 3], rtol=0.05), (r, got)
    others = np.setdiff1d(np.arange(pxl.shape[1]), [3 * r + a for r in rows for a in range(3)])
    assert np.all(pxl[:, others] == 0.0)


def test_the_map_check_finds_honest_landmark_covariances_honest_and_wide_ones_wide() -> None:
    """:func:`map_landmark_nees` (the recovery benchmark's check of the map): landmarks off
    their truth by draws from their own covariance, in a frame shifted, turned and scaled
    from the truth's, average a NEES of 3; the same map saying 4× its σ reads 16× lower."""
    from scipy.stats import chi2

    from mowerhw.evaluation.recovery import map_landmark_nees

    rng = np.random.default_rng(5)
    truth = rng.uniform(-10, 10, (60, 3))
    cov = np.diag([0.01, 0.012, 0.006]) ** 2
    c, s = math.cos(0.3), math.sin(0.3)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    est = 1.01 * (truth + rng.normal(size=truth.shape) * np.sqrt(np.diag(cov))) @ turn.T + 2.0

    def check(scale: float) -> float:
        # the map's frame is turned and 1 % bigger: so are the errors' covariances there
        in_map = turn @ cov @ turn.T * (1.01 * scale) ** 2
        lms = [Landmark(i, est[i], in_map) for i in range(len(est))]
        m = LawnMap(boundary=_map().boundary, landmarks=lms, camera=None, teach={})
        m.teach["sim"] = {"landmark_truth": {str(i): truth[i].tolist() for i in range(60)}}
        out = map_landmark_nees(m)
        assert out is not None and out["landmarks"] == 60
        return float(out["nees_mean"])

    lo, hi = chi2.ppf([0.005, 0.995], 3 * 60) / 60
    assert lo <= check(1.0) <= hi
    assert check(4.0) < lo / 8


def test_the_frame_check_finds_an_honest_frame_covariance_honest_and_a_wide_one_wide() -> None:
    """:func:`map_frame_nees`: maps whose whole frame is off the truth by a draw from their
    own frame covariance (a shift, a turn and a scale, frame_jacobian's δ) average a NEES of
    4 and read each part's error back (z² about 1); the same maps saying 4× their σ read 16×
    lower; a map without the truth or the covariance is left out."""
    from scipy.stats import chi2

    from mowerhw.common.geometry import frame_jacobian
    from mowerhw.evaluation.recovery import map_frame_error, map_frame_nees

    rng = np.random.default_rng(4)
    sigma = np.array([0.003, 0.002, 0.001, 0.0005])
    corr = np.array(
        [[1.0, 0.3, 0.2, 0.0], [0.3, 1.0, -0.4, 0.1], [0.2, -0.4, 1.0, 0.0], [0.0, 0.1, 0.0, 1.0]]
    )
    cov = corr * np.outer(sigma, sigma)
    base = _map()

    def maps(declared: float) -> list[LawnMap]:
        out = []
        for k in range(200):
            truth = np.c_[rng.uniform(-12, 12, (40, 2)), rng.uniform(0, 3, 40)]
            delta = rng.multivariate_normal(np.zeros(4), cov)
            est = truth + frame_jacobian(truth) @ delta + rng.normal(0, 1e-5, truth.shape)
            lms = [Landmark(i, est[i], np.eye(3) * 1e-8) for i in range(40)]
            m = LawnMap(boundary=base.boundary, landmarks=lms, camera=None, teach={})
            m.teach["sim"] = {"landmark_truth": {str(i): truth[i].tolist() for i in range(40)}}
            m.frame_covariance = cov * declared**2
            if k == 0:
                err = map_frame_error(m)
                assert err is not None and np.allclose(err, delta, atol=1e-5)
            out.append(m)
        return out

    lo, hi = chi2.ppf([0.005, 0.995], 4 * 200) / 200
    honest = map_frame_nees(maps(1.0))
    assert honest is not None and honest["maps"] == 200 and honest["dof"] == 4
    assert lo <= honest["nees_mean"] <= hi
    assert all(0.75 < z2 < 1.3 for z2 in honest["z2_shift_x_y_turn_scale"])
    wide = map_frame_nees(maps(4.0))
    assert wide is not None and wide["nees_mean"] < lo / 8
    no_truth = LawnMap(boundary=base.boundary, landmarks=base.landmarks, camera=None, teach={})
    no_truth.frame_covariance = cov
    assert map_frame_nees([no_truth]) is None
    assert map_frame_nees([base]) is None  # neither the truth nor the covariance


def test_a_landmark_far_off_the_rest_does_not_move_the_maps_frame() -> None:
    """:func:`map_alignment` fits the frame the consistent landmarks define: a map whose 80
    landmarks sit 1 mm (rms) off a known similarity reads that similarity back to 0.1 mm,
    0.01° and 10 ppm, with two landmarks 0.3 m off as without them; least squares over all of
    them (the old fit) would have moved the frame by mm."""
    from mowerhw.evaluation.recovery import _similarity, map_alignment, map_frame_error

    rng = np.random.default_rng(72)
    base = _map()
    truth = np.c_[rng.uniform(-12, 12, (80, 2)), rng.uniform(0, 3, 80)]
    turn, scale, shift = 0.002, 1.0005, np.array([0.004, -0.003])
    c, s = np.cos(turn), np.sin(turn)
    r = np.array([[c, -s], [s, c]])
    est = truth.copy()
    est[:, :2] = scale * truth[:, :2] @ r.T + shift + rng.normal(0, 0.0007, (80, 2))

    def map_of(points: np.ndarray) -> LawnMap:
        lms = [Landmark(i, points[i], np.eye(3) * 1e-6) for i in range(80)]
        m = LawnMap(boundary=base.boundary, landmarks=lms, camera=None, teach={})
        m.teach["sim"] = {"landmark_truth": {str(i): truth[i].tolist() for i in range(80)}}
        return m

    clean = map_frame_error(map_of(est))
    far = est.copy()
    far[[5, 40], :2] += np.array([[0.3, 0.0], [0.0, -0.25]])
    robust = map_frame_error(map_of(far))
    assert clean is not None and robust is not None
    assert np.allclose(robust, clean, atol=[1e-4, 1e-4, 2e-4, 1e-5]), (robust, clean)
    # the truth ≈ s R m + t: the map is off by the inverse of (shift, turn, scale)
    align = map_alignment(map_of(far))
    assert align is not None and abs(align[3] + turn) < 2e-4 and abs(align[0] * scale - 1) < 1e-5
    _, _, t_all = _similarity(far[:, :2], truth[:, :2])
    assert np.hypot(*(t_all - align[2])) > 0.003  # what least squares over all would say


def test_the_per_relocalization_nees_shows_a_heavy_tail_the_bin_means_hide() -> None:
    """:func:`per_relocalization_nees`: 400 relocalizations whose errors are drawn from
    their covariance (each a held error: one χ²₃ draw over its 10 s) have about 2.5 % on
    either side of the χ²₃ interval; a mixture with the same mean of 3 — 90 % at a third of
    their σ² and 10 % at 7× — has 4× as many below and 2× as many above, and its top tenth
    carries most of the NEES."""
    from mowerhw.evaluation.recovery import per_relocalization_nees

    rng = np.random.default_rng(18)

    def runs(scales: np.ndarray) -> list[np.ndarray]:
        return [np.full(1000, s * rng.chisquare(3)) for s in scales]

    honest = per_relocalization_nees(runs(np.ones(400)))
    assert honest["relocalizations"] == 400
    assert 2 <= honest["below_interval"] <= 20 and 2 <= honest["above_interval"] <= 20
    assert 2.0 <= honest["mean_nees"]["median"] <= 2.8  # χ²₃ median 2.37
    tail = per_relocalization_nees(runs(np.where(np.arange(400) < 360, 1 / 3, 7.0)))
    assert tail["below_interval"] > 3 * honest["below_interval"]
    assert tail["above_interval"] > 1.5 * honest["above_interval"]
    assert tail["share_of_nees_from_top_10pct"] > 0.6 > honest["share_of_nees_from_top_10pct"]
    assert per_relocalization_nees([]) == {"relocalizations": 0}


def test_bearing_errors_are_told_apart_into_what_stays_and_what_changes() -> None:
    """:func:`bearing_error_figures` (issue 18's measurement of the pixel-level bearings):
    on made-up errors — a per-landmark bias of 0.1°, then AR(1) noise of 0.05° whose
    frame-to-frame correlation is 0.8 — it finds each part; and :func:`bearing_error` reads
    a bearing turned 0.2° to the left as +0.2° of azimuth."""
    from mowerhw.evaluation.pixel import bearing_error, bearing_error_figures

    rng = np.random.default_rng(8)
    rows = []
    for landmark in range(40):
        bias, ar = rng.normal(0.0, math.radians(0.1)), 0.0
        for k in range(200):
            ar = 0.8 * ar + rng.normal(0.0, math.radians(0.05) * math.sqrt(1 - 0.64))
            rows.append((0.25 * k, landmark, bias + ar, 0.0))
    fig = bearing_error_figures(np.array(rows))
    assert fig["landmarks"] == 40 and fig["frames"] == 200
    assert 0.07 < fig["landmark_bias_rms_deg"] < 0.13
    assert 0.04 < fig["within_landmark_rms_deg"] < 0.06
    assert 0.7 < fig["next_frame_correlation"] < 0.85
    assert 0.25 < fig["fourth_frame_correlation"] < 0.55  # 0.8⁴ = 0.41
    point = np.array([10.0, 0.0, 1.0])
    turned = yaw_rotation(math.radians(0.2)) @ (point / np.linalg.norm(point))
    az, el = bearing_error(np.zeros(2), 0.0, turned, point)
    assert az == pytest.approx(math.radians(0.2), abs=1e-9) and abs(el) < 1e-9


def test_starts_over_several_maps_pool_their_scores_and_nees(monkeypatch) -> None:
    """``runs_over_maps``, starts: each map's starts scored on their own (``per_map``) and
    together, every relocalization's NEES in one pool — one map's wrong answer shows in the
    pooled per-relocalization tail."""
    from mowerhw.evaluation import recovery as R

    def run(seed: int, error_m: float, nees: float) -> dict[str, object]:
        return {
            "accepted_s": 0.4,
            "error_m": error_m,
            "yaw_error_deg": 0.01,
            "permits_wrong": 50 if error_m > R.WRONG_M else 0,
            "missed_halts": 0,
            "nees": nees,
        }

    def fake_starts(lawn_map, scenario, seed, starts, config, seconds, progress, compass):
        log = R._NeesLog(None)
        runs = [
            run(seed, 0.2 if seed == 2 and i == 0 else 0.005, 500.0 if seed == 2 else 3.0)
            for i in range(starts)
        ]
        log.series = [np.full(1000, r["nees"]) for r in runs]
        log.aligned = [np.full(1000, r["nees"]) for r in runs]
        return runs, log

    monkeypatch.setattr(R, "_starts", fake_starts)
    made: list[int] = []
    out = R.runs_over_maps([1, 2, 3], made.append, "paper", 4, 0)
    assert made == [1, 2, 3] and "kidnaps" not in out  # each map made once, in its task
    assert out["maps"] == 3
    out = out["starts"]
    assert out["starts"] == 12
    assert [m["seed"] for m in out["per_map"]] == [1, 2, 3]
    assert [m["accepted_wrong_over_0.15m"] for m in out["per_map"]] == [0, 1, 0]
    assert (
        out["accepted_wrong_over_0.15m"] == 1 and out["permit_samples_while_wrong_over_0.15m"] == 50
    )
    assert out["success_rate"] == round(11 / 12, 3)
    assert {r["seed"] for r in out["runs"]} == {1, 2, 3}
    for key in ("nees", "nees_in_map_frame"):
        per = out[key]["per_relocalization"]
        assert per["relocalizations"] == 12 and per["above_interval"] == 4


def test_kidnaps_over_several_maps_pool_their_scores_and_nees(monkeypatch) -> None:
    """``runs_over_maps``, kidnaps: each map's kidnaps scored on their own (``per_map``) and
    together — a wrong relocalization permitted on one map counts in the pool, a run that
    was never kidnapped while mowing counts in neither."""
    from mowerhw.evaluation import recovery as R

    def run(wrong: bool, reloc: float | None) -> dict[str, object]:
        return {
            "time_to_halt_s": 0.01,
            "time_to_relocalize_s": reloc,
            "permits_during_carry": 0,
            "permits_before_halt_over_0.15m": 0,
            "permits_wrong_after_relocalization": 40 if wrong else 0,
            "missed_halts": 0,
        }

    def fake_kidnaps(lawn_map, scenario, seed, runs, config, lifted, progress, compass):
        out: list[dict[str, object]] = [
            run(seed == 2 and i == 0, 2.3 + 0.01 * i) for i in range(runs)
        ]
        if seed == 3:
            out[-1] = {"walk_m": 7.0, "kidnapped": False}
        log = R._NeesLog(None)
        log.series = [np.full(1000, 3.0) for r in out if r.get("kidnapped", True)]
        log.aligned = list(log.series)
        return out, log

    monkeypatch.setattr(R, "_kidnaps", fake_kidnaps)
    out = R.runs_over_maps([1, 2, 3], lambda seed: None, "paper", 0, 4)
    assert out["maps"] == 3 and "starts" not in out
    out = out["kidnaps"]
    assert out["runs"] == 12
    assert [m["seed"] for m in out["per_map"]] == [1, 2, 3]
    assert [m["kidnapped_while_mowing"] for m in out["per_map"]] == [4, 4, 3]
    assert [m["wrong_relocalizations_permitted"] for m in out["per_map"]] == [0, 1, 0]
    assert out["kidnapped_while_mowing"] == 11 and out["relocalized"] == 11
    assert out["wrong_relocalizations_permitted"] == 1
    assert {r["seed"] for r in out["per_run"]} == {1, 2, 3}
    assert out["nees"]["per_relocalization"]["relocalizations"] == 11


def test_pixel_maps_keep_a_taught_map_and_refuse_another_yards(monkeypatch, tmp_path, map_file):
    """``PixelMaps`` with a folder: a map taught once is written there and loaded the next
    time (not taught again); a file there that is another yard's map is refused by name."""
    from mowerhw.evaluation import pixel
    from mowerhw.map import load

    taught: list[int] = []

    def fake_pixel_map(scenario, seed, config, path=None, save=None):
        taught.append(seed)
        lawn_map = load(map_file)
        lawn_map.teach["sim"] = {"scenario": scenario, "seed": seed, "level": "pixel"}
        if save:
            lawn_map.save(save)
        return lawn_map

    monkeypatch.setattr(pixel, "pixel_map", fake_pixel_map)
    maps = pixel.PixelMaps("paper", object(), str(tmp_path / "kept"))  # type: ignore[arg-type]
    first = maps(4)
    again = maps(4)
    assert taught == [4] and (tmp_path / "kept" / "paper_4.json").exists()
    assert (
        again.teach["sim"]
        == first.teach["sim"]
        == {"scenario": "paper", "seed": 4, "level": "pixel"}
    )
    (tmp_path / "kept" / "paper_4.json").rename(tmp_path / "kept" / "paper_5.json")
    with pytest.raises(ValueError, match=r"paper_5\.json: kept map is of scenario 'paper', seed 4"):
        maps(5)
    assert taught == [4]


def test_the_nees_split_by_component_and_phase_names_the_over_sure_part() -> None:
    """``component_summary``: x held at twice its σ while the mower stands (the first 2.5 s),
    at its σ after; y at its σ throughout; the heading exact — each component's z² per
    phase, and its rms error and σ in mm and degrees."""
    from mowerhw.evaluation.recovery import component_summary

    n, dt = 1000, 0.01
    sigma = np.array([0.002, 0.003, math.radians(0.02)])
    err = np.tile(sigma * [1.0, 1.0, 0.0], (n, 1))
    err[:250, 0] *= 2.0
    cov = np.tile(np.diag(sigma**2), (n, 1, 1))
    rows = component_summary([(err, cov), (-err, cov)], dt)
    assert [(r["from_s"], r["to_s"]) for r in rows] == [(0.0, 2.5), (2.5, 5.0), (5.0, 10.0)]
    assert rows[0]["z2_x_y_heading"] == [4.0, 1.0, 0.0]
    assert rows[1]["z2_x_y_heading"] == rows[2]["z2_x_y_heading"] == [1.0, 1.0, 0.0]
    assert rows[0]["rms_error_mm_mm_deg"] == [4.0, 3.0, 0.0]
    assert rows[2]["rms_sigma_mm_mm_deg"] == [2.0, 3.0, 0.02]
    assert component_summary([(err[:100], cov[:100])], dt)[-1]["to_s"] == 2.5  # short: one phase


def test_a_kidnap_runs_nees_is_also_told_apart_for_its_start_and_its_kidnap() -> None:
    """A kidnap run relocalizes at its start (then turns out of the dock) and again after
    the kidnap: the pool's NEES is told apart for the two as well, each relocalization by
    when it came (before or after the kidnap), each kind's bins and components its own."""
    from types import SimpleNamespace

    from mowerhw.evaluation import recovery as R

    n, dt = 4000, 0.01
    t = np.arange(n) * dt
    relocs = np.zeros(n, np.int64)
    relocs[25:] = 1  # accepted at 0.25 s: the start
    relocs[2500:] = 2  # at 25 s, after a kidnap at 20 s
    est = np.zeros((n, 7))
    est[:, 3] = 1.0  # heading 0
    true_xy = np.zeros((n, 2))
    true_xy[:2500, 0] = 0.002  # 2 mm off before the kidnap's relocalization, 0 after it
    cov = np.tile(np.diag([1e-6, 1e-6, 1e-6]), (n, 1, 1))
    out = SimpleNamespace(
        t=t, relocalizations=relocs, est=est, true_xy=true_xy, true_yaw=np.zeros(n),
        cov_xy_yaw=cov, cov_xy_yaw_ground=cov,
    )  # fmt: skip
    log = R._NeesLog(None)
    log.add(out, 20.0)  # type: ignore[arg-type]
    assert log.kinds == [R.AT_THE_START, R.AFTER_THE_KIDNAP]
    kinds = log.summary()["nees_by_kind"]
    assert kinds[R.AT_THE_START]["nees"]["mean_nees"] == 4.0  # (2 mm / 1 mm)²
    assert kinds[R.AFTER_THE_KIDNAP]["nees"]["mean_nees"] == 0.0
    assert kinds[R.AT_THE_START]["nees_in_map_frame"] is None  # no map to align
    assert kinds[R.AT_THE_START]["components_in_map_frame"] is None
    aligned = R._NeesLog(None)
    aligned.align = (1.0, np.eye(2), np.zeros(2), 0.0)  # the map's frame is the truth's
    aligned.add(out, 20.0)  # type: ignore[arg-type]
    parts = aligned.summary()["nees_by_kind"]
    start = parts[R.AT_THE_START]["components_in_map_frame"][0]
    kidnap = parts[R.AFTER_THE_KIDNAP]["components_in_map_frame"][0]
    assert start["z2_x_y_heading"] == [4.0, 0.0, 0.0]  # the x error is the start's alone
    assert kidnap["z2_x_y_heading"] == [0.0, 0.0, 0.0]
    assert parts[R.AT_THE_START]["components_in_map_frame_along_track"][0][
        "z2_along_sideways_heading"
    ] == [4.0, 0.0, 0.0]  # heading 0: along-track is x
    plain = R._NeesLog(None)
    plain.add(out)  # a start run: every relocalization is of one kind, no split
    assert "nees_by_kind" not in plain.summary()


def test_the_nees_split_along_the_track_and_sideways_follows_the_true_heading() -> None:
    """The mower's own axes: an error along world x while the mower heads along world y
    (90°) is sideways (to its right, −), one along world y is along-track; the covariance
    turns with it (x's σ 1 mm, y's 3 mm → along-track 3 mm, sideways 1 mm)."""
    from types import SimpleNamespace

    from mowerhw.evaluation import recovery as R

    n, dt = 1000, 0.01
    relocs = np.zeros(n, np.int64)
    relocs[10:] = 1
    est = np.zeros((n, 7))
    est[:, 3], est[:, 6] = math.cos(math.pi / 4), math.sin(math.pi / 4)  # heading 90°
    true_xy = np.zeros((n, 2))
    true_xy[:500, 0] = -0.002  # the estimate 2 mm along +x of the truth: 2 σ of x
    true_xy[500:, 1] = -0.006  # then 6 mm along +y: 2 σ of y
    cov = np.tile(np.diag([1e-6, 9e-6, 1e-6]), (n, 1, 1))
    out = SimpleNamespace(
        t=np.arange(n) * dt, relocalizations=relocs, est=est, true_xy=true_xy,
        true_yaw=np.full(n, math.pi / 2), cov_xy_yaw=cov, cov_xy_yaw_ground=cov,
    )  # fmt: skip
    log = R._NeesLog(None)
    log.align = (1.0, np.eye(2), np.zeros(2), 0.0)
    log.add(out)  # type: ignore[arg-type]
    ((err, turned),) = log.along_track
    assert err[0] == pytest.approx([0.0, -0.002, 0.0], abs=1e-12)
    assert err[-1] == pytest.approx([0.006, 0.0, 0.0], abs=1e-12)
    assert turned[0] == pytest.approx(np.diag([9e-6, 1e-6, 1e-6]), abs=1e-15)
    rows = log.summary()["components_in_map_frame_along_track"]
    assert rows[0]["z2_along_sideways_heading"] == [0.0, 4.0, 0.0]  # 0–2.5 s: x's error
    assert rows[2]["z2_along_sideways_heading"] == [4.0, 0.0, 0.0]  # 5–10 s: y's error
    assert rows[2]["rms_sigma_mm_mm_deg"][:2] == [3.0, 1.0]


def test_a_start_runs_record_names_its_relocalizations_error_sigma_and_standing_nees() -> None:
    """A start run's ``--per-run`` record (:func:`_first_relocalization`): its first
    relocalization's error and σ in the map's frame at acceptance (mm, mm, degrees) and its
    mean NEES while it stands — which runs make a NEES bin's tail, and with what; nothing
    for a run that never relocalized."""
    from mowerhw.evaluation import recovery as R

    log = R._NeesLog(None)
    log.dt = 0.01
    err = np.tile([0.006, -0.002, math.radians(0.01)], (1000, 1))
    cov = np.tile(np.diag([0.002, 0.004, math.radians(0.02)]) ** 2, (1000, 1, 1))
    log.components = [(err, cov)]
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    log.aligned = [nees]
    got = R._first_relocalization(log, 1)
    assert got["map_frame_error_mm_mm_deg"] == [6.0, -2.0, 0.01]
    assert got["map_frame_sigma_mm_mm_deg"] == [2.0, 4.0, 0.02]
    assert got["map_frame_nees_standing"] == pytest.approx(9.0 + 0.25 + 0.25, abs=0.01)
    assert R._first_relocalization(log, 0) == {}
