"""Why a client of the control socket got no reply, in the words an operator needs. The
daemon serves the socket; its clients — ``mowerhw ctl`` and the status page's process, which
must not import the runtime — word their failures with this one function."""

from __future__ import annotations


def unreachable(exc: BaseException, timeout: float | None = None) -> str:
    """Why a client got no reply on the control socket, in the words an operator needs:
    which of the usual causes it is and where to look (the CLI and the status page)."""
    if isinstance(exc, TimeoutError):
        within = f" within {timeout:g} s" if timeout is not None else " in time"
        return (
            f"no reply{within}: the daemon's estimation process is busy or stalled (the "
            "permit supervisor halts the deck once its lease runs out); its log says more"
        )
    if isinstance(exc, FileNotFoundError):
        return "no such socket: the daemon is not running with this config (or not yet)"
    if isinstance(exc, ConnectionRefusedError):
        return "nothing listens on it: the daemon is not running, or is restarting"
    if isinstance(exc, PermissionError):
        return (
            "no permission to open it (runtime.socket_mode: the service's user and "
            "the socket's group only)"
        )
    return str(exc) or type(exc).__name__
