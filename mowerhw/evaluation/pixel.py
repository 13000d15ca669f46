"""The pixel-level bench (docs/design.md §9, level 2): rendered images → front end → estimators.

The same simulated drives as the bearing level (:mod:`mowerhw.evaluation.teach`,
:mod:`mowerhw.evaluation.mow`), but the camera delivers 1540×1540 images rendered by
:class:`mowerhw.sim.render.OmniRenderer`, and landmarks are whatever the front end finds and
re-identifies (:mod:`mowerhw.vision`). The truth is used only to score:

* each track's true 3-D point is what its first pixel sees (ray cast in the renderer); a map
  landmark's truth is that of the track that created it (sky features have none);
* ``association_precision``: of the bearings handed to the estimator under a landmark id that
  another track created, the share whose track truly sees the same point (within
  ``SAME_POINT_M``); at teach time these are the re-identifications, at mow time every
  association with the map;
* ``tracks_per_frame``, ``track_length_median`` (frames, over every track that ended),
  ``frontend_ms_per_frame``.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.geometry import wrap_angle, yaw_rotation
from mowerhw.config import Config, FrontendConfig, TeachConfig
from mowerhw.evaluation.teach import sim_map, teach_metrics
from mowerhw.sim import TeachRun, simulate_teach
from mowerhw.sim.render import OmniRenderer
from mowerhw.teach import BoundaryError, Teacher, TeachError, TeachResult
from mowerhw.vision import TeachVision

FloatArray = NDArray[np.float64]

#: two tracks see "the same point" if their true points are this close (panel code cells are
#: 0.1 m apart)
SAME_POINT_M = 0.05


@dataclass
class TrackTruth:
    """The true 3-D point (world frame) each track sees in each frame (ray cast in the
    renderer; NaN for the sky), and one point per track: the one most of its frames agree on
    (a track that jumps to another feature keeps the truth of its majority)."""

    points: dict[int, list[FloatArray]] = field(default_factory=dict)
    frames: dict[int, list[float]] = field(default_factory=dict)

    def record(self, renderer: OmniRenderer, pose: tuple, to_world: Any, tracks: Any) -> None:
        if tracks.ids.size == 0:
            return
        pts = renderer.true_points(*pose, tracks.pixels)
        world = to_world(np.nan_to_num(pts, nan=0.0))
        world[~np.all(np.isfinite(pts), axis=1)] = np.nan
        for tid, w in zip(tracks.ids.tolist(), world, strict=True):
            self.points.setdefault(int(tid), []).append(w)
            self.frames.setdefault(int(tid), []).append(tracks.t)

    def at(self, tid: int, t: float) -> FloatArray:
        """What track ``tid`` saw in the frame at ``t``."""
        ts = self.frames.get(int(tid), [])
        for k in range(len(ts) - 1, -1, -1):
            if abs(ts[k] - t) < 1e-9:
                return self.points[int(tid)][k]
        return np.full(3, np.nan)

    def point(self, tid: int) -> FloatArray:
        return majority_point(np.asarray(self.points.get(int(tid), np.zeros((0, 3)))))


def majority_point(pts: FloatArray) -> FloatArray:
    """The point most of ``pts`` (N, 3) lie within ``SAME_POINT_M`` of (mean of that
    cluster); NaN if no point is shared by more than half of them: a feature that is not a
    fixed point (the sky, or a corner formed by an edge passing in front of something else,
    which slides as the mower moves)."""
    n = pts.shape[0] if pts.size else 0
    fin = pts[np.all(np.isfinite(pts), axis=1)] if n else np.zeros((0, 3))
    if fin.shape[0] * 2 <= n:
        return np.full(3, np.nan)
    step = max(1, fin.shape[0] // 400)  # plenty: a subsample finds the same cluster
    sub = fin[::step]
    d = np.linalg.norm(sub[:, None, :] - sub[None, :, :], axis=-1) <= SAME_POINT_M
    best = int(np.argmax(d.sum(axis=1)))
    if d[best].sum() * 2 <= n / step:
        return np.full(3, np.nan)
    return sub[d[best]].mean(axis=0)


def _ray_and_offset(
    position: FloatArray, yaw: float, bearing_b: FloatArray, point: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """A body-frame bearing as a world ray from a (true) planar pose, and ``point`` (world
    frame) from there: the camera at the body origin, the pixel level flat."""
    ray = yaw_rotation(yaw) @ np.asarray(bearing_b, dtype=np.float64)
    return ray, point - np.array([position[0], position[1], 0.0])


def sees_point(
    position: FloatArray, yaw: float, bearing_b: FloatArray, point: FloatArray
) -> bool | None:
    """Whether a body-frame bearing measured from a (true) planar pose passes within
    ``SAME_POINT_M`` of ``point`` (world frame; the camera at the body origin). None if the
    point is unknown. This is how associations are judged: did the estimator get a bearing
    of that landmark, or of something next to it?"""
    if not np.all(np.isfinite(point)):
        return None
    ray, d = _ray_and_offset(position, yaw, bearing_b, point)
    along = float(d @ ray)
    if along <= 0:
        return False
    return bool(np.linalg.norm(d - along * ray) <= SAME_POINT_M)


def bearing_error(
    position: FloatArray, yaw: float, bearing_b: FloatArray, point: FloatArray
) -> tuple[float, float]:
    """A body-frame bearing's azimuth and elevation error (rad) against the direction from
    a (true) planar pose to ``point`` (world frame; the camera at the body origin)."""
    ray, d = _ray_and_offset(position, yaw, bearing_b, point)
    az = wrap_angle(math.atan2(ray[1], ray[0]) - math.atan2(d[1], d[0]))
    el = math.atan2(ray[2], math.hypot(ray[0], ray[1])) - math.atan2(d[2], math.hypot(d[0], d[1]))
    return float(az), float(el)


def bearing_error_figures(errors: FloatArray, min_frames: int = 12) -> dict[str, Any]:
    """What the bearings' errors against the truth are made of (rows: frame time, landmark
    id, azimuth and elevation error in rad; :func:`mowerhw.evaluation.mow.run_mow`), in
    degrees: their RMS; the frame's mean over its landmarks (what all share: a clock or
    heading error) against what independent errors would average to; per landmark seen in
    at least ``min_frames`` frames, the spread of their means (a bias that stays with the
    landmark) and of what is left, and how alike the errors of one landmark are from one
    of its frames to the next and to the fourth next (1: the same error again)."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1, 4)
    if e.shape[0] == 0:
        return {"bearings": 0}
    t, lid, az = e[:, 0], e[:, 1].astype(np.int64), e[:, 2]
    frames, frame_of = np.unique(t, return_inverse=True)
    n_per_frame = np.bincount(frame_of)
    per_frame = np.bincount(frame_of, az) / n_per_frame
    left = az - per_frame[frame_of]
    means, lag1, lag4, kept = [], [], [], []
    for landmark in np.unique(lid):
        track = left[lid == landmark]
        if track.size < min_frames:
            continue
        means.append(float(track.mean()))
        centred = track - track.mean()
        kept.append(centred)
        if centred.var() > 0:
            lag1.append(float(np.corrcoef(centred[:-1], centred[1:])[0, 1]))
            lag4.append(float(np.corrcoef(centred[:-4], centred[4:])[0, 1]))

    def deg(v: float) -> float:
        return round(math.degrees(v), 4)

    rest = np.concatenate(kept) if kept else np.zeros(0)
    return {
        "bearings": int(e.shape[0]),
        "frames": int(frames.size),
        "azimuth_rms_deg": deg(float(np.sqrt(np.mean(az**2)))),
        "elevation_rms_deg": deg(float(np.sqrt(np.mean(e[:, 3] ** 2)))),
        "frame_mean_rms_deg": deg(float(np.sqrt(np.mean(per_frame**2)))),
        "frame_mean_rms_if_independent_deg": deg(
            float(np.sqrt(np.mean(np.mean(az**2) / n_per_frame)))
        ),
        "landmarks": len(means),
        "landmark_bias_rms_deg": deg(float(np.sqrt(np.mean(np.square(means))))) if means else None,
        "within_landmark_rms_deg": deg(float(np.sqrt(np.mean(rest**2)))) if rest.size else None,
        "next_frame_correlation": round(float(np.nanmean(lag1)), 3) if lag1 else None,
        "fourth_frame_correlation": round(float(np.nanmean(lag4)), 3) if lag4 else None,
    }


