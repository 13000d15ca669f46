"""Starting anywhere and being carried elsewhere, at pixel level (issue 18), scored on truth.

Both run the closed loop of :func:`mowerhw.evaluation.mow.run_mow` (rendered frames, the
front end, :class:`mowerhw.vision.MowVision`, the localizer, the gate, the safety functions):

* :func:`start_runs` — the mower stands at a random pose inside the lawn and the localizer has
  no prior: it searches (global relocalization), accepts, checks, and only then may permit;
* :func:`kidnap_runs` — the mower mows from the dock, is lifted mid-mow and carried 5–20 m
  to a random pose, and put down: the lift halts the deck, the localizer gives its pose up,
  searches, and mowing goes on only after an accepted relocalization. The walk is 5–20 m
  long (its duration); it ends at a random pose inside the lawn at least 4 m from where
  it began where the lawn allows (the displacement is reported).

Scored per run: when the pose was accepted and how far off it was then, permits while the
pose was more than :data:`WRONG_M` off (the dangerous case), missed halts (permits truly
outside), and the NEES of (x, y, heading) in the :data:`NEES_S` after every accepted
relocalization against the χ²₃ bounds of the runs' average — against the truth, and against
the truth expressed in the map's frame (:func:`map_alignment`: containment's boundary lives in
that frame, so an error the whole map shares moves the boundary with the pose).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from scipy.stats import chi2

from mowerhw.common.geometry import quat_to_yaw, wrap_angle
from mowerhw.config import Config
from mowerhw.evaluation.mow import MowOutcome, landmark_truth, run_mow
from mowerhw.map import LawnMap
from mowerhw.sim import make_world
from mowerhw.sim.handling import Kidnap

FloatArray = NDArray[np.float64]

WRONG_M = 0.15
SUCCESS_M, SUCCESS_RAD = 0.10, math.radians(3.0)
NEES_S = 10.0
CARRY_MPS = 1.5  # walking with a mower in the arms
MOW_BEFORE_S = 15.0  # mowing from the dock before the kidnap
AFTER_S = 20.0  # simulated after the mower is put down
#: put down at least this far from where it was picked up, where the lawn allows (m)
MIN_DISPLACEMENT_M = 4.0
#: simulated after each start with no prior (s)
START_S = 12.0

Runs = list[dict[str, Any]]  # one dict per run


def _pct(a: list[float], q: float) -> float | None:
    return round(float(np.percentile(a, q)), 3) if a else None


def _inside(scenario: str, seed: int, margin_m: float) -> shapely.Polygon:
    world = make_world(scenario, seed)
    return shapely.Polygon(world.lawn.outline(720)).buffer(-margin_m)


def random_pose(lawn: shapely.Polygon, rng: np.random.Generator) -> tuple[float, float, float]:
    """A uniform position inside ``lawn`` (simulator map frame) and a uniform heading."""
    minx, miny, maxx, maxy = lawn.bounds
    while True:
        x, y = rng.uniform(minx, maxx), rng.uniform(miny, maxy)
        if lawn.contains(shapely.Point(x, y)):
            return float(x), float(y), float(rng.uniform(-math.pi, math.pi))


Alignment = tuple[float, FloatArray, FloatArray, float]  # scale, R (2×2), t (2,), rotation


def _pose_errors(out: MowOutcome, align: Alignment | None = None) -> FloatArray:
    """Per sample (K, 3): the estimate's x, y and heading minus the truth's (heading
    wrapped), or (``align``) the estimate's taken into the truth's frame by the map's
    similarity first."""
    est_xy, yaw = out.est[:, :2], quat_to_yaw(out.est[:, 3:])
    if align is not None:
        scale, r, t, rot = align
        est_xy, yaw = scale * est_xy @ r.T + t, yaw + rot
    return np.column_stack([est_xy - out.true_xy, wrap_angle(yaw - out.true_yaw)])


def _errors(out: MowOutcome) -> tuple[FloatArray, FloatArray]:
    """Per sample: horizontal position error (m) and heading error (rad)."""
    e = _pose_errors(out)
    return np.linalg.norm(e[:, :2], axis=1), np.abs(e[:, 2])


def _landmark_truth(lawn_map: LawnMap, dims: int) -> tuple[FloatArray, FloatArray]:
    """The map's landmarks whose true position the simulated teach recorded: (their map
    rows, their true positions), the first ``dims`` coordinates."""
    truth = landmark_truth(lawn_map)
    ids = lawn_map.landmark_ids().tolist()
    rows = np.array([k for k, i in enumerate(ids) if i in truth], dtype=np.int64)
    true = np.array([truth[ids[k]][:dims] for k in rows.tolist()], dtype=np.float64)
    return rows, true.reshape(-1, dims)


def _similarity(a: FloatArray, b: FloatArray) -> tuple[float, FloatArray, FloatArray]:
    """``b ≈ s R a + t`` in least squares (Umeyama; a proper rotation), any dimension."""
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    u, sv, vt = np.linalg.svd((a - ma).T @ (b - mb))
    flip = np.ones(a.shape[1])
    flip[-1] = float(np.sign(np.linalg.det(vt.T @ u.T))) or 1.0
    r = vt.T @ np.diag(flip) @ u.T
    scale = float((sv * flip).sum() / ((a - ma) ** 2).sum())
    return scale, r, mb - scale * r @ ma


#: a landmark farther than this many robust σ (1.4826 × the median distance) from the fitted
#: similarity does not define the map's frame (:func:`map_alignment`)
ALIGN_OUTLIER_MADS = 5.0


def _robust_similarity(a: FloatArray, b: FloatArray) -> tuple[float, FloatArray, FloatArray]:
    """:func:`_similarity` refitted without the points farther than
    :data:`ALIGN_OUTLIER_MADS` robust σ from it, until none is left out anew (at least 3
    kept)."""
    keep = np.ones(a.shape[0], dtype=bool)
    for _ in range(10):
        scale, r, t = _similarity(a[keep], b[keep])
        dist = np.linalg.norm(b - (scale * a @ r.T + t), axis=1)
        inside = dist <= ALIGN_OUTLIER_MADS * 1.4826 * float(np.median(dist[keep]))
        if inside.sum() < 3 or np.array_equal(inside, keep):
            break
        keep = inside
    return scale, r, t


def map_alignment(lawn_map: LawnMap) -> Alignment | None:
    """The similarity that takes the map's frame onto the truth (least squares over the
    landmarks whose true position the simulated teach recorded, those that agree with it:
    :func:`_robust_similarity`), or None without them. Containment works in the map's frame —
    its boundary shares the landmarks' errors — so the localizer is judged against the truth
    expressed in that frame as well. The frame is the one the consistent landmarks define: a
    landmark 0.1–0.3 m off (a track the teach re-identified with the wrong point, or whose
    recorded truth is another point than the one it mapped) is what the localizer's gate is
    there to refuse, and fitted with the rest it moved the frame of an 87-landmark map by
    3 mm, as much as the frame's own σ (README, issue 18, stop 72)."""
    rows, true = _landmark_truth(lawn_map, 2)
    if rows.size < 3:
        return None
    scale, r, t = _robust_similarity(lawn_map.landmark_positions()[rows, :2], true)
    return scale, r, t, math.atan2(r[1, 0], r[0, 0])


