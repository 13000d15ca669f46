"""The front end wired to an estimator: gyro derotation history, tracking on a worker
thread, the tracks' descriptors (see :mod:`mowerhw.vision`)."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mowerhw.camera import CameraModel
from mowerhw.common.geometry import quat_to_rotmat
from mowerhw.common.relocalization import SearchRequest
from mowerhw.config import FrontendConfig
from mowerhw.frontend import FrameTracks, FrontEnd, RotationHistory
from mowerhw.frontend.descriptors import DESCRIPTOR_BYTES, hamming

FloatArray = NDArray[np.float64]
#: radians per pixel of the omni camera near the horizon (Table I: ~470 px/rad there)
RAD_PER_PX = 1.0 / 470.0


#: a refused (track, landmark) pair is not tried again for this long (s): long enough to stop
#: a wrong pair coming back every frame, short enough that a standing mower whose tracks
#: all lost their landmarks (a sensor gap) re-identifies them again
BAN_S = 3.0
#: per-frame figures kept (bounded: the daemon runs for days); 20000 frames = 83 min at 4 Hz
STATS_FRAMES = 20000


@dataclass
class VisionStats:
    frames: int = 0
    tracks_per_frame: deque[int] = field(default_factory=lambda: deque(maxlen=STATS_FRAMES))
    observations: int = 0  # bearings handed to the estimator
    reidentified: int = 0  # tracks matched to a known landmark
    dropped_associations: int = 0
    frontend_ms: deque[float] = field(default_factory=lambda: deque(maxlen=STATS_FRAMES))


def merge_descriptors(
    have: NDArray[np.uint8] | None, new: NDArray[np.uint8], limit: int, min_bits: int = 12
) -> NDArray[np.uint8]:
    """Add the descriptors of ``new`` that differ from all of ``have`` (up to ``limit``)."""
    out = np.zeros((0, DESCRIPTOR_BYTES), np.uint8) if have is None else have
    for d in new.reshape(-1, DESCRIPTOR_BYTES):
        if out.shape[0] >= limit:
            break
        if out.shape[0] == 0 or hamming(d[None], out).min() > min_bits:
            out = np.vstack([out, d[None]])
    return out


class VisionBase:
    def __init__(
        self, camera: CameraModel, q_bc: ArrayLike, config: FrontendConfig | None, seed: int
    ) -> None:
        self.cfg = config or FrontendConfig()
        #: what the front end is built from (a runtime may run an equal one elsewhere)
        self.frontend_args = (camera, tuple(np.asarray(q_bc, dtype=float).tolist()), self.cfg, seed)
        self.frontend = FrontEnd(*self.frontend_args)
        #: what a global relocalizer is built from, where the tracking runs (mow: the map)
        self.search_args: tuple[Any, ...] | None = None
        self.camera = camera
        self.r_bc = quat_to_rotmat(np.asarray(q_bc, dtype=np.float64))
        self.rotations = RotationHistory()
        self.stats = VisionStats()
        self._t_prev: float | None = None
        # Kalibr's camera-to-IMU time shift: t_imu = t_cam + shift (calibrations without one: 0)
        self.time_shift_s = float(getattr(camera, "timeshift_cam_imu", 0.0))

    def imu(self, t: float, gyro_xyz: Any) -> None:
        """A gyro sample (body frame, as measured): its rate with the estimator's bias (and
        scale) taken out goes into the rotation history the front end derotates with — a MEMS
        gyro's ±20 °/s turn-on bias would turn every predicted feature 5° per frame."""
        self.rotations.add(t, self.estimator_rate(np.asarray(gyro_xyz, dtype=np.float64)))

    def estimator_rate(self, gyro: FloatArray) -> FloatArray:  # pragma: no cover - overridden
        return gyro

    def frame(self, t: float, image: NDArray[np.uint8]) -> FrameTracks:
        """One image, start to end: :meth:`prepare`, :meth:`track`, :meth:`use`."""
        return self.use(self.track(t, image, self.prepare(t), self.wants_search()))

    def wants_search(self) -> SearchRequest | None:
        """Whether the next frame's tracking should also relocalize, and where (call on the
        estimator's thread, with :meth:`prepare`)."""
        return None

    def prepare(self, t: float) -> FloatArray | None:
        """The gyro's body rotation from the previous frame to the one taken at ``t`` (call on
        the estimator's thread: it reads the IMU history)."""
        t = t + self.time_shift_s
        r = None
        if self._t_prev is not None:
            r = self.rotations.rotation_between(self._t_prev, t)
        self._t_prev = t
        return r

    def track(
        self,
        t: float,
        image: NDArray[np.uint8],
        r_prev_cur: FloatArray | None,
        search: SearchRequest | None = None,
    ) -> FrameTracks:
        """Detection and tracking, the costly part: touches only the front end, so a runtime
        may run it on a worker thread (one frame at a time). ``t`` is the camera's capture
        time; the tracks carry it on the IMU's clock (``timeshift_cam_imu`` applied).
        ``search``: relocalize from the tracks too (:meth:`wants_search`)."""
        carried = search is not None and search.carried
        tracks = self.frontend.process(t + self.time_shift_s, image, r_prev_cur, carried)
        return self.tracked(tracks if search is None else self.searched(tracks, search))

    def searched(self, tracks: FrameTracks, search: SearchRequest) -> FrameTracks:
        """The tracks with a relocalization from their bearings (mow only)."""
        return tracks

    def tracked(self, tracks: FrameTracks) -> FrameTracks:
        """Count a frame's tracks (however they were made)."""
        self.stats.frames += 1
        self.stats.tracks_per_frame.append(int(tracks.ids.size))
        self.stats.frontend_ms.append(tracks.ms)
        return tracks

    def use(self, tracks: FrameTracks) -> FrameTracks:  # pragma: no cover - overridden
        raise NotImplementedError

    def _track_descriptors(self, tracks: FrameTracks) -> tuple[NDArray[np.uint8], NDArray]:
        """The newest descriptor of every track, and which tracks have one."""
        desc = np.zeros((tracks.ids.size, DESCRIPTOR_BYTES), np.uint8)
        has = np.zeros(tracks.ids.size, bool)
        for k, dd in enumerate(tracks.descriptors):
            if dd.shape[0]:
                desc[k], has[k] = dd[-1], True
        return desc, has

    def _in_view(self, bearings: FloatArray) -> NDArray[np.bool_]:
        """Predicted bearings that land inside the camera's mask."""
        if bearings.shape[0] == 0:
            return np.zeros(0, bool)
        _, ok = self.camera.visible(bearings @ self.r_bc)
        return ok
