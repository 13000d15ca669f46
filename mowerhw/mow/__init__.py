"""Mow phase (paper §IV): world-centric localization against the map, and containment.

``from mowerhw.mow import Localizer`` — see :mod:`mowerhw.mow.localizer`. The names are
loaded on first use (PEP 562), so ``mowerhw.mow.gate`` is cheap to import (the permit
supervisor imports it, and must stay small).
"""

from __future__ import annotations

import importlib
from typing import Any

_WHERE = {
    "Containment": "mowerhw.mow.containment",
    "ContainmentResult": "mowerhw.mow.containment",
    "LawnGeometry": "mowerhw.mow.containment",
    "Localizer": "mowerhw.mow.localizer",
    "Pose": "mowerhw.mow.localizer",
    "Reason": "mowerhw.common.reasons",
    "State": "mowerhw.common.reasons",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'mowerhw.mow' has no attribute {name!r}")