def _nees_of(err: FloatArray, cov: FloatArray) -> FloatArray:
    """Each row's NEES ``eᵀ C⁻¹ e``: errors (N, d) against their covariances (N, d, d)."""
    out: FloatArray = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    return out


def map_frame_error(lawn_map: LawnMap) -> FloatArray | None:
    """The map frame's error against the ground, ``δ = (t_x, t_y, θ, s)`` of
    :func:`~mowerhw.common.geometry.frame_jacobian` (the map's points sit at the truth's
    ``+ A δ``), from the similarity :func:`map_alignment` fits; None without the truth."""
    align = map_alignment(lawn_map)
    if align is None:
        return None
    scale, _, t, rot = align  # truth ≈ s R m + t: to first order the map is off by −(t, θ, s−1)
    return -np.array([t[0], t[1], rot, scale - 1.0])


def map_frame_nees(maps: Sequence[LawnMap]) -> dict[str, Any] | None:
    """How honest the maps' :attr:`~mowerhw.map.LawnMap.frame_covariance` is — the part of
    the localizer's covariance against the ground (``Localizer.ground_covariance``) that the
    teach owns: each map's frame error (:func:`map_frame_error`) against it, a NEES of 4
    degrees of freedom (4 on average over honest maps), with each part's error² over its
    variance (1 if honest) and the rms error and σ (mm, mm, millidegrees, ppm). None when no
    map has both the truth and the covariance."""
    errs, covs = [], []
    for m in maps:
        err = map_frame_error(m)
        if err is not None and m.frame_covariance is not None:
            errs.append(err)
            covs.append(np.asarray(m.frame_covariance, dtype=np.float64))
    if not errs:
        return None
    err, cov = np.array(errs), np.array(covs)
    nees = _nees_of(err, cov)
    var = np.diagonal(cov, axis1=1, axis2=2)
    units = np.array([1e3, 1e3, 1e3 * math.degrees(1.0), 1e6])

    def parts(v: FloatArray) -> list[float]:
        return [round(float(x), 3) for x in v]

    return {
        "maps": len(errs),
        "dof": 4,
        "nees_mean": round(float(nees.mean()), 2),
        "nees_median": round(float(np.median(nees)), 2),
        "z2_shift_x_y_turn_scale": parts(np.mean(err**2 / var, axis=0)),
        "rms_error_mm_mm_mdeg_ppm": parts(np.sqrt(np.mean(err**2, axis=0)) * units),
        "rms_sigma_mm_mm_mdeg_ppm": parts(np.sqrt(np.mean(var, axis=0)) * units),
    }


