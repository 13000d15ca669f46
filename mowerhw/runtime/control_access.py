"""Who may use the control socket, and which daemon owns it (docs/design.md §8).

Who may do what comes from the peer's credentials (SO_PEERCRED): ``status`` for anyone who
can open the socket (its mode and group), everything else only for the service's own user,
root, or members of ``runtime.control_group``. Only one daemon serves a control socket:
:func:`claim_control_socket` takes a lock beside it.
"""

from __future__ import annotations

import contextlib
import fcntl
import grp
import os
import pwd
import socket
import stat
import struct
from dataclasses import dataclass
from pathlib import Path


class ControlSocketBusy(RuntimeError):
    """Another daemon serves this control socket."""


@dataclass(frozen=True)
class Peer:
    """Who is at the other end of a connection (SO_PEERCRED)."""

    pid: int
    uid: int
    gid: int

    @classmethod
    def of(cls, conn: socket.socket) -> Peer:
        raw = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        pid, uid, gid = struct.unpack("3i", raw)
        return cls(pid, uid, gid)


@dataclass(frozen=True)
class ControlPolicy:
    """Limits and authorization of the control socket (``runtime.control_*`` keys)."""

    max_clients: int = 8
    idle_s: float = 60.0
    requests_per_s: float = 20.0
    group: str | None = None

    def may_change(self, peer: Peer) -> bool:
        """Commands that change the mode or write files: the service user, root, or a member
        (primary or supplementary, from the user database) of ``group``."""
        if peer.uid in (0, os.geteuid()):
            return True
        if self.group is None:
            return False
        try:
            gid = grp.getgrnam(self.group).gr_gid
            user = pwd.getpwuid(peer.uid).pw_name
            return gid == peer.gid or gid in os.getgrouplist(user, peer.gid)
        except (KeyError, OSError):
            return False

    def refusal(self, cmd: str, peer: Peer) -> str:
        who = f"uid {peer.uid}"
        allowed = "the service's user, root" + (
            f" or members of group {self.group!r}" if self.group else ""
        )
        return f"{cmd}: not allowed for {who}; commands that change the mower need {allowed}"


def listen_unix(path: Path, mode: int, backlog: int = 64) -> socket.socket:
    """A non-blocking Unix stream socket listening at ``path`` with file mode ``mode``. A
    socket left there by a dead daemon is replaced (the caller holds the control socket's
    lock: no live daemon serves it); anything else there is refused (OSError)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.suppress(FileNotFoundError):
        if not stat.S_ISSOCK(path.lstat().st_mode):
            raise OSError(f"{path} exists and is not a socket: refusing to replace it")
        path.unlink()
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(path))
        os.chmod(path, mode)
        sock.listen(backlog)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


def claim_control_socket(path: str | Path) -> int:
    """Lock ``<socket>.lock`` for this process's life (the descriptor is returned and must be
    kept open); :class:`ControlSocketBusy` naming the holder if another daemon has it."""
    lock = Path(str(path) + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise ControlSocketBusy(
            f"another mowerhw daemon (pid {holder}) serves the control socket {path}; stop it "
            "first, or give this one its own runtime.control_socket"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd
