"""Run the estimators on simulated streams and score them against the truth.

Used by ``mowerhw sim``, the tools (Monte-Carlo, benchmarks) and the tests, so the figures a
user sees are the ones the suite checks. Wires the simulator to the estimators; no I/O.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import quat_to_rotmat, rotmat_log
from mowerhw.config import TeachConfig
from mowerhw.sim import TeachRun, simulate_teach
from mowerhw.sim.sensors import body_points
from mowerhw.teach import BoundaryError, Teacher, TeachError, TeachResult

FloatArray = NDArray[np.float64]

#: a teach run "diverged" when its landmarks or its boundary are off by more than this (once
#: the speed sensor's scale is taken out), or produced NaN, or could not make a boundary
DIVERGENCE_M = 1.0


@dataclass
class TeachHistory:
    """What the plots need, recorded frame by frame while the teacher runs."""

    t: list[float] = field(default_factory=list)
    depth_est: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)
    direction_est: dict[int, list[tuple[float, FloatArray, FloatArray]]] = field(
        default_factory=dict
    )
    landmark_err: list[float] = field(default_factory=list)  # mean world landmark error
    nees: list[tuple[float, float, float]] = field(default_factory=list)  # t, pose (6), 9-dof


@dataclass
class TeachOutcome:
    run: TeachRun
    result: TeachResult | None
    metrics: dict[str, Any]
    history: TeachHistory | None = None
    error: str = ""


def feed(teacher: Any, run: TeachRun) -> float:
    """Feed every stream sample in time order; returns the wall time spent (s)."""
    imu, speed, bearings = teacher.imu, teacher.speed, teacher.bearings
    t0 = time.perf_counter()
    for kind, payload in run.streams.events():
        if kind == "imu":
            imu(*payload)
        elif kind == "speed":
            speed(*payload)
        else:
            bearings(payload.t, payload.ids, payload.bearings)
    return time.perf_counter() - t0


def _history_hook(run: TeachRun, hist: TeachHistory):
    truth = run.truth

    def on_frame(teacher: Teacher, t: float, depth: Any) -> None:
        k = truth.index_at(t)
        true_b = body_points(truth, k, run.landmarks_w)
        hist.t.append(t)
        obs = teacher.obs
        for row, lid in enumerate(obs.ids.tolist()):
            meas = np.nan
            if depth is not None:
                hit = np.flatnonzero(depth[0] == lid)
                meas = float(depth[1][hit[0]]) if hit.size else np.nan
            hist.depth_est.setdefault(lid, []).append(
                (t, float(obs.d[row]), float(np.linalg.norm(true_b[lid])), meas)
            )
            y_true = true_b[lid] / np.linalg.norm(true_b[lid])
            hist.direction_est.setdefault(lid, []).append((t, obs.y[row].copy(), y_true))
        nees = ekf_nees(teacher, run, k)
        if nees is not None:
            hist.nees.append((t, *nees))
        ids, xyz = teacher.landmark_snapshot()
        if ids.size:
            hist.landmark_err.append(
                float(np.mean(np.linalg.norm(xyz - run.landmarks_w[ids], axis=1)))
            )
        else:
            hist.landmark_err.append(np.nan)

    return on_frame


def ekf_nees(teacher: Teacher, run: TeachRun, k: int) -> tuple[float, float] | None:
    """NEES of the robot-centric EKF at truth sample ``k``: (pose 6-dof, pose + bias 9-dof).

    The state is the keyframe's pose in the current body frame; its truth comes from the
    body's true poses at the keyframe's time and now. Skipped in the first second after a
    keyframe, where the covariance is (exactly) zero.
    """
    kf = teacher.keyframes[-1]
    truth = run.truth
    if truth.t[k] - kf.t < 1.0:
        return None
    j = truth.index_at(kf.t)
    r_now = quat_to_rotmat(truth.quat[k])
    r_kf = quat_to_rotmat(truth.quat[j])
    p_true = r_now.T @ (truth.position[j] - truth.position[k])
    r_true = r_now.T @ r_kf
    ekf = teacher.ekf
    d_theta = rotmat_log(r_true @ ekf.R.T)
    d_bias = run.streams.gyro_bias[k] - ekf.bg
    e = np.concatenate([p_true - ekf.p, d_theta, d_bias])
    p6 = ekf.P[:6, :6]
    try:
        n6 = float(e[:6] @ np.linalg.solve(p6, e[:6]))
        n9 = float(e @ np.linalg.solve(ekf.P, e))
    except np.linalg.LinAlgError:
        return None
    return n6, n9


def horizontal_errors(traj: FloatArray, run: TeachRun) -> FloatArray:
    """Per-sample horizontal error of a (K, 8) trajectory against the truth at the same time."""
    idx = np.clip(np.searchsorted(run.truth.t, traj[:, 0] - 1e-9), 0, run.truth.t.size - 1)
    return np.linalg.norm(traj[:, 1:3] - run.truth.xy[idx], axis=1)


def teach_metrics(
    run: TeachRun,
    result: TeachResult,
    wall_s: float,
    finish_s: float,
    landmark_truth: dict[int, FloatArray] | None = None,
) -> dict:
    """Scores of a teach run. ``landmark_truth`` (id → true world xyz) replaces the world's
    landmark list when ids are not the world's (pixel level: ids are tracks)."""
    moving = run.truth.speed[
        np.clip(np.searchsorted(run.truth.t, result.trajectory[:, 0]), 0, run.truth.t.size - 1)
    ]
    first = int(np.argmax(moving > 0)) if np.any(moving > 0) else 0
    e = horizontal_errors(result.trajectory, run)[first:]
    e0 = horizontal_errors(result.trajectory_no_closure, run)[first:]
    ids = np.array(sorted(result.landmarks), dtype=np.int64)
    if landmark_truth is not None:  # only landmarks whose true point is known (not the sky)
        ids = np.array([i for i in ids.tolist() if i in landmark_truth], dtype=np.int64)
        true_xyz = np.array([landmark_truth[i] for i in ids.tolist()]).reshape(-1, 3)
    else:
        true_xyz = run.landmarks_w[ids]
    est = np.array([result.landmarks[i] for i in ids]).reshape(-1, 3)
    lm_err = np.linalg.norm(est - true_xyz, axis=1) if ids.size else np.zeros(0)
    boundary_rmse = float(np.sqrt(np.mean(e**2)))
    scale_free = _scale_free_errors(result, run, first, ids, true_xyz)
    landmark_rmse = float(np.sqrt(np.mean(lm_err**2))) if lm_err.size else float("nan")
    finite = bool(np.all(np.isfinite(result.trajectory)) and np.all(np.isfinite(est)))
    # diverged: the estimator failed, judged once the speed sensor's scale is out (a map
    # that is 5 % large is the sensor's doing, not a diverged estimate)
    b_free = scale_free["boundary_rmse_scale_free_m"]
    l_free = scale_free.get("landmark_rmse_scale_free_m", landmark_rmse)
    diverged = (not finite) or not (b_free < DIVERGENCE_M and l_free < DIVERGENCE_M)
    return {
        "boundary_rmse_m": round(boundary_rmse, 5),
        "boundary_max_m": round(float(e.max()), 5),
        "boundary_rmse_no_closure_m": round(float(np.sqrt(np.mean(e0**2))), 5),
        "landmark_rmse_m": round(landmark_rmse, 5),
        "landmark_max_m": round(float(lm_err.max()), 5) if lm_err.size else None,
        **scale_free,
        "landmarks_mapped": int(ids.size),
        "landmarks_in_world": int(run.landmarks_w.shape[0]),
        "diverged": bool(diverged),
        "loop_closure": {
            "applied": result.closure.applied,
            "reason": result.closure.reason,
            "end_correction_m": round(result.closure.translation_m, 4),
            "end_correction_deg": round(float(np.degrees(result.closure.rotation_rad)), 4),
        },
        "keyframes": len(result.keyframes),
        "sim_duration_s": round(run.duration_s, 3),
        "wall_s": round(wall_s + finish_s, 4),
        "estimator_wall_s": round(wall_s, 4),
        "finish_wall_s": round(finish_s, 4),
        "real_time_factor": round(run.duration_s / max(wall_s + finish_s, 1e-9), 1),
    }