def map_landmark_nees(lawn_map: LawnMap) -> dict[str, Any] | None:
    """How honest the map's landmark covariances are where the localizer uses them: each
    landmark's NEES against its true position taken into the map's frame (the 3-D
    similarity fitted over all of them, as :func:`map_alignment` in the plane), or None
    without the truth. A mean far below 3 says the covariances are wider than the map's
    errors (the localizer then takes the map to be worse than it is). At pixel level the
    truth is itself a few mm off what the tracker follows (the mean of the points a track's
    pixel hit, within ``SAME_POINT_M``), so a mean above 3 there is no proof of an over-sure
    map: the pose NEES after a relocalization is the check."""
    rows, true = _landmark_truth(lawn_map, 3)
    if rows.size < 4:
        return None
    est = lawn_map.landmark_positions()[rows]
    scale, r, t = _similarity(est, true)
    err = est - (true - t) @ r / scale  # against the truth in the map's frame
    cov = lawn_map.landmark_covariances()[rows]
    nees = _nees_of(err, cov)
    return {
        "landmarks": int(rows.size),
        "nees_mean": round(float(nees.mean()), 3),
        "nees_median": round(float(np.median(nees)), 3),
        "dof": 3,
        "error_mm_median": round(1e3 * float(np.median(np.linalg.norm(err, axis=1))), 2),
        "sigma_mm_median": round(
            1e3 * float(np.median(np.sqrt(np.trace(cov, axis1=1, axis2=2) / 3))), 2
        ),
    }


def _after_relocalizations(
    out: MowOutcome, align: Alignment | None = None
) -> list[tuple[FloatArray, FloatArray]]:
    """The (x, y, heading) errors and covariances over :data:`NEES_S` after each accepted
    relocalization: against the truth with the covariance against the ground, or
    (``align``) against the truth in the map's frame with the covariance against the map."""
    err = _pose_errors(out, align)
    covs = out.cov_xy_yaw if align is not None else out.cov_xy_yaw_ground
    return [(err[seg], covs[seg]) for seg in _relocalization_spans(out)]


def _relocalization_spans(out: MowOutcome) -> list[slice]:
    """The samples over :data:`NEES_S` after each accepted relocalization, in order."""
    n = round(NEES_S / float(out.t[1] - out.t[0]))
    return [slice(k, min(k + n, out.t.size)) for k in _accepted_at(out)]


def _along_track(
    out: MowOutcome, segments: list[tuple[FloatArray, FloatArray]]
) -> list[tuple[FloatArray, FloatArray]]:
    """``segments`` (:func:`_after_relocalizations`, one per accepted relocalization of
    ``out``) turned into the mower's own axes at each sample: the position error and its
    covariance along the true heading and sideways of it (heading unchanged). The ground
    speed's noise is along-track and a sideways slip's across: this split says which of the
    two a bin's misfit is."""
    turned = []
    for span, (err, cov) in zip(_relocalization_spans(out), segments, strict=True):
        yaw = out.true_yaw[span]
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.zeros((yaw.size, 3, 3))  # world → body: rows (heading, its left, up-turn)
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, s, -s, c
        rot[:, 2, 2] = 1.0
        turned.append(
            (
                np.einsum("nij,nj->ni", rot, err),
                np.einsum("nij,njk,nlk->nil", rot, cov, rot),
            )
        )
    return turned


def _accepted_at(out: MowOutcome) -> NDArray[np.intp]:
    """The samples at which a relocalization was accepted, in order."""
    return np.flatnonzero(np.diff(out.relocalizations) > 0) + 1


def _nees(segments: list[tuple[FloatArray, FloatArray]]) -> list[FloatArray]:
    """The NEES of (x, y, heading) of each segment (:func:`_after_relocalizations`)."""
    return [_nees_of(e, cov) for e, cov in segments]


#: the phases of :func:`component_summary` (s after acceptance): a relocalized mower stands
#: for the first few seconds (a start: 5 s), then drives
PHASES_S = ((0.0, 2.5), (2.5, 5.0), (5.0, NEES_S))


