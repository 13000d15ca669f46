"""Mow phase (paper §IV): world-centric localization against the map, and containment.

``from mowerhw.mow import Localizer`` — see :mod:`mowerhw.mow.localizer`.
"""

from mowerhw.mow.containment import Containment, ContainmentResult, LawnGeometry, Reason, State
from mowerhw.mow.localizer import Localizer, Pose

__all__ = [
    "Containment",
    "ContainmentResult",
    "LawnGeometry",
    "Localizer",
    "Pose",
    "Reason",
    "State",
]