def _scale_free_errors(
    result: TeachResult, run: TeachRun, first: int, ids: Any, true_xyz: FloatArray
) -> dict[str, Any]:
    """Errors once a uniform scale about the start is taken out. Bearings and a ground-speed
    sensor cannot tell a map from the same map a few per cent larger: a speed sensor that
    reads 3 % high makes a map 3 % large, and it mows on it consistently (it localises with
    the same sensor). What is left after the best such scale is the estimator's own error."""
    traj = result.trajectory[first:]
    idx = np.clip(np.searchsorted(run.truth.t, traj[:, 0] - 1e-9), 0, run.truth.t.size - 1)
    est, ref = traj[:, 1:3], run.truth.xy[idx]
    denom = float(np.sum(est * est))
    scale = float(np.sum(est * ref) / denom) if denom > 0 else 1.0
    e = np.linalg.norm(scale * est - ref, axis=1)
    out = {
        "map_scale": round(scale, 5),
        "boundary_rmse_scale_free_m": round(float(np.sqrt(np.mean(e**2))), 5),
    }
    if ids.size:
        lm = np.array([result.landmarks[i] for i in ids.tolist()]).reshape(-1, 3)
        err = np.linalg.norm(scale * lm - true_xyz, axis=1)
        out["landmark_rmse_scale_free_m"] = round(float(np.sqrt(np.mean(err**2))), 5)
    streams = run.streams
    out["speed_scale_true"] = round(float(getattr(streams, "speed_scale", 1.0)), 5)
    return out