#: (x, y, heading) in m, m, rad → mm, mm, degrees: how the summaries report them
_MM_MM_DEG = np.array([1e3, 1e3, math.degrees(1.0)])


def _mm_mm_deg(v: FloatArray) -> list[float]:
    """An (x, y, heading) vector in mm, mm and degrees, rounded for the JSON."""
    return [round(float(x), 3) for x in v * _MM_MM_DEG]


def _phase(lo: float, hi: float, dt: float) -> slice:
    """The samples of a series at ``dt`` from ``lo`` to ``hi`` s after its start."""
    return slice(round(lo / dt), round(hi / dt))


def component_summary(
    segments: list[tuple[FloatArray, FloatArray]], dt: float, axes: str = "x_y_heading"
) -> list[dict[str, Any]]:
    """Each component's share of the NEES, phase by phase (:data:`PHASES_S`): the mean of
    its error² over its own variance (1 for an honest filter; the NEES of 3 split into x, y
    and heading, correlations aside), its rms error and its rms σ (mm, mm, degrees). Where a
    bin is over or under, this says which component and when (standing or driving).
    ``axes``: what the three components are, for the keys (``along_sideways_heading``:
    :func:`_along_track`'s)."""
    rows = []
    for lo, hi in PHASES_S:
        part = _phase(lo, hi, dt)
        inside = [(e[part], cov[part]) for e, cov in segments if e[part].size]
        if not inside:
            continue
        err = np.concatenate([e for e, _ in inside])
        var = np.concatenate([np.diagonal(cov, axis1=1, axis2=2) for _, cov in inside])
        rows.append(
            {
                "from_s": lo,
                "to_s": hi,
                f"z2_{axes}": [round(float(v), 2) for v in np.mean(err**2 / var, axis=0)],
                "rms_error_mm_mm_deg": _mm_mm_deg(np.sqrt(np.mean(err**2, axis=0))),
                "rms_sigma_mm_mm_deg": _mm_mm_deg(np.sqrt(np.mean(var, axis=0))),
            }
        )
    return rows


#: what a relocalization in a kidnap run followed: the run's start at the dock (the mower
#: turns out of it at once, its gyro's scale not yet learned) or the kidnap
AT_THE_START, AFTER_THE_KIDNAP = "at_the_start", "after_the_kidnap"


class _NeesLog:
    """The NEES series of every run, against the truth and in the map's frame, each with
    what its relocalization followed (:data:`AT_THE_START`, :data:`AFTER_THE_KIDNAP`)."""

    def __init__(self, lawn_map: LawnMap | None) -> None:
        """``lawn_map`` None: a pool of other logs (:meth:`extend`), each aligned its way."""
        self.align = None if lawn_map is None else map_alignment(lawn_map)
        self.series: list[FloatArray] = []
        self.aligned: list[FloatArray] = []
        #: per relocalization, in the map's frame: errors and covariances (component_summary)
        self.components: list[tuple[FloatArray, FloatArray]] = []
        #: the same in the mower's axes (:func:`_along_track`)
        self.along_track: list[tuple[FloatArray, FloatArray]] = []
        self.kinds: list[str] = []  # per relocalization, what it followed
        self.dt = 0.01

    def extend(self, other: _NeesLog) -> None:
        self.series += other.series
        self.aligned += other.aligned
        self.components += other.components
        self.along_track += other.along_track
        self.kinds += other.kinds
        self.dt = other.dt

    def add(self, out: MowOutcome, kidnapped_at_s: float | None = None) -> None:
        """``out``'s relocalizations; ``kidnapped_at_s``: those from then on followed the
        kidnap, those before it the start."""
        self.dt = float(out.t[1] - out.t[0])
        self.series += _nees(_after_relocalizations(out))
        at = out.t[_accepted_at(out)]
        self.kinds += [
            AFTER_THE_KIDNAP if kidnapped_at_s is not None and t >= kidnapped_at_s else AT_THE_START
            for t in at.tolist()
        ]
        if self.align is not None:
            in_map_frame = _after_relocalizations(out, self.align)
            self.aligned += _nees(in_map_frame)
            self.components += in_map_frame
            self.along_track += _along_track(out, in_map_frame)

    def by_kind(self) -> dict[str, Any] | None:
        """The NEES bins of each kind apart (kidnap runs: the start's and the kidnap's), or
        None when every relocalization is of one kind."""
        kinds = sorted(set(self.kinds))
        if len(kinds) < 2:
            return None
        aligned = len(self.aligned) == len(self.kinds)  # every map had the truth to align
        out = {}
        for kind in kinds:
            mine = [k == kind for k in self.kinds]
            truth = [s for s, m in zip(self.series, mine, strict=True) if m]
            in_map = [s for s, m in zip(self.aligned, mine, strict=True) if m] if aligned else []
            parts = [c for c, m in zip(self.components, mine, strict=True) if m] if aligned else []
            axes = [c for c, m in zip(self.along_track, mine, strict=True) if m] if aligned else []
            out[kind] = {
                "nees": nees_summary(truth, self.dt),
                "nees_in_map_frame": nees_summary(in_map, self.dt) if in_map else None,
                "components_in_map_frame": component_summary(parts, self.dt) if parts else None,
                "components_in_map_frame_along_track": (
                    component_summary(axes, self.dt, "along_sideways_heading") if axes else None
                ),
            }
        return out

    def summary(self) -> dict[str, Any]:
        by_kind = self.by_kind()
        return {
            **({"nees_by_kind": by_kind} if by_kind is not None else {}),
            "nees": nees_summary(self.series, self.dt),
            "nees_in_map_frame": (
                # a map without the truth to align adds none: a pool has them if any map did
                nees_summary(self.aligned, self.dt)
                if self.align is not None or self.aligned
                else None
            ),
            "components_in_map_frame": (
                component_summary(self.components, self.dt) if self.components else None
            ),
            "components_in_map_frame_along_track": (
                component_summary(self.along_track, self.dt, "along_sideways_heading")
                if self.along_track
                else None
            ),
        }


