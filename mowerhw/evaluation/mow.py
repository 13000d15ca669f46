"""Closed-loop mowing on the simulated bench (the paper's §V mowing run), scored against truth.

Every IMU period: the mower's controller (:class:`mowerhw.sim.controller.BangBangMower`) picks
(v, ω) from the *estimated* pose and containment; the plant moves the true mower and produces
sensor readings (late camera frames included); the :class:`mowerhw.mow.Localizer` takes them
and decides containment. The truth is used only to score:

* ``position_rmse_m`` / ``position_max_m``: 3-D position error of the estimate;
* ``quaternion_err_max``: largest component error of the estimated q_wb (sign-aligned), the
  paper's Fig. 8 measure;
* ``missed_halts``: IMU samples with the deck permitted while the mower is truly more than
  0.10 m outside the lawn edge or more than 0.10 m inside a keep-out zone;
* ``false_halt_fraction``: share of the samples with the mower truly more than 1 m inside where
  the deck was halted (after the start-up calibration);
* ``time_outside_s``: time the mower truly spent outside the mowable area;
* ``handling``: per lift / tilt / bump event (``handling=``), when the deck halted and why,
  permits while the safety function held (goal 0), and when the deck ran again. The safety
  functions (:class:`mowerhw.estimation.safety.SafetyMonitor`) see the plant's specific force
  and the mower's switches every IMU period, as the supervisor does on the mower.

The true lawn edge is the path the operator drove when teaching (the simulated lawn outline);
keep-out zones are the map's (they exist only as the user drew them).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import yaw_to_quat
from mowerhw.common.reasons import Reason
from mowerhw.config import Config, FrontendConfig, SafetyConfig
from mowerhw.estimation.safety import SafetyMonitor
from mowerhw.evaluation.pixel import bearing_error, frontend_figures, sees_point
from mowerhw.evaluation.scoring import score_halts
from mowerhw.map import LawnMap
from mowerhw.mow import LawnGeometry, Localizer
from mowerhw.mow.gate import PermitGate
from mowerhw.sim import make_world
from mowerhw.sim.controller import BangBangMower
from mowerhw.sim.handling import HandlingEvent, Kidnap, handled
from mowerhw.sim.plant import MowerPlant
from mowerhw.sim.render import OmniRenderer
from mowerhw.sim.sensors import mower_gyro_scale, mower_speed_scale
from mowerhw.vision import MowVision

FloatArray = NDArray[np.float64]

STATE_CODE = {"INSIDE": 0, "NEAR_EDGE": 1, "OUTSIDE": 2, "UNKNOWN": 3}


@dataclass
class MowOutcome:
    metrics: dict[str, Any]
    t: FloatArray
    true_xy: FloatArray
    true_yaw: FloatArray
    est: FloatArray  # (K, 7): x, y, z, qw, qx, qy, qz
    permit: NDArray[np.bool_]
    state: NDArray[np.int8]
    sigma: FloatArray
    true_outline: FloatArray
    lawn_map: LawnMap
    landmarks_w: FloatArray
    halts_by_reason: dict[str, int] = field(default_factory=dict)
    #: (K, 3, 3) covariance of the estimate's (x, y, heading); the localizer's global
    #: relocalizations so far, and whether it was searching for its pose, per sample
    cov_xy_yaw: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    #: (K, 3, 3) the same against the ground (:meth:`Localizer.ground_covariance`): the truth
    cov_xy_yaw_ground: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    relocalizations: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    searching: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    details: NDArray[Any] = field(default_factory=lambda: np.zeros(0, object))  # why halted
    #: pixel level: each right association's bearing error against the truth (frame time,
    #: landmark id, azimuth and elevation error in rad), (K, 4)
    bearing_errors: FloatArray | None = None


def run_mow(
    lawn_map: LawnMap,
    scenario: str = "paper",
    seed: int = 7,
    duration_s: float = 500.0,
    config: Config | None = None,
    vision_dropout: tuple[float, float] | None = None,
    frame_latency_s: float | None = None,
    mow_seed: int | None = None,
    level: str = "bearing",
    handling: list[HandlingEvent] | None = None,
    start: tuple[float, float, float] | None = None,
    no_prior: bool = False,
    kidnaps: list[Kidnap] | None = None,
    compass: bool = True,
) -> MowOutcome:
    """Mow a simulated yard (the world of ``scenario``/``seed``) with the given map.
    ``compass``: the magnetometer's readings go to the localizer (its map must have the
    taught field for them to count).

    ``level="pixel"``: the camera delivers rendered images, and landmarks are found and
    re-identified by the front end (:class:`mowerhw.vision.MowVision`); the map must come
    from a pixel-level teach (its landmarks carry descriptors)."""
    world = make_world(scenario, seed)
    run_seed = seed if mow_seed is None else mow_seed
    renderer = OmniRenderer(world, run_seed) if level == "pixel" else None
    plant = MowerPlant(
        world,
        run_seed * 7919 + 13,
        speed_scale=mower_speed_scale(world.scenario.sensors, seed),
        gyro_scale=mower_gyro_scale(world.scenario.sensors, seed),
        frame_latency_s=frame_latency_s,
        vision_dropout=vision_dropout,
        renderer=renderer,
    )
    if start is not None:
        plant.place((start[0], start[1]), start[2])
    loc = Localizer(lawn_map, config)
    if no_prior:
        loc.lose("since the start (no prior pose)")
    vision = None
    if renderer is not None:
        fe_cfg = config.frontend if isinstance(config, Config) else FrontendConfig()
        px_sigma = config.camera.pixel_sigma if isinstance(config, Config) else 1.0
        vision = MowVision(loc, world.camera, world.q_bc, fe_cfg, run_seed, px_sigma)
        truth = landmark_truth(lawn_map)
        verdicts: list[bool] = []
        bearing_errors: list[tuple[float, int, float, float]] = []
    geom = loc.geometry
    controller = BangBangMower(geom.inward_direction, np.random.default_rng([run_seed, 30]))
    truth_geom = LawnGeometry(
        plant.outline_world(world.lawn.outline(1440)),
        [(z.name, z.polygon) for z in lawn_map.keepouts],
    )
    n = round(duration_s * plant.rates.imu_hz)
    t_arr = np.zeros(n + 1)
    true_xy = np.zeros((n + 1, 2))
    true_yaw = np.zeros(n + 1)
    est = np.zeros((n + 1, 7))
    permit = np.zeros(n + 1, dtype=bool)
    state = np.zeros(n + 1, dtype=np.int8)
    sigma = np.zeros(n + 1)
    reason = np.empty(n + 1, dtype=object)
    detail = np.empty(n + 1, dtype=object)
    cov3 = np.zeros((n + 1, 3, 3))
    cov3_ground = np.zeros((n + 1, 3, 3))
    relocalized = np.zeros(n + 1, np.int64)
    searching = np.zeros(n + 1, bool)
    reasons: Counter[str] = Counter()
    out = plant.first_output()
    loc.imu(*out.imu)
    loc.speed(*out.speed)
    prev_permit = False
    wall0 = time.perf_counter()
    gate = PermitGate.from_config(config if isinstance(config, Config) else None, False)
    safety = SafetyMonitor(config.safety if isinstance(config, Config) else SafetyConfig())
    moves = sorted(kidnaps or [], key=lambda e: e.at_s)
    kidnapped_at: list[float] = []
    events = list(handling or [])
    safety_reason = np.empty(n + 1, dtype=object)
    for k in range(n + 1):
        cont = loc.containment()
        arrivals = {"imu": loc.t_imu, "speed": loc.t_speed, "camera": loc.t_camera}
        res = gate.decide(plant.t, "mow", arrivals, cont)
        force, switches = handled(events, plant.t, plant.specific_force())
        safety.imu(plant.t, force)
        safety.switches(plant.t, *switches)
        stop = safety.halt(plant.t)
        safety_reason[k] = stop[0] if stop else ""
        if stop is not None and stop[0] == Reason.LIFTED:
            loc.lifted()  # as the runtime wires it
        if moves and plant.t >= moves[0].at_s and prev_permit and not plant.carried:
            move = replace(moves.pop(0), at_s=plant.t)  # mid-mow: while the deck runs
            x, y, heading = move.destination((float(plant.map_xy[0]), float(plant.map_xy[1])))
            plant.carry((x, y), heading, move.carry_s)
            kidnapped_at.append(plant.t)
            if (lift := move.lift()) is not None:
                events.append(lift)
        deck, why = (False, stop[0]) if stop else (res.permit, res.reason)
        x, q = loc.ekf.x, loc.ekf.q
        yaw = float(np.arctan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2)))
        t_arr[k], true_xy[k], true_yaw[k] = plant.t, plant.xy, plant.yaw
        est[k, :3], est[k, 3:] = x, q
        permit[k], state[k], sigma[k] = deck, STATE_CODE[res.state], cont.sigma_m
        reason[k] = why
        detail[k] = "" if deck or stop else f"{why}: {cont.detail}"
        cov3[k] = loc.pose().covariance[np.ix_([0, 1, 5], [0, 1, 5])]
        cov3_ground[k] = loc.ground_covariance()
        relocalized[k] = loc.counters.relocalizations
        searching[k] = loc.searching
        if prev_permit and not deck:
            reasons[why] += 1
        prev_permit = deck
        if k == n:
            break
        v, w = controller.command(plant.t, float(x[0]), float(x[1]), yaw, str(res.state))
        out = plant.step(v, w)
        loc.imu(*out.imu, plant.specific_force())
        if vision is not None:
            vision.imu(*out.imu)
        if out.speed is not None:
            loc.speed(*out.speed)
        if out.mag is not None and compass:
            loc.magnetometer(*out.mag)
        for f in out.frames:
            if vision is None:
                loc.bearings(f.t, f.ids, f.bearings)
                continue
            vision.frame(f.t, f.image)
            judged, errors = _judge(vision, plant, f, truth)
            verdicts += judged
            bearing_errors += errors
    wall = time.perf_counter() - wall0
    # -- scoring against the truth ----------------------------------------------------------
    s_true = truth_geom.signed_distances(true_xy)
    err = np.linalg.norm(est[:, :3] - np.column_stack([true_xy, np.zeros(len(t_arr))]), axis=1)
    q_true = yaw_to_quat(true_yaw)
    q_est = est[:, 3:] * np.sign(np.sum(est[:, 3:] * q_true, axis=1))[:, None]
    q_err = np.abs(q_est - q_true).max(axis=1)
    after_start = t_arr >= controller.start_after_s
    excluded = None
    if vision_dropout is not None:  # halting without vision is intended, not a false halt
        d0, d1 = vision_dropout
        excluded = (t_arr >= d0) & (t_arr < d0 + d1 + 2.0)
    for e in events:  # nor is halting while the mower is handled (and latched after)
        held = (t_arr >= e.at_s) & (t_arr < e.at_s + e.duration_s + safety.cfg.clear_s + 1.0)
        excluded = held if excluded is None else excluded | held
    dt = 1.0 / plant.rates.imu_hz
    halts = score_halts(t_arr, permit, s_true, controller.start_after_s, dt, excluded)
    metrics = {
        "position_rmse_m": round(float(np.sqrt(np.mean(err[after_start] ** 2))), 5),
        "position_max_m": round(float(err[after_start].max()), 5),
        "quaternion_err_max": round(float(q_err[after_start].max()), 5),
        **halts,
        "permit_fraction": round(float(np.mean(permit[after_start])), 4),
        "halts_by_reason": dict(reasons),
        "edge_turns": controller.turns,
        "keepout_zones": len(lawn_map.keepouts),
        "localizer": {k: v for k, v in vars(loc.counters).items()},
        "sim_duration_s": round(float(t_arr[-1]), 2),
        "wall_s": round(wall, 3),
        "real_time_factor": round(float(t_arr[-1]) / wall, 1),
    }
    if vision_dropout is not None:
        metrics["vision_dropout"] = _dropout_timeline(vision_dropout, t_arr, permit, reason, sigma)
    if kidnaps:
        metrics["kidnapped_at_s"] = kidnapped_at
    if events:
        metrics["handling"] = [_handling_result(e, t_arr, permit, safety_reason) for e in events]
    if vision is not None:
        metrics.update(
            level="pixel",
            associations_judged=len(verdicts),
            association_precision=round(float(np.mean(verdicts)), 5) if verdicts else None,
            reidentifications=vision.stats.reidentified,
            associations_dropped=vision.stats.dropped_associations,
            **frontend_figures(vision),
        )
    return MowOutcome(
        metrics,
        t_arr,
        true_xy,
        true_yaw,
        est,
        permit,
        state,
        sigma,
        plant.outline_world(world.lawn.outline(1440)),
        lawn_map,
        plant.landmarks_w,
        dict(reasons),
        cov3,
        cov3_ground,
        relocalized,
        searching,
        detail,
        np.array(bearing_errors, dtype=np.float64).reshape(-1, 4) if vision is not None else None,
    )


def landmark_truth(lawn_map: LawnMap) -> dict[int, FloatArray]:
    """True world position of each map landmark, as the simulated teach run recorded it."""
    sim = lawn_map.teach.get("sim") or {}
    raw = sim.get("landmark_truth") or {}
    return {int(k): np.asarray(v, dtype=np.float64) for k, v in raw.items()}


def _judge(
    vision: Any, plant: MowerPlant, frame: Any, truth: dict[int, FloatArray]
) -> tuple[list[bool], list[tuple[float, int, float, float]]]:
    """For each association of this frame: did the localizer get a bearing of that map
    landmark? Judged from the true pose at the frame: the bearing's ray must pass within
    ``SAME_POINT_M`` of the landmark's true position (landmarks without a known true
    position — features that are not fixed points — are not judged). And for each right
    one, its error against the truth: (frame time, landmark id, azimuth and elevation
    error in rad)."""
    _, lm, _ = vision.last_associated
    if lm.size == 0:
        return [], []
    f = plant.frame  # the pixel level is flat: world = map turned and shifted in the plane
    x, y, yaw_map = frame.map_pose
    c, s = np.cos(f.yaw), np.sin(f.yaw)
    d = np.array([x, y]) - f.origin[:2]
    xy_w = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    yaw_w = yaw_map - f.yaw
    bearings = vision.last_bearings
    verdicts, errors = [], []
    nan = np.full(3, np.nan)
    for k, lid in enumerate(lm.tolist()):
        point = truth.get(lid, nan)
        verdict = sees_point(xy_w, yaw_w, bearings[k], point)
        if verdict is None:
            continue
        verdicts.append(verdict)
        if verdict:
            az, el = bearing_error(xy_w, yaw_w, bearings[k], point)
            errors.append((float(frame.t), int(lid), az, el))
    return verdicts, errors


#: the halt reason each kind of handling must give
HANDLING_REASON = {"lift": Reason.LIFTED, "tilt": Reason.TILTED, "bump": Reason.COLLISION}


def _handling_result(
    e: HandlingEvent, t: FloatArray, permit: NDArray[np.bool_], safety_reason: NDArray[Any]
) -> dict[str, Any]:
    """When the deck halted for one event and why, permits while the safety function held
    (goal 0), and when the deck ran again after the event ended."""
    k0 = int(np.searchsorted(t, e.at_s))
    end = e.at_s + e.duration_s
    out: dict[str, Any] = {
        "kind": e.kind,
        "at_s": e.at_s,
        "duration_s": e.duration_s,
        "deck_running": bool(permit[k0 - 1]) if k0 > 0 else False,
    }
    want = HANDLING_REASON[e.kind].value
    held = np.flatnonzero(safety_reason[k0:] == want)
    halted = np.flatnonzero(~permit[k0:])
    if held.size:
        out["detected_after_ms"] = round(float(t[k0 + held[0]] - e.at_s) * 1e3, 1)
        out["reason"] = want
    if halted.size:
        out["halted_after_ms"] = round(float(t[k0 + halted[0]] - e.at_s) * 1e3, 1)
    latched = np.asarray(safety_reason != "", dtype=bool)
    out["permits_while_held"] = int(np.sum(permit & latched))
    again = np.flatnonzero((t >= end) & permit)
    out["deck_again_after_end_s"] = round(float(t[again[0]] - end), 2) if again.size else None
    return out


def _dropout_timeline(dropout, t, permit, reason, sigma) -> dict[str, Any]:
    """When the deck halted after vision went, why, and when it was permitted again."""
    d0, d1 = dropout
    halted = (t >= d0) & ~permit
    out: dict[str, Any] = {"start_s": d0, "end_s": d0 + d1}
    if halted.any():
        k = int(np.argmax(halted))
        back_idx = min(int(np.searchsorted(t, d0 + d1)), len(t) - 1)
        out.update(
            halt_at_s=round(float(t[k]), 2),
            halt_reason=str(reason[k]),
            halt_after_s=round(float(t[k] - d0), 2),
            sigma_at_halt_m=round(float(sigma[k]), 4),
            sigma_at_vision_return_m=round(float(sigma[back_idx]), 4),
        )
        back = (t > t[k]) & permit
        if back.any():
            j = int(np.argmax(back))
            out.update(
                permit_again_at_s=round(float(t[j]), 2),
                permit_again_after_vision_s=round(float(t[j] - d0 - d1), 2),
            )
    window = (t >= d0) & (t < d0 + d1 + 5) & ~permit
    out["halt_reasons_in_window"] = dict(Counter(str(r) for r in reason[window]))
    return out
