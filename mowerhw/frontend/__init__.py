"""Vision front end (pixel level): features, tracking, outlier rejection, re-identification.

Tracking (:mod:`.tracker`) is kept apart from estimation: it turns images into
``(t, ids, bearings)``. Re-identification (:mod:`.association`) matches tracks to known
landmarks using what an estimator predicts, and is wired by the runtime / bench.
"""

from mowerhw.frontend.gyro import RotationHistory
from mowerhw.frontend.tracker import FrameTracks, FrontEnd, FrontendStats

__all__ = ["FrameTracks", "FrontEnd", "FrontendStats", "RotationHistory"]
