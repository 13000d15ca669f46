#!/usr/bin/env python3
"""Monte-Carlo: the paper's teach estimators vs the inverse-depth EKF, on many seeds.

For every seed of a scenario the same simulated streams go to

* ``observer+closure``  — landmark observers + robot-centric EKF (this project's defaults:
  epipolar measurement, precision-weighted depth gain, consider anchors) + loop closure;
* ``observer (filter)`` — the same run before loop closure (the on-line estimate);
* ``paper as printed``  — eq. (16) bearing measurement, eq. (7) gains only, no closure;
* ``inverse-depth EKF`` — Civera et al. (2008) EKF-SLAM, the standard the paper argues
  against (:mod:`mowerhw.baselines.inverse_depth`).

Prints a table (median / 95th percentile of boundary and landmark RMSE, divergences, wall
time per run) and the NEES of the robot-centric EKF (average over runs at each frame against
the two-sided 95 % χ² bounds), then one JSON object. A run *diverges* when its boundary or
landmark RMSE exceeds 1 m, it produced NaN, or it could not make a boundary.

    .venv/bin/python tools/montecarlo_teach.py --seeds 100 --jobs 2   # or --scheduler ADDRESS

The runs go through :func:`mowerhw.evaluation.campaign.parallel_map` (local processes or Dask), as
``mowerhw eval`` does.
"""

from __future__ import annotations

import os

# one BLAS thread per worker process: small matrices, and two workers share two cores
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import sys
import time
from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from mowerhw.baselines.inverse_depth import InverseDepthEkfMapper
from mowerhw.config import TeachConfig
from mowerhw.evaluation.campaign import parallel_map
from mowerhw.evaluation.teach import DIVERGENCE_M, feed, horizontal_errors, run_teach
from mowerhw.sim import simulate_teach

METHODS = ("observer+closure", "observer (filter)", "paper as printed", "inverse-depth EKF")


def _score(traj, landmarks, run) -> tuple[float, float]:
    e = horizontal_errors(traj, run)
    moving = (
        run.truth.speed[np.clip(np.searchsorted(run.truth.t, traj[:, 0]), 0, run.truth.t.size - 1)]
        > 0
    )
    first = int(np.argmax(moving)) if moving.any() else 0
    e = e[first:]
    ids = sorted(landmarks)
    est = np.array([landmarks[i] for i in ids]).reshape(-1, 3)
    lm = np.linalg.norm(est - run.landmarks_w[ids], axis=1)
    b = float(np.sqrt(np.mean(e**2))) if np.all(np.isfinite(e)) else float("nan")
    m = float(np.sqrt(np.mean(lm**2))) if np.all(np.isfinite(lm)) else float("nan")
    return b, m


def one_seed(args: tuple[str, int]) -> dict:
    scenario, seed = args
    run = simulate_teach(scenario, seed)
    out: dict = {"seed": seed}
    # ours, with NEES history
    t0 = time.perf_counter()
    o = run_teach(run=run, record_history=True)
    wall = time.perf_counter() - t0
    if o.result is not None:
        b, m = _score(o.result.trajectory, o.result.landmarks, run)
        b0, _ = _score(o.result.trajectory_no_closure, o.result.landmarks, run)
        out["observer+closure"] = (b, m, wall)
        out["observer (filter)"] = (b0, float("nan"), o.metrics["estimator_wall_s"])
        out["nees"] = [n[1] for n in o.history.nees]
        out["nees_t"] = [n[0] for n in o.history.nees]
    else:
        out["observer+closure"] = out["observer (filter)"] = (np.nan, np.nan, wall)
        out["nees"] = []
    # the paper as printed
    printed = replace(
        TeachConfig(), ekf_measurement="bearing", depth_gain="contraction", loop_closure=False
    )
    t0 = time.perf_counter()
    p = run_teach(run=run, config=printed)
    wall = time.perf_counter() - t0
    if p.result is not None:
        out["paper as printed"] = (*_score(p.result.trajectory, p.result.landmarks, run), wall)
    else:
        out["paper as printed"] = (np.nan, np.nan, wall)
    # inverse-depth EKF
    mapper = InverseDepthEkfMapper(TeachConfig())
    wall = feed(mapper, run)
    r = mapper.finish()
    out["inverse-depth EKF"] = (*_score(r.trajectory, r.landmarks, run), wall)
    out["idp_negative_depth_events"] = r.negative_depths
    return out


def summarise(rows: list[dict]) -> dict:
    table = {}
    for meth in METHODS:
        arr = np.array([r[meth] for r in rows], dtype=float)
        b, m, w = arr[:, 0], arr[:, 1], arr[:, 2]
        div = ~(np.isfinite(b) & (b < DIVERGENCE_M))
        if meth != "observer (filter)":
            div |= ~(np.isfinite(m) & (m < DIVERGENCE_M))
        ok = ~div

        def q(x, p, ok=ok):
            x = x[ok & np.isfinite(x)]
            return round(float(np.percentile(x, p)), 4) if x.size else None

        table[meth] = {
            "boundary_rmse_median_m": q(b, 50),
            "boundary_rmse_p95_m": q(b, 95),
            "landmark_rmse_median_m": q(m, 50),
            "landmark_rmse_p95_m": q(m, 95),
            "diverged": int(div.sum()),
            "wall_s_per_run": round(float(np.mean(w)), 3),
        }
    return table


def nees_summary(rows: list[dict], dof: int = 6) -> dict:
    """Average NEES over runs at each frame (aligned by frame index) vs the χ² bounds."""
    series = [np.asarray(r["nees"]) for r in rows if len(r["nees"])]
    n = min(len(s) for s in series)
    mat = np.stack([s[:n] for s in series])  # (M, n)
    m = mat.shape[0]
    anees = mat.mean(axis=0)
    lo, hi = chi2.ppf(0.025, dof * m) / m, chi2.ppf(0.975, dof * m) / m
    inside = (anees >= lo) & (anees <= hi)
    return {
        "dof": dof,
        "runs": m,
        "frames": n,
        "anees_mean": round(float(anees.mean()), 3),
        "anees_median": round(float(np.median(anees)), 3),
        "chi2_95_bounds": [round(float(lo), 3), round(float(hi), 3)],
        "fraction_of_frames_inside": round(float(inside.mean()), 3),
        "fraction_above": round(float((anees > hi).mean()), 3),
        "fraction_below": round(float((anees < lo).mean()), 3),
        "single_run_nees_mean": round(float(mat.mean()), 3),
    }


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scenario", default="paper", choices=("paper", "large"))
    ap.add_argument("--seeds", type=int, default=100, help="seeds 1..N (default 100)")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes")
    ap.add_argument("--scheduler", help="a Dask scheduler address (tcp://host:8786)")
    ap.add_argument("--json", action="store_true", help="print only the JSON object")
    args = ap.parse_args()
    tasks = [(args.scenario, s) for s in range(1, args.seeds + 1)]
    t0 = time.perf_counter()
    rows = parallel_map(one_seed, tasks, args.jobs, args.scheduler, "monte-carlo")
    table = summarise(rows)
    nees = nees_summary(rows)
    summary = {
        "scenario": args.scenario,
        "seeds": args.seeds,
        "methods": table,
        "robot_centric_ekf_nees": nees,
        "idp_negative_depth_events_total": int(sum(r["idp_negative_depth_events"] for r in rows)),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    if not args.json:
        print(f"\nTeach Monte-Carlo, scenario '{args.scenario}', seeds 1..{args.seeds}\n")
        print(
            "| method | boundary RMSE median / p95 (m) | landmark RMSE median / p95 (m) "
            "| diverged | wall s/run |"
        )
        print("|---|---|---|---|---|")
        for meth, r in table.items():
            lm = (
                f"{r['landmark_rmse_median_m']} / {r['landmark_rmse_p95_m']}"
                if r["landmark_rmse_median_m"] is not None
                else "—"
            )
            print(
                f"| {meth} | {r['boundary_rmse_median_m']} / {r['boundary_rmse_p95_m']} | {lm} "
                f"| {r['diverged']} | {r['wall_s_per_run']} |"
            )
        print(
            f"\nRobot-centric EKF NEES (6-dof pose, {nees['runs']} runs, {nees['frames']} frames):"
            f" ANEES mean {nees['anees_mean']}, 95 % bounds {nees['chi2_95_bounds']}, "
            f"{100 * nees['fraction_of_frames_inside']:.0f} % of frames inside\n"
        )
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
