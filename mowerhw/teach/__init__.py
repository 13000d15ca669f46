"""Teach phase (paper §II–III): landmark observers, robot-centric EKF, boundary, map.

``from mowerhw.teach import Teacher`` — see :mod:`mowerhw.teach.teacher`.
"""

from mowerhw.teach.boundary import BoundaryError
from mowerhw.teach.teacher import LoopClosure, Teacher, TeachError, TeachResult

__all__ = ["BoundaryError", "LoopClosure", "TeachError", "TeachResult", "Teacher"]