def run_teach(
    scenario: str = "paper",
    seed: int = 0,
    config: TeachConfig | None = None,
    n_landmarks: int | None = None,
    record_history: bool = False,
    run: TeachRun | None = None,
) -> TeachOutcome:
    """Simulate a teach drive, run the Teacher on it, and score the result."""
    run = run or simulate_teach(scenario, seed, n_landmarks=n_landmarks)
    hist = TeachHistory() if record_history else None
    teacher = Teacher(
        config,
        camera=run.world.camera,
        on_frame=_history_hook(run, hist) if hist is not None else None,
    )
    wall = feed(teacher, run)
    t0 = time.perf_counter()
    try:
        result = teacher.finish()
    except (BoundaryError, TeachError) as exc:
        metrics = {
            "diverged": True,
            "error": str(exc),
            "sim_duration_s": run.duration_s,
            "wall_s": wall,
        }
        return TeachOutcome(run, None, metrics, hist, str(exc))
    finish = time.perf_counter() - t0
    return TeachOutcome(run, result, teach_metrics(run, result, wall, finish), hist)


def sim_map(
    result: TeachResult,
    scenario: str,
    seed: int,
    level: str = "bearing",
    truth: dict[int, FloatArray] | None = None,
) -> Any:
    """The map of a simulated teach run, remembering which simulated yard it belongs to (and,
    at pixel level, each landmark's true position, to score re-identification when mowing)."""
    from mowerhw.map import LawnMap

    lawn_map = LawnMap.from_teach_result(result)
    sim: dict[str, Any] = {"scenario": scenario, "seed": seed, "level": level}
    if truth is not None:
        sim["landmark_truth"] = {
            str(i): [round(float(v), 5) for v in truth[i]] for i in result.landmarks if i in truth
        }
    lawn_map.teach["sim"] = sim
    return lawn_map
