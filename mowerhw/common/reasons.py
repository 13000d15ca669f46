"""The words of a decision: containment states and halt reasons (shared by the estimators,
the runtime, the supervisor and the status frame; importing this costs nothing)."""

from __future__ import annotations

from enum import StrEnum


class State(StrEnum):
    INSIDE = "INSIDE"
    NEAR_EDGE = "NEAR_EDGE"
    OUTSIDE = "OUTSIDE"
    UNKNOWN = "UNKNOWN"
    TRANSIT = "TRANSIT"  # in a navigation area (or a mowing area not chosen): drive, do not cut


class Reason(StrEnum):
    """Why the deck is halted (empty string while permitted)."""

    OUTSIDE = "OUTSIDE"  # beyond the boundary or inside a keep-out zone
    UNCERTAIN = "UNCERTAIN"  # σ above containment.sigma_max_m
    NOT_LOCALIZED = "NOT_LOCALIZED"  # starting, lost, or re-initialising
    SENSOR_STALE = "SENSOR_STALE"  # IMU, speed or camera silent for too long
    FAULT = "FAULT"  # estimator produced NaN / raised; it was reset
    MAP_INVALID = "MAP_INVALID"  # no usable map
    NOT_MOWING = "NOT_MOWING"  # the runtime is not in mow mode
    SHUTTING_DOWN = "SHUTTING_DOWN"
    ESTIMATOR_LATE = "ESTIMATOR_LATE"  # the supervisor holds no fresh permit lease
    LIFTED = "LIFTED"  # lifted, or a lift switch (latched until clear for a while)
    TILTED = "TILTED"  # tilted past the limit, or rolled over
    COLLISION = "COLLISION"  # a bump: an acceleration spike or a bump switch
    TRANSIT = "TRANSIT"  # in a navigation area: the mower may drive there, the deck stays off
