"""Gyro noise from data: the Allan deviation of a static recording, and what it says.

``mowerhw imu characterize RECORDING`` reads the gyro samples of a recording made with the
mower standing still — an MCAP from ``mowerhw record`` (the VN-100's own bytes, through the
same parser and extractor the daemon uses: the command's part) or a CSV of ``t, gx, gy, gz``
(s, rad/s, :func:`load_csv`) — and :func:`characterize` computes the overlapping Allan
deviation of each axis (``allantools.oadev``, octave-spaced τ) and reads off the three figures
the estimators need:

* **white noise** ``N`` (angle random walk, rad/s/√Hz): σ(τ)·√τ on the short-τ part where
  the curve falls as τ^-½;
* **bias instability** ``B`` (rad/s): the curve's floor, as datasheets quote "in-run bias
  stability" (IEEE 952's B coefficient is this / 0.664);
* **rate random walk** ``K`` (rad/s/√s): σ(τ)·√(3/τ) on the long-τ part where the curve rises
  as τ^½ — only if the recording is long enough to reach it (say so otherwise).

The config keys are the largest over the three axes (a conservative estimator).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

AXES = ("x", "y", "z")
#: fewest samples worth an Allan analysis
MIN_SAMPLES = 1000
#: τ is read only up to the recording's length over this (enough stretches to average)
MIN_STRETCHES = 9


class CharacterizeError(ValueError):
    """The recording cannot be characterised; the message says why."""


@dataclass
class AllanResult:
    rate_hz: float
    duration_s: float
    samples: int
    taus: FloatArray
    adev: FloatArray  # (T, 3)
    noise_density: FloatArray  # (3,)
    bias_instability: FloatArray  # (3,)
    bias_instability_tau_s: FloatArray  # (3,)
    rate_random_walk: FloatArray  # (3,) NaN where the recording is too short
    source: str = ""
    notes: list[str] = field(default_factory=list)

    def config_values(self) -> dict[str, float | None]:
        """The imu keys to use: the largest over the axes (null: not measured)."""
        k = self.rate_random_walk
        return {
            "gyro_noise_density": float(np.max(self.noise_density)),
            "gyro_bias_instability": float(np.max(self.bias_instability)),
            "gyro_random_walk": float(np.nanmax(k)) if np.any(np.isfinite(k)) else None,
        }

    def as_dict(self) -> dict[str, Any]:
        def per_axis(values: FloatArray) -> dict[str, float | None]:
            return {
                a: (float(v) if math.isfinite(v) else None)
                for a, v in zip(AXES, values, strict=True)
            }

        return {
            "source": self.source,
            "samples": self.samples,
            "rate_hz": round(self.rate_hz, 3),
            "duration_s": round(self.duration_s, 1),
            "noise_density_rad_s_rthz": per_axis(self.noise_density),
            "bias_instability_rad_s": per_axis(self.bias_instability),
            "bias_instability_at_tau_s": per_axis(self.bias_instability_tau_s),
            "rate_random_walk_rad_s_rts": per_axis(self.rate_random_walk),
            "config": {"imu": self.config_values()},
            "notes": self.notes,
        }


def load_csv(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Times (s) and gyro samples (N, 3) rad/s of a CSV of ``t, gx, gy, gz``."""
    path = Path(path)
    if not path.exists():
        raise CharacterizeError(f"{path}: no such file")
    rows = []
    with path.open(newline="", encoding="utf-8") as fh:
        for k, rec in enumerate(csv.reader(fh)):
            if not rec or rec[0].lstrip().startswith("#"):
                continue
            try:
                rows.append([float(v) for v in rec[:4]])
            except ValueError:
                if k == 0:  # a header
                    continue
                raise CharacterizeError(
                    f"{path}: line {k + 1} is not four numbers t, gx, gy, gz: {rec[:4]}"
                ) from None
    if not rows or any(len(r) != 4 for r in rows):
        raise CharacterizeError(f"{path}: expected columns t, gx, gy, gz (s, rad/s)")
    data = np.asarray(rows, dtype=np.float64)
    return data[:, 0], data[:, 1:4]