def same_point(a: FloatArray, b: FloatArray) -> bool | None:
    """Whether two true points are the same (None if either is unknown)."""
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return None
    return bool(np.linalg.norm(a - b) <= SAME_POINT_M)


def frontend_figures(vision: Any) -> dict[str, Any]:
    st = vision.stats
    fe = vision.frontend
    lengths = fe.stats.track_lengths
    return {
        "tracks_per_frame": round(float(np.median(st.tracks_per_frame)), 1)
        if st.tracks_per_frame
        else 0.0,
        "track_length_median": float(np.median(lengths)) if lengths else 0.0,
        "frontend_ms_per_frame": round(float(np.mean(st.frontend_ms)), 2)
        if st.frontend_ms
        else 0.0,
        "frontend": {
            "frames": fe.stats.frames,
            "features_detected": fe.stats.detected,
            "lost_klt": fe.stats.lost_klt,
            "lost_forward_backward": fe.stats.lost_forward_backward,
            "lost_refine": fe.stats.lost_refine,
            "lost_epipolar": fe.stats.lost_epipolar,
            "lost_outside": fe.stats.lost_outside,
        },
    }


@dataclass
class PixelTeachOutcome:
    run: TeachRun
    result: TeachResult | None
    metrics: dict[str, Any]
    vision: TeachVision
    truth: TrackTruth
    landmark_truth: dict[int, FloatArray]
    error: str = ""
    images: dict[float, Any] = field(default_factory=dict)  # t → (image, tracks, extras)


