"""Pixel-level vision wired to the estimators: front end + re-identification → teach / mow.

These two classes turn camera images into the ``(t, ids, bearings)`` the estimators take,
with landmark ids that mean the same thing across track losses (teach) and sessions (mow):

* :class:`TeachVision` — every new track is first offered to the landmarks the
  :class:`~mowerhw.teach.Teacher` has already located but does not see now (predicted
  bearing from the teacher's pose and map, gate, ORB distance); a match continues that
  landmark (it comes back into view, the loop closes on it); otherwise the track starts a
  new landmark. Descriptors and the keyframe of first sight are kept for the map.
* :class:`MowVision` — a track becomes a map landmark only through re-identification
  against the :class:`~mowerhw.mow.Localizer`'s prediction for the frame's time (bearing and
  its covariance, χ² gate) plus ORB distance to the map's descriptors; an association the
  localizer's own χ² gate keeps refusing is dropped and that pair is not tried again.

Pure computation (no device I/O): the runtime feeds it frames from the camera driver, the
bench from the renderer.

Modules: :mod:`.base` (the front end on a worker thread, derotation), :mod:`.teach`,
:mod:`.mow`.
"""

from mowerhw.vision.base import VisionBase, VisionStats
from mowerhw.vision.mow import MowVision
from mowerhw.vision.teach import TeachVision

__all__ = ["MowVision", "TeachVision", "VisionBase", "VisionStats"]
