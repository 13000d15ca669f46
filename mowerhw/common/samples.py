"""Timestamped sample types that flow from drivers to estimators (docs/design.md §3, §8).

Every sample carries ``t``: seconds on the host monotonic clock (``time.monotonic_ns() / 1e9``
at arrival, or a device timestamp mapped onto it by :mod:`mowerhw.common.clocksync`). Drivers build
them, the runtime buffers them (:mod:`mowerhw.common.buffer`), estimators read their arrays.
Arrays are float64 and never shared mutable state: a sample is frozen once made.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class Stream(StrEnum):
    """Names of the sensor streams in the buffer."""

    IMU = "imu"
    SPEED = "speed"
    FRAME = "frame"
    BEARINGS = "bearings"


def _vec3(value: object, name: str) -> FloatArray:
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (3,):
        arr = value.view()  # the common case (a driver's own array), made once per IMU sample
    else:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
        if arr.shape != (3,):
            raise ValueError(f"{name} must have 3 components, got shape {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU reading in the IMU frame: gyro (rad/s), optional accel (m/s²) and magnetic
    field (T)."""

    t: float
    gyro: FloatArray
    accel: FloatArray | None = None
    device_time_ns: int | None = None  # VN-100 TimeStartup, if the packet had it
    host_time_ns: int | None = None  # arrival, before clock mapping
    mag: FloatArray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "gyro", _vec3(self.gyro, "gyro"))
        if self.accel is not None:
            object.__setattr__(self, "accel", _vec3(self.accel, "accel"))
        if self.mag is not None:
            object.__setattr__(self, "mag", _vec3(self.mag, "mag"))

    @property
    def finite(self) -> bool:
        # one sum (of Python floats: no numpy warning for inf − inf): a NaN or an infinity
        # anywhere makes it non-finite
        total = self.t + sum(self.gyro.tolist())
        if self.accel is not None:
            total += sum(self.accel.tolist())
        return math.isfinite(total)


@dataclass(frozen=True, slots=True)
class SpeedSample:
    """Signed ground speed (m/s; negative = reverse) from ISO 11783 GBSD/WBSD/CCVS1.

    ``valid`` is False when the sensor reported an error or "not available" in the speed or
    the direction field: then ``speed_mps`` is NaN and must not be used as a number.
    """

    t: float
    speed_mps: float
    valid: bool = True
    source: str = "ground"  # "ground" (GBSD, PGN 65097), "wheel" (WBSD), "ccvs1" (PGN 65265)
    distance_m: float | None = None
    source_address: int | None = None
    reason: str = ""  # why it is invalid, as the sensor said it ("not available (0xFFFF)")
    message: str = ""  # the message it came in: GBSD, WBSD, CCVS1
    direction_known: bool = True  # False: an unsigned speed (CCVS1) not yet signed

    def __post_init__(self) -> None:
        if self.valid and not np.isfinite(self.speed_mps):
            raise ValueError("a valid speed sample needs a finite speed")

    def invalid_detail(self) -> str:
        """What a halt says about an invalid speed: ``speed sensor reports not available
        (GBSD from 0x47)``."""
        sa = "" if self.source_address is None else f" from 0x{self.source_address:02X}"
        return f"speed sensor reports {self.reason} ({self.message}{sa})"


@dataclass(frozen=True, slots=True)
class FrameSample:
    """One camera frame (8-bit, grey or BGR) with its capture time."""

    t: float
    image: NDArray[np.uint8]
    sequence: int = 0
    device_time_s: float | None = None  # V4L2 buffer time, before clock mapping

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.image.shape)


@dataclass(frozen=True, slots=True)
class BearingObservation:
    """Unit bearings (body frame) of identified landmarks seen in one frame at time ``t``."""

    t: float
    ids: NDArray[np.int64]
    bearings: FloatArray
    descriptors: NDArray[np.uint8] | None = field(default=None)

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        bearings = np.asarray(self.bearings, dtype=np.float64).reshape(-1, 3)
        if ids.shape[0] != bearings.shape[0]:
            raise ValueError(
                f"{ids.shape[0]} landmark ids but {bearings.shape[0]} bearings in one observation"
            )
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "bearings", bearings)

    def __len__(self) -> int:
        return int(self.ids.shape[0])


Sample = ImuSample | SpeedSample | FrameSample | BearingObservation