def run_teach_pixel(
    scenario: str = "paper",
    seed: int = 0,
    config: Config | None = None,
    keep_images_at: tuple[float, ...] = (),
) -> PixelTeachOutcome:
    """Simulate a teach drive, render its frames, run front end + Teacher, score."""
    cfg = config or Config()
    teach_cfg: TeachConfig = cfg.teach
    fe_cfg: FrontendConfig = cfg.frontend
    run = simulate_teach(scenario, seed)
    world, truth = run.world, run.truth
    renderer = OmniRenderer(world, seed)
    teacher = Teacher(teach_cfg, camera=world.camera)
    vision = TeachVision(teacher, world.camera, world.q_bc, fe_cfg, seed)
    track_truth = TrackTruth()
    images: dict[float, tuple[NDArray[np.uint8], Any, dict[int, list]]] = {}
    trails: dict[int, list[FloatArray]] = {}  # recent pixels of every live track (figures)
    wall_render = 0.0
    t0 = time.perf_counter()
    for kind, payload in run.streams.events(magnetometer=True):
        if kind == "imu":
            teacher.imu(*payload)
            vision.imu(*payload)
        elif kind == "mag":
            teacher.magnetometer(*payload)
        elif kind == "speed":
            teacher.speed(*payload)
        else:
            t = payload.t
            k = truth.index_at(t)
            pose = (
                float(truth.map_xy[k, 0]),
                float(truth.map_xy[k, 1]),
                float(truth.map_heading[k]),
            )
            r0 = time.perf_counter()
            image = renderer.render(*pose)
            wall_render += time.perf_counter() - r0
            tracks = vision.frame(t, image)
            track_truth.record(renderer, pose, truth.map_to_world, tracks)
            if keep_images_at:
                trails = {
                    tid: ([*trails.get(tid, []), px])[-12:]
                    for tid, px in zip(tracks.ids.tolist(), tracks.pixels, strict=True)
                }
                if any(abs(t - ti) < 0.125 for ti in keep_images_at):
                    lm = {tid: vision.landmark_of[tid] for tid in tracks.ids.tolist()}
                    images[t] = (image, tracks, {"trails": dict(trails), "landmark_of": lm})
    wall = time.perf_counter() - t0 - wall_render
    # a landmark's truth is what the track that created it saw (landmark id = its track id)
    landmark_truth = {}
    for lid in track_truth.points:
        p = track_truth.point(lid)
        if np.all(np.isfinite(p)):
            landmark_truth[lid] = p
    f0 = time.perf_counter()
    try:
        result = vision.annotate(teacher.finish())
    except (BoundaryError, TeachError) as exc:
        metrics = {"diverged": True, "error": str(exc), **frontend_figures(vision)}
        return PixelTeachOutcome(
            run, None, metrics, vision, track_truth, landmark_truth, error=str(exc), images=images
        )
    finish = time.perf_counter() - f0
    metrics = teach_metrics(run, result, wall, finish, landmark_truth)
    # re-identification at teach time: a new track given an older landmark's id
    nan = np.full(3, np.nan)
    verdicts = []
    for t, _tid, lid, bearing in vision.reidentifications:
        k = truth.index_at(t)
        verdicts.append(
            sees_point(truth.xy[k], float(truth.yaw[k]), bearing, landmark_truth.get(lid, nan))
        )
    known = [v for v in verdicts if v is not None]
    metrics.update(
        level="pixel",
        landmarks_in_map=len(result.landmarks),
        landmarks_not_fixed_points=len(result.landmarks) - metrics["landmarks_mapped"],
        reidentifications=len(vision.reidentifications),
        reidentifications_judged=len(known),
        association_precision=round(float(np.mean(known)), 4) if known else None,
        render_wall_s=round(wall_render, 3),
        **frontend_figures(vision),
    )
    return PixelTeachOutcome(
        run, result, metrics, vision, track_truth, landmark_truth, images=images
    )


