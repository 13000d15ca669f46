"""Which estimator chain the runtime wants and which it has (docs/design.md §8): at most one
request outstanding, named by a serial, so a chain built for a mode or map that has changed
meanwhile is never installed; and how a new localizer resumes from a pose it had."""

from __future__ import annotations

import math
from collections.abc import Callable

from mowerhw.map import LawnMap
from mowerhw.runtime.pipelines import BuildRequest, MowPipeline, StartPose

#: good frames a rebuilt or resumed estimator needs before it may permit (4 Hz: 2.5 s)
REBUILT_FRAMES = 10
#: how far a resumed pose is widened: after a restart (the pose file is written at 10 Hz; σ
#: under a third of the 0.4 m pane spacing of window landmarks, a wider prior locked onto the
#: neighbouring corners on the bench) and after an estimator rebuilt within this run (from a
#: pose at most 0.1 s old). The mower may have moved on meanwhile (on the bench: killed while
#: turning on the spot, it turned 18° more): the relocalizer's check near the prior takes only
#: an optimum near it, and with none there judges the frame as a search of the whole map
RESUME_SIGMA_RESTART = (0.12, math.radians(6.0))
RESUME_SIGMA_REBUILT = (0.05, math.radians(3.0))


class ChainRequests:
    """The outstanding :class:`BuildRequest` (handed to ``on_build``) and the installed one."""

    def __init__(self, on_build: Callable[[BuildRequest], None] | None = None) -> None:
        self.on_build = on_build
        self.pending: BuildRequest | None = None
        self.installed_serial = 0
        self._serial = 0

    def request(
        self,
        kind: str,
        lawn_map: LawnMap | None = None,
        start_pose: StartPose | None = None,
        resumed: bool = False,
        mow_areas: tuple[str, ...] | None = None,
    ) -> BuildRequest:
        self._serial += 1
        req = BuildRequest(self._serial, kind, lawn_map, start_pose, resumed, mow_areas)
        self.pending = req
        if self.on_build is not None:
            self.on_build(req)
        return req

    def cancel(self) -> None:
        self.pending = None

    def accept(self, serial: int, mode: str) -> BuildRequest | None:
        """The request ``serial`` if it is still the one wanted in ``mode`` (then installed)."""
        req = self.pending
        if req is None or req.serial != serial or req.kind != mode:
            return None
        self.pending = None
        self.installed_serial = serial
        return req


def resume_localizer(pipe: MowPipeline, pose: StartPose, restarted: bool) -> None:
    """A new localizer resumes from a pose it had, widened, with the gyro bias it had where
    it is known (a rebuild; a restart within the same boot, from the pose file); a restart
    without one calibrates the gyro first, while the mower stands. A standstill cannot tell
    a bias from a turn at a steady rate: measured in the simulator, a daemon restarted while
    the mower turned on the spot at 0.8 rad/s learnt 0.8 rad/s of bias, and no two answers
    of the relocalizer agreed through its odometry again (11° apart each frame), halted for
    good."""
    sigma = RESUME_SIGMA_RESTART if restarted else RESUME_SIGMA_REBUILT
    pipe.localizer.resume(
        pose.position,
        pose.quaternion,
        *sigma,
        gyro_bias=pose.gyro_bias,
        calibrate=restarted and pose.gyro_bias is None,
        frames_needed=REBUILT_FRAMES,
    )
