"""The permit supervisor's status socket (docs/design.md §8): what a client hears from the
supervisor when the estimation process, which serves the control socket, does not answer.

The supervisor listens on ``<runtime.control_socket>.supervisor``. A client connects and
reads: the supervisor writes one JSON object (strict JSON, one line) and closes; it reads
nothing, so no request can be malformed. Read-only: the permit, the halt reason, the lease's
age and the estimation process's state (alive, ready, how long it has been silent).
``mowerhw ctl``, the status page and the bench ask it when the control socket is silent.
Here: its path, reading its reply and wording it (the status page may not import the
supervisor); the server and the blocking client are in :mod:`mowerhw.supervisor.status_socket`,
the page's own client in :mod:`mowerhw.web.feed`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mowerhw.common.strictjson import no_constant, unique_keys
from mowerhw.common.unreachable import unreachable

#: the status socket's path is the control socket's with this added
SUFFIX = ".supervisor"
#: the longest reply a client reads (the supervisor's status is about 1.5 kB)
MAX_REPLY_BYTES = 65536
#: an estimation process silent this long is said to be so (it leases every 20–40 ms)
QUIET_S = 0.5


def supervisor_socket(control_socket: str | Path) -> Path:
    """Where the permit supervisor of the daemon serving ``control_socket`` answers."""
    return Path(str(control_socket) + SUFFIX)


def parse_reply(raw: bytes, path: Path) -> dict[str, Any]:
    """The supervisor's reply read from ``path``: ConnectionError when there was none,
    ValueError when it is not one strict-JSON object of at most :data:`MAX_REPLY_BYTES`."""
    if not raw:
        raise ConnectionError(f"{path}: the supervisor closed the connection without a reply")
    if len(raw) > MAX_REPLY_BYTES:
        raise ValueError(f"{path}: a reply over {MAX_REPLY_BYTES} bytes")
    # strict: the supervisor writes strict JSON, so anything else is not its reply
    try:
        reply = json.loads(raw, parse_constant=no_constant, object_pairs_hook=unique_keys)
    except RecursionError:
        raise ValueError(f"{path}: the reply is nested too deep") from None
    if not isinstance(reply, dict):
        raise ValueError(f"{path}: the reply is not a JSON object")
    return reply


def supervisor_unreachable(exc: BaseException) -> str:
    """Why the supervisor's status socket gave no reply, in an operator's words."""
    if isinstance(exc, FileNotFoundError):
        return (
            "no such socket: the daemon is not running, or runs without a permit supervisor "
            "(supervisor.enabled false)"
        )
    if isinstance(exc, TimeoutError):
        return "no reply in time: the supervisor answers at once unless it is stopped"
    return unreachable(exc)


def describe(status: dict[str, Any]) -> str:
    """The supervisor's status in one sentence for an operator: the deck, why, and the
    estimation process."""
    reason = status.get("reason") or ""
    detail = status.get("detail") or ""
    why = f"{reason}: {detail}" if reason and detail else reason or detail
    deck = "permits mowing" if status.get("permit") else "holds the deck halted"
    said = f"the permit supervisor {deck}" + (f" ({why})" if why else "")
    est = status.get("estimation")
    if isinstance(est, dict):
        pid = est.get("pid")
        who = f"the estimation process (pid {pid})" if pid else "the estimation process"
        silent = est.get("silent_s")
        if not est.get("alive"):
            said += f"; {who} is not running"
        elif not est.get("ready"):
            said += f"; {who} is starting"
        elif isinstance(silent, int | float) and silent >= QUIET_S:
            said += f"; {who} has sent nothing for {silent:.1f} s"
        else:
            said += f"; {who} is running"
    return said
