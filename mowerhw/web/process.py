"""The page's process, as the permit supervisor runs it (``web.enabled``).

The page is outside the safety chain: it reads the daemon through the control socket and
nothing reads it. So, unlike the estimation process, its death does not end the service: it
is said in the log and the process is started again after a backoff (1 s, doubling to 60 s);
a configuration it cannot use (the token file) is said once and not retried. Nothing here
imports aiohttp: the supervisor stays small.
"""

from __future__ import annotations

import logging
import multiprocessing
from collections.abc import Callable
from typing import Any

from mowerhw.config import EX_CONFIG, Config

log = logging.getLogger("mowerhw.web")

MAX_BACKOFF_S = 60.0


class WebProcess:
    """Start, watch and stop the page's process."""

    def __init__(self, config: Config, target: Callable[[Config, int], None]) -> None:
        self.cfg = config
        self.target = target  # the process's entry point (the supervisor's web_child_main)
        self.proc: Any = None
        self.starts = 0
        self.deaths = 0
        self._backoff = 1.0
        self._restart_at: float | None = None
        self.given_up = ""
        self._next_check = 0.0

    def start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.proc = ctx.Process(
            target=self.target,
            args=(self.cfg, logging.getLogger().level),
            name="mowerhw-web",
            daemon=True,
        )
        self.proc.start()
        self.starts += 1
        log.info("status page process started (pid %d)", self.proc.pid)

    def check(self, now: float) -> None:
        """Called from the supervisor's loop: notice a dead page, start it again later."""
        if self.given_up or now < self._next_check:
            return
        self._next_check = now + 1.0  # a look a second is plenty (a waitpid each)
        if self._restart_at is not None:
            if now >= self._restart_at:
                self._restart_at = None
                self.start()
            return
        if self.proc is None or self.proc.is_alive():
            return
        self.proc.join(timeout=0.1)
        code = self.proc.exitcode
        self.deaths += 1
        if code == EX_CONFIG:
            self.given_up = f"exit status {code}: its configuration cannot be used"
            log.error("the status page process ended (%s); not restarted", self.given_up)
            return
        log.error(
            "the status page process died (exit code %s); starting it again in %.0f s "
            "(mowing is not affected)",
            code,
            self._backoff,
        )
        self._restart_at = now + self._backoff
        self._backoff = min(MAX_BACKOFF_S, 2.0 * self._backoff)

    def stop(self) -> None:
        if self.proc is not None and self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(timeout=2.0)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(timeout=1.0)

    def status(self) -> dict[str, Any]:
        alive = self.proc is not None and self.proc.is_alive()
        pid = self.proc.pid if alive else None
        return {"alive": alive, "pid": pid, "starts": self.starts, "deaths": self.deaths}