def characterize(t: FloatArray, gyro: FloatArray, source: str = "") -> AllanResult:
    """The Allan analysis of static gyro samples (see the module doc)."""
    import allantools

    t = np.asarray(t, dtype=np.float64)
    gyro = np.asarray(gyro, dtype=np.float64)
    if gyro.shape[0] < MIN_SAMPLES:
        raise CharacterizeError(
            f"{gyro.shape[0]} samples: an Allan analysis needs at least {MIN_SAMPLES} "
            "(record the mower standing still for 30 min or more)"
        )
    dt = np.diff(t)
    if not np.all(np.isfinite(dt)) or np.any(dt <= 0):
        raise CharacterizeError("sample times must increase")
    rate = 1.0 / float(np.median(dt))
    gaps = int(np.sum(dt > 2.5 / rate))
    notes = []
    if gaps:
        notes.append(f"{gaps} gaps longer than 2.5 samples: the analysis treats samples as even")
    adevs = []
    taus = None
    for axis in range(3):
        tau, ad, _, _ = allantools.oadev(gyro[:, axis], rate=rate, data_type="freq", taus="octave")
        taus = tau if taus is None else taus
        adevs.append(ad[: len(taus)])
    assert taus is not None
    adev = np.stack(adevs, axis=1)
    duration = float(t[-1] - t[0])
    # an Allan deviation at τ is worth reading only with enough τ-long stretches to average
    usable = taus <= duration / MIN_STRETCHES
    taus, adev = taus[usable], adev[usable]
    n_est, b_est, b_tau, k_est = (np.full(3, np.nan) for _ in range(4))
    for axis in range(3):
        n_est[axis], b_est[axis], b_tau[axis], k_est[axis] = _read_off(taus, adev[:, axis])
    falling = [
        AXES[a] for a in range(3) if b_tau[a] >= taus[-1] and _slope_at_end(taus, adev[:, a]) < -0.2
    ]
    if falling:
        notes.append(
            f"axis {', '.join(falling)}: the curve still falls at the longest usable τ "
            f"({taus[-1]:.0f} s): its bias instability is at most the value given; record longer"
        )
    if not np.any(np.isfinite(k_est)):
        notes.append(
            f"no τ^½ rise up to τ = {taus[-1]:.0f} s (a ninth of the recording): the rate "
            "random walk is not measured; record longer (hours) to see it"
        )
    return AllanResult(
        rate, duration, int(gyro.shape[0]), taus, adev, n_est, b_est, b_tau, k_est, source, notes
    )


def _read_off(taus: FloatArray, adev: FloatArray) -> tuple[float, float, float, float]:
    ok = np.isfinite(adev) & (adev > 0)
    taus, adev = taus[ok], adev[ok]
    lt, la = np.log(taus), np.log(adev)
    slope = np.gradient(la, lt)
    k_min = int(np.argmin(adev))
    floor, floor_tau = float(adev[k_min]), float(taus[k_min])
    # white noise: the τ^-½ part, before the floor
    white = (slope < -0.35) & (slope > -0.65) & (np.arange(taus.size) < k_min)
    if not white.any():
        white = np.arange(taus.size) < max(1, k_min // 2)
    n = float(np.median(adev[white] * np.sqrt(taus[white])))
    # rate random walk: the τ^½ part, after the floor
    rising = (slope > 0.35) & (slope < 0.7) & (np.arange(taus.size) > k_min)
    k = float(np.median(adev[rising] * np.sqrt(3.0 / taus[rising]))) if rising.any() else math.nan
    return n, floor, floor_tau, k


def _slope_at_end(taus: FloatArray, adev: FloatArray) -> float:
    if taus.size < 2:
        return 0.0
    return float(np.log(adev[-1] / adev[-2]) / np.log(taus[-1] / taus[-2]))


def plot_allan(result: AllanResult, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5.5))
    tau = result.taus
    for axis, name in enumerate(AXES):
        (line,) = ax.loglog(tau, result.adev[:, axis], "o-", ms=3, label=f"gyro {name}")
        n, b, k = (
            result.noise_density[axis],
            result.bias_instability[axis],
            result.rate_random_walk[axis],
        )
        ax.loglog(tau, n / np.sqrt(tau), ":", color=line.get_color(), lw=1)
        ax.axhline(b, color=line.get_color(), lw=0.6, ls="--")
        if math.isfinite(k):
            ax.loglog(tau, k * np.sqrt(tau / 3.0), "-.", color=line.get_color(), lw=1)
    ax.set_xlabel("τ (s)")
    ax.set_ylabel("Allan deviation (rad/s)")
    ax.set_title(
        f"gyro Allan deviation, {result.duration_s / 60:.0f} min at {result.rate_hz:.0f} Hz "
        "(dotted: N/√τ, dashed: floor, dash-dot: K√(τ/3))"
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def static_recording(grade_name: str, duration_s: float, seed: int = 0, rate_hz: float = 100.0):
    """Times and gyro samples of a simulated gyro of ``grade_name`` standing still (the
    simulator's own :class:`~mowerhw.sim.sensors.Gyro`)."""
    from mowerhw.imu.grades import IMU_GRADES
    from mowerhw.sim.sensors import Gyro

    gyro = Gyro(IMU_GRADES[grade_name], np.random.default_rng([seed, 77]), rate_hz)
    n = int(duration_s * rate_hz)
    t = np.arange(n) / rate_hz
    out, _ = gyro.measure_all(np.zeros((n, 3)))
    return t, out