def yard_arguments(parser: argparse.ArgumentParser, with_map: bool = True) -> None:
    """The pixel-level benchmarks' common options: the simulated yard (``--scenario``,
    ``--seed``) and, ``with_map``, a map taught before (``--map``, for :func:`pixel_map`)."""
    parser.add_argument("--scenario", default="paper")
    parser.add_argument("--seed", type=int, default=1)
    if with_map:
        parser.add_argument("--map", help="a map a pixel-level teach saved (skips the teach)")


def pixel_map(
    scenario: str, seed: int, config: Config, path: str | None = None, save: str | None = None
) -> Any:
    """A pixel-level map of the yard ``scenario``/``seed``: the one a teach saved at ``path``,
    or one taught now on rendered images, with its landmarks' true positions (the NEES in
    the map's frame, the bearings' errors), written to ``save`` when given."""
    from mowerhw.map import load

    if path:
        return load(path)
    taught = run_teach_pixel(scenario, seed, config)
    if taught.result is None:
        raise RuntimeError(f"the pixel-level teach of {scenario}/{seed} failed: {taught.error}")
    lawn_map = sim_map(taught.result, scenario, seed, "pixel", taught.landmark_truth)
    if save:
        lawn_map.save(save)
    return lawn_map


@dataclass(frozen=True)
class PixelMaps:
    """The pixel-level map of each seed of the yard ``scenario`` (:func:`pixel_map`, taught
    with ``config``), kept in ``folder`` as ``<scenario>_<seed>.json`` when one is given:
    a map kept there is loaded instead of taught again (a pool re-run with other settings
    draws the same maps; delete the folder after changing the teach), a map taught is
    written there. A file there that is not this yard's pixel-level map of that seed is
    refused. Picklable: a campaign's workers each make their own maps."""

    scenario: str
    config: Config
    folder: str | None = None

    def __call__(self, seed: int) -> Any:
        from pathlib import Path

        from mowerhw.map import load

        if self.folder is None:
            return pixel_map(self.scenario, seed, self.config)
        path = Path(self.folder) / f"{self.scenario}_{seed}.json"
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            return pixel_map(self.scenario, seed, self.config, save=str(path))
        lawn_map = load(path)
        sim = lawn_map.teach.get("sim") or {}
        got = (sim.get("scenario"), sim.get("seed"), sim.get("level"))
        if got != (self.scenario, seed, "pixel"):
            raise ValueError(
                f"{path}: kept map is of scenario {got[0]!r}, seed {got[1]!r}, level "
                f"{got[2]!r}; expected {self.scenario!r}, seed {seed}, level 'pixel' "
                "(a map from another yard cannot score this one: move it away)"
            )
        return lawn_map
