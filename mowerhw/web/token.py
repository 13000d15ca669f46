"""The controls' token (``web.token_file``, or the systemd credential ``web-token``)."""

from __future__ import annotations

import contextlib
import hmac
import os
import secrets
from pathlib import Path

#: the name of the systemd credential (LoadCredential=web-token:/path) used when present
CREDENTIAL = "web-token"


class TokenError(RuntimeError):
    """The token cannot be read or created; the message says where and why."""


def token_path(configured: Path) -> Path:
    """Where the token is read from: the systemd credential when the service has one."""
    creds = os.environ.get("CREDENTIALS_DIRECTORY")
    if creds and (Path(creds) / CREDENTIAL).is_file():
        return Path(creds) / CREDENTIAL
    return configured


def load_or_create_token(configured: Path) -> tuple[str, Path]:
    """(token, the file it is in). A missing file is created with a random token, mode 0600,
    atomically (written beside it, then renamed). A file that others may read is refused."""
    path = token_path(configured)
    try:
        st = path.stat()
    except FileNotFoundError:
        return _create(path), path
    except OSError as exc:
        raise TokenError(f"web token {path}: cannot read it ({exc.strerror})") from None
    if st.st_mode & 0o077 and path == configured:
        raise TokenError(
            f"web token {path}: mode {st.st_mode & 0o777:04o} lets others read it; allowed: "
            f"0600 or 0400 (chmod 600 {path})"
        )
    try:
        token = path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise TokenError(f"web token {path}: unreadable ({exc})") from None
    if len(token) < 16 or not token.isprintable() or " " in token:
        raise TokenError(
            f"web token {path}: must be one line of at least 16 printable characters without spaces"
        )
    return token, path


def _create(path: Path) -> str:
    token = secrets.token_urlsafe(32)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(token + "\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise TokenError(f"web token {path}: cannot create it ({exc.strerror})") from None
    return token


def token_matches(given: str | None, token: str) -> bool:
    """Constant-time comparison (no timing hint of how much of a guess was right)."""
    return given is not None and hmac.compare_digest(given.encode(), token.encode())
