"""What the page may ask of the daemon, checked before it is forwarded (issue 19).

A control request is ``POST /api/command`` with ``Authorization: Bearer <token>`` and a JSON
body ``{"cmd": "mow", "areas": ["front"]}``. Only the commands an operator needs from the
page are allowed; everything else in the control socket (saving maps, fault injection, the
status) is not reachable from the page's controls.
"""

from __future__ import annotations

import json
from typing import Any

from mowerhw.common.strictjson import unique_keys

#: the page's controls and what each is forwarded as
CONTROLS = ("teach", "mow", "idle", "finish-teach")
#: the largest request body (bytes)
MAX_BODY_BYTES = 1024
#: at most this many areas, each name at most this long
MAX_AREAS, MAX_NAME = 32, 64


class CommandError(ValueError):
    """A malformed request; the message says what is allowed."""


def parse_command(body: bytes) -> dict[str, Any]:
    """The control request to forward (``{"cmd": ..., "areas": [...]}``), or CommandError."""
    if len(body) > MAX_BODY_BYTES:
        raise CommandError(f"request of {len(body)} bytes; at most {MAX_BODY_BYTES} allowed")
    try:
        req = json.loads(
            body.decode("utf-8"), object_pairs_hook=unique_keys, parse_constant=_no_constant
        )
    except UnicodeDecodeError:
        raise CommandError("request is not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise CommandError(f"request is not valid JSON ({exc.msg} at column {exc.colno})") from None
    except CommandError:
        raise
    except ValueError as exc:  # a duplicate key
        raise CommandError(f"request is not valid: {exc}") from None
    if not isinstance(req, dict):
        raise CommandError('request must be a JSON object like {"cmd": "mow"}')
    cmd = req.get("cmd")
    if cmd not in CONTROLS:
        shown = repr(cmd)[:40] if isinstance(cmd, str) else "missing"
        raise CommandError(f"unknown command {shown}; allowed: {', '.join(CONTROLS)}")
    extra = sorted(set(req) - {"cmd", "areas"})
    if extra:
        raise CommandError(f"unknown field {extra[0][:40]!r}; allowed: cmd, areas (mow only)")
    out: dict[str, Any] = {"cmd": cmd}
    if "areas" in req:
        areas = req["areas"]
        if cmd != "mow":
            raise CommandError("areas: only with mow")
        if (
            not isinstance(areas, list)
            or not 1 <= len(areas) <= MAX_AREAS
            or not all(isinstance(a, str) and 0 < len(a) <= MAX_NAME for a in areas)
        ):
            raise CommandError(
                f"areas: a list of 1 to {MAX_AREAS} mowing area names of at most {MAX_NAME} "
                "characters"
            )
        out["areas"] = areas
    return out


def _no_constant(name: str) -> Any:
    raise CommandError(f"request is not valid JSON ({name} is not a number JSON allows)")
