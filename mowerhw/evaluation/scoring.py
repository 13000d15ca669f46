"""How a mowing run is scored against the truth, for the simulator and the bench alike.

* ``missed_halts``: samples with the deck permitted while the mower is truly more than
  :data:`MISSED_HALT_M` outside the lawn (the deck should have stopped);
* ``false_halt_fraction``: share of the samples with the mower truly more than
  :data:`SAFE_INSIDE_M` inside (after the start, outside excluded windows such as injected
  faults) where the deck was halted; None when there is no such sample;
* ``time_outside_s``: time the mower truly spent outside.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

MISSED_HALT_M = 0.10
SAFE_INSIDE_M = 1.0


def score_halts(
    t: NDArray[np.float64],
    permit: NDArray[np.bool_],
    s_true: NDArray[np.float64],
    start_s: float,
    dt: float,
    excluded: NDArray[np.bool_] | None = None,
) -> dict[str, Any]:
    """The three figures of the module doc. ``s_true``: the true signed distance to the
    edge (positive inside) at each sample; ``start_s``: when scoring of false halts starts;
    ``dt``: the sample period."""
    missed = permit & (s_true < -MISSED_HALT_M)
    safe = (t >= start_s) & (s_true > SAFE_INSIDE_M)
    if excluded is not None:
        safe &= ~excluded
    return {
        "missed_halts": int(missed.sum()),
        "false_halt_fraction": round(float(np.mean(~permit[safe])), 5) if safe.any() else None,
        "time_outside_s": round(float(np.sum(s_true < 0) * dt), 3),
    }