def per_relocalization_nees(series: list[FloatArray]) -> dict[str, Any]:
    """How the NEES is spread over the relocalizations: each one's mean over its
    :data:`NEES_S` (its samples are one error held for seconds, so about one χ²₃ draw), its
    median, p90 and max, and how many fall outside the two-sided 95 % χ²₃ interval (an
    honest filter: about 2.5 % on each side). A bin mean inside its bounds can be most
    relocalizations far below 3 and a few far above (a heavy tail), which the bins alone do
    not show."""
    means = np.array([float(np.mean(s)) for s in series if s.size])
    if means.size == 0:
        return {"relocalizations": 0}
    lo, hi = chi2.ppf([0.025, 0.975], 3)
    top = np.sort(means)[::-1][: max(1, math.ceil(0.1 * means.size))]
    total = float(means.sum())  # 0 only for errors of exactly 0 (then no share: null)
    return {
        "relocalizations": int(means.size),
        "mean_nees": {
            "median": round(float(np.median(means)), 2),
            "p90": round(float(np.percentile(means, 90)), 2),
            "max": round(float(means.max()), 2),
        },
        "chi2_95pct_interval": [round(float(lo), 3), round(float(hi), 2)],
        "below_interval": int(np.sum(means < lo)),
        "above_interval": int(np.sum(means > hi)),
        "share_of_nees_from_top_10pct": (
            round(float(top.sum()) / total, 3) if total > 0.0 else None
        ),
    }


def nees_summary(series: list[FloatArray], dt: float) -> dict[str, Any]:
    """Average NEES over the runs in 0.5 s bins after acceptance, against the two-sided 95 %
    χ² bounds of an average of M three-dimensional NEES."""
    if not series:
        return {"relocalizations": 0}
    per_bin = round(0.5 / dt)
    bins = max(len(s) for s in series) // per_bin
    rows = []
    for b in range(bins):
        lo_k, hi_k = b * per_bin, (b + 1) * per_bin
        vals = [float(np.mean(s[lo_k:hi_k])) for s in series if s.size >= hi_k]
        m = len(vals)
        lo, hi = chi2.ppf([0.025, 0.975], 3 * m) / m
        rows.append((b * 0.5, float(np.mean(vals)), float(lo), float(hi), m))
    inside = [lo <= v <= hi for _, v, lo, hi, _ in rows]
    every = np.concatenate(series)
    return {
        "relocalizations": len(series),
        "mean_nees": round(float(np.mean(every)), 2),
        "expected": 3.0,
        "bins_within_95pct_bounds": f"{sum(inside)}/{len(inside)}",
        "per_relocalization": per_relocalization_nees(series),
        "by_time_s": [
            {"t": t, "avg_nees": round(v, 2), "bounds": [round(lo, 2), round(hi, 2)], "runs": m}
            for t, v, lo, hi, m in rows
        ],
    }


def start_runs(
    lawn_map: LawnMap,
    scenario: str,
    seed: int,
    starts: int,
    config: Config | None = None,
    seconds: float = START_S,
    progress: Callable[[int, dict[str, Any]], None] | None = None,
    compass: bool = True,
) -> dict[str, Any]:
    """``starts`` random starts with no prior (module doc); ``compass``: the magnetometer
    helps the search (when the map has the taught field)."""
    runs, nees = _starts(lawn_map, scenario, seed, starts, config, seconds, progress, compass)
    return {
        "scenario": scenario,
        "seed": seed,
        **_start_scores(runs),
        "compass": compass and lawn_map.compass is not None,
        "map_landmarks": len(lawn_map.landmarks),
        **nees.summary(),
        "runs": runs,
    }


