"""JSON read with limits, for input nobody here wrote (maps, control requests): a number of
thousands of digits, a key given twice or NaN are refused by name, not parsed into something
else (docs/design.md §8, "Untrusted input")."""

from __future__ import annotations

from typing import Any


class JsonLimitError(ValueError):
    """A JSON document outside the limits (the message says which)."""


def unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook``: an object, or :class:`JsonLimitError` for a key given twice
    (``json`` would keep the last one silently: ``{"cmd": "status", "cmd": "mow"}``)."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise JsonLimitError(f"the key {key[:40]!r} appears twice in one object")
        out[key] = value
    return out


def bounded_int(text: str) -> int:
    """``parse_int``: integers that fit in 64 bits (19 digits), no more."""
    if len(text.lstrip("-")) > 19:
        raise JsonLimitError(f"an integer of {len(text)} digits; at most 19 (64-bit) allowed")
    return int(text)


def no_constant(text: str) -> Any:
    """``parse_constant``: NaN and the infinities are no numbers here."""
    raise JsonLimitError(f"{text} is not an allowed number")


def finite(value: Any) -> Any:
    """``value`` ready for strict JSON: NaN and the infinities become null (JSON has no such
    numbers, and strict readers refuse them), numpy scalars and arrays plain Python."""
    import math

    import numpy as np

    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    if isinstance(value, np.ndarray):
        return finite(value.tolist())
    return value