@dataclass(frozen=True)
class _MapRuns:
    """One map's share of :func:`runs_over_maps` (a worker's task: it makes the map too)."""

    seed: int
    map_of: Callable[[int], LawnMap]
    scenario: str
    starts: int
    kidnaps: int
    config: Config | None
    lifted: bool
    compass: bool

    def __call__(self) -> tuple[Runs, _NeesLog, Runs, _NeesLog]:
        lawn_map = self.map_of(self.seed)
        starts: tuple[Runs, _NeesLog] = ([], _NeesLog(None))
        kidnaps: tuple[Runs, _NeesLog] = ([], _NeesLog(None))
        if self.starts > 0:
            starts = _starts(
                lawn_map, self.scenario, self.seed, self.starts, self.config, START_S, None,
                self.compass,
            )  # fmt: skip
        if self.kidnaps > 0:
            kidnaps = _kidnaps(
                lawn_map, self.scenario, self.seed, self.kidnaps, self.config, self.lifted,
                None, self.compass,
            )  # fmt: skip
        return (*starts, *kidnaps)


def _run_task(task: _MapRuns) -> tuple[Runs, _NeesLog, Runs, _NeesLog]:
    return task()


def runs_over_maps(
    seeds: Sequence[int],
    map_of: Callable[[int], LawnMap],
    scenario: str,
    starts_per_map: int,
    kidnaps_per_map: int,
    config: Config | None = None,
    lifted: bool = True,
    compass: bool = True,
    workers: int = 1,
    scheduler: Any = None,
) -> dict[str, Any]:
    """:func:`start_runs` and :func:`kidnap_runs` spread over independently taught maps, one
    per yard seed (``map_of(seed)``, e.g. :class:`mowerhw.evaluation.pixel.PixelMaps`): the
    Monte-Carlo then draws the map's errors too, where one map draws them once for all its
    runs (its runs' NEES share that map's error, so a pool of few maps is a smaller sample
    than its run count says; one run per map makes every run an independent draw). Each
    map made and run in one task, ``workers`` local processes or a Dask ``scheduler``
    (:func:`mowerhw.evaluation.campaign.parallel_map`). Scores and NEES pooled per kind
    (``starts``, ``kidnaps``: a kind with no runs is left out), ``per_map`` each map's."""
    from mowerhw.evaluation.campaign import parallel_map

    tasks = [
        _MapRuns(seed, map_of, scenario, starts_per_map, kidnaps_per_map, config, lifted, compass)
        for seed in seeds
    ]
    done = parallel_map(_run_task, tasks, workers, scheduler, "maps")
    out: dict[str, Any] = {"scenario": scenario, "maps": len(tasks)}
    if starts_per_map > 0:
        runs, pooled, per_map = _pool(seeds, [(d[0], d[1]) for d in done], _start_scores)
        out["starts"] = {
            **_start_scores(runs),
            **pooled.summary(),
            "per_map": per_map,
            "runs": runs,
        }
    if kidnaps_per_map > 0:
        runs, pooled, per_map = _pool(seeds, [(d[2], d[3]) for d in done], _kidnap_scores)
        out["kidnaps"] = {
            "runs": len(runs),
            "lift_seen": lifted,
            **_kidnap_scores(runs),
            **pooled.summary(),
            "per_map": per_map,
            "per_run": runs,
        }
    return out


def _pool(
    seeds: Sequence[int],
    each: Sequence[tuple[Runs, _NeesLog]],
    score: Callable[[Runs], dict[str, Any]],
) -> tuple[Runs, _NeesLog, Runs]:
    """Each map's runs (its seed put in each run), their NEES pooled, and each map's
    ``score``."""
    runs: Runs = []
    pooled = _NeesLog(None)
    per_map: Runs = []
    for seed, (mine, nees) in zip(seeds, each, strict=True):
        pooled.extend(nees)
        per_map.append({"seed": seed, **score(mine)})
        runs += [{"seed": seed, **r} for r in mine]
    return runs, pooled, per_map


def _starts(
    lawn_map: LawnMap,
    scenario: str,
    seed: int,
    starts: int,
    config: Config | None,
    seconds: float,
    progress: Callable[[int, dict[str, Any]], None] | None,
    compass: bool,
) -> tuple[Runs, _NeesLog]:
    """The runs of :func:`start_runs`, and their NEES."""
    lawn = _inside(scenario, seed, 0.3)
    rng = np.random.default_rng([seed, 18, 1])
    nees = _NeesLog(lawn_map)
    runs = []
    for i in range(starts):
        pose = random_pose(lawn, rng)
        out = run_mow(
            lawn_map,
            scenario,
            seed,
            seconds,
            config,
            mow_seed=seed * 1000 + i,
            level="pixel",
            start=pose,
            no_prior=True,
            compass=compass,
        )
        err, yaw_err = _errors(out)
        acc = np.flatnonzero(out.relocalizations > 0)
        first_permit = np.flatnonzero(out.permit)
        run: dict[str, Any] = {
            "start": [round(v, 3) for v in pose],
            "accepted_s": round(float(out.t[acc[0]]), 2) if acc.size else None,
            "error_m": round(float(err[acc[0]]), 4) if acc.size else None,
            "yaw_error_deg": round(math.degrees(float(yaw_err[acc[0]])), 3) if acc.size else None,
            "first_permit_s": (
                round(float(out.t[first_permit[0]]), 2) if first_permit.size else None
            ),
            "permits_wrong": int(np.sum(out.permit & (err > WRONG_M))),
            "missed_halts": out.metrics["missed_halts"],
            "searches": out.metrics["localizer"]["searches"],
            "relocalizations": int(out.relocalizations[-1]),
        }
        nees.add(out)
        run.update(_first_relocalization(nees, int(out.relocalizations[-1])))
        runs.append(run)
        if progress is not None:
            progress(i, run)
    return runs, nees


def _first_relocalization(nees: _NeesLog, count: int) -> dict[str, Any]:
    """For a run's per-run record: its first relocalization's error and σ in the map's
    frame at acceptance (mm, mm, degrees) and its mean NEES over the standing
    :data:`PHASES_S`' first phase — which runs make a NEES bin's tail, and with what."""
    if count == 0 or len(nees.components) < count:
        return {}
    err, cov = nees.components[-count]
    if not err.size:
        return {}
    first = nees.aligned[-count][_phase(*PHASES_S[0], nees.dt)]
    return {
        "map_frame_error_mm_mm_deg": _mm_mm_deg(err[0]),
        "map_frame_sigma_mm_mm_deg": _mm_mm_deg(np.sqrt(np.diagonal(cov[0]))),
        "map_frame_nees_standing": round(float(np.mean(first)), 2) if first.size else None,
    }


def _start_scores(runs: Runs) -> dict[str, Any]:
    """Success (within :data:`SUCCESS_M` and :data:`SUCCESS_RAD` in 5 s), times and the
    safety counts of start runs."""
    ok = [
        r
        for r in runs
        if r["accepted_s"] is not None
        and r["accepted_s"] <= 5.0
        and r["error_m"] < SUCCESS_M
        and math.radians(r["yaw_error_deg"]) < SUCCESS_RAD
    ]
    times = [r["accepted_s"] for r in runs if r["accepted_s"] is not None]
    return {
        "starts": len(runs),
        "success_rate": round(len(ok) / max(1, len(runs)), 3),
        "accepted": len(times),
        "accepted_wrong_over_0.15m": sum(
            1 for r in runs if r["error_m"] is not None and r["error_m"] > WRONG_M
        ),
        "time_to_relocalize_s": {"median": _pct(times, 50), "p95": _pct(times, 95)},
        "permit_samples_while_wrong_over_0.15m": sum(r["permits_wrong"] for r in runs),
        "missed_halts": sum(r["missed_halts"] for r in runs),
    }


def kidnap_runs(
    lawn_map: LawnMap,
    scenario: str,
    seed: int,
    runs: int,
    config: Config | None = None,
    lifted: bool = True,
    progress: Callable[[int, dict[str, Any]], None] | None = None,
    compass: bool = True,
) -> dict[str, Any]:
    """``runs`` kidnaps mid-mow: a 5–20 m walk (at :data:`CARRY_MPS`), put down at a
    random pose inside the lawn (module doc)."""
    out_runs, nees = _kidnaps(lawn_map, scenario, seed, runs, config, lifted, progress, compass)
    return {
        "scenario": scenario,
        "seed": seed,
        "runs": runs,
        "lift_seen": lifted,
        "compass": compass and lawn_map.compass is not None,
        **_kidnap_scores(out_runs),
        **nees.summary(),
        "per_run": out_runs,
    }


def _kidnaps(
    lawn_map: LawnMap,
    scenario: str,
    seed: int,
    runs: int,
    config: Config | None,
    lifted: bool,
    progress: Callable[[int, dict[str, Any]], None] | None,
    compass: bool,
) -> tuple[Runs, _NeesLog]:
    """The runs of :func:`kidnap_runs`, and their NEES."""
    lawn = _inside(scenario, seed, 0.5)
    rng = np.random.default_rng([seed, 18, 2])
    nees = _NeesLog(lawn_map)
    out_runs = []
    for i in range(runs):
        mow_seed = seed * 1000 + i
        # carried along a 5–20 m walk (its length sets the carry's duration) and put down
        # at a random pose inside the lawn at least MIN_DISPLACEMENT_M from the pick-up
        options = [random_pose(lawn, rng) for _ in range(20)]
        walk = float(rng.uniform(5.0, 20.0))
        carry_s = walk / CARRY_MPS
        to = options[0]
        kidnap = Kidnap(
            MOW_BEFORE_S,
            carry_s,
            (to[0], to[1]),
            to[2],
            lifted,
            tuple(options[1:]),
            min(MIN_DISPLACEMENT_M, walk),
        )
        out = run_mow(
            lawn_map,
            scenario,
            seed,
            MOW_BEFORE_S + carry_s + AFTER_S,
            config,
            mow_seed=mow_seed,
            level="pixel",
            kidnaps=[kidnap],
            compass=compass,
        )
        dt = float(out.t[1] - out.t[0])
        err, _ = _errors(out)
        if not out.metrics["kidnapped_at_s"]:  # the deck never ran after MOW_BEFORE_S
            out_runs.append({"walk_m": round(walk, 2), "kidnapped": False})
            continue
        t_k = float(out.metrics["kidnapped_at_s"][0])
        at = int(np.searchsorted(out.t, t_k))
        down = int(np.searchsorted(out.t, t_k + carry_s))
        moved = float(np.hypot(*(out.true_xy[down] - out.true_xy[at])))
        halted = np.flatnonzero(~out.permit[at:])
        reloc = np.flatnonzero(out.relocalizations[down:] > out.relocalizations[at])
        first_reloc = np.flatnonzero(out.relocalizations[at:] > out.relocalizations[at])
        after = at + int(first_reloc[0]) if first_reloc.size else out.t.size
        stop = at + int(halted[0]) if halted.size else out.t.size
        permit_after = np.flatnonzero(out.permit[down:])
        run: dict[str, Any] = {
            "walk_m": round(walk, 2),
            "kidnapped_at_s": round(t_k, 2),
            "displaced_m": round(moved, 2),
            "carry_s": round(carry_s, 2),
            "time_to_halt_s": round(float(halted[0]) * dt, 3) if halted.size else None,
            "time_to_relocalize_s": round(float(reloc[0]) * dt, 2) if reloc.size else None,
            "time_to_permit_s": (
                round(float(permit_after[0]) * dt, 2) if permit_after.size else None
            ),
            "permits_during_carry": int(out.permit[at + 1 : down].sum()),
            # before the halt: the deck ran on while the kidnap was not yet seen
            "permits_before_halt_over_0.15m": int(
                np.sum(out.permit[at:stop] & (err[at:stop] > WRONG_M))
            ),
            # after a relocalization: the deck ran on a wrong pose (the dangerous case)
            "permits_wrong_after_relocalization": int(
                np.sum(out.permit[after:] & (err[after:] > WRONG_M))
            ),
            "missed_halts": out.metrics["missed_halts"],
            "searches": out.metrics["localizer"]["searches"],
        }
        out_runs.append(run)
        nees.add(out, t_k)
        if progress is not None:
            progress(i, run)
    return out_runs, nees


def _kidnap_scores(out_runs: Runs) -> dict[str, Any]:
    """The scores of kidnap runs (:func:`kidnap_runs`, one map's or a pool's)."""
    done = [r for r in out_runs if r.get("kidnapped", True)]
    halts = [r["time_to_halt_s"] for r in done if r["time_to_halt_s"] is not None]
    relocs = [r["time_to_relocalize_s"] for r in done if r["time_to_relocalize_s"] is not None]
    return {
        "kidnapped_while_mowing": len(done),
        "time_to_halt_s": {"median": _pct(halts, 50), "max": max(halts) if halts else None},
        "relocalized": len(relocs),
        "time_to_relocalize_s": {"median": _pct(relocs, 50), "p95": _pct(relocs, 95)},
        "missed_halts": sum(r["missed_halts"] for r in done),
        "permits_during_carry": sum(r["permits_during_carry"] for r in done),
        "permit_samples_before_halt_over_0.15m": sum(
            r["permits_before_halt_over_0.15m"] for r in done
        ),
        "wrong_relocalizations_permitted": sum(
            1 for r in done if r["permits_wrong_after_relocalization"]
        ),
    }
