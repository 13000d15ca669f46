"""The estimation process: the daemon (:class:`mowerhw.runtime.daemon.Daemon`) with its
decisions going to the supervisor as leases, its ground speed coming from it."""

from __future__ import annotations

import asyncio
import logging
import os
from multiprocessing.connection import Connection
from pathlib import Path

from mowerhw.config import Config
from mowerhw.supervisor.link import SupervisorLink


def estimator_main(
    config: Config, mode: str | None, record: Path | None, conn: Connection, log_level: int
) -> None:
    """Entry point of the spawned estimation process."""
    from mowerhw.runtime.process import die_with_parent

    die_with_parent()
    os.environ.pop("NOTIFY_SOCKET", None)  # only the supervisor talks to systemd
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from mowerhw.runtime.daemon import Daemon
    from mowerhw.runtime.process import tune_process
    from mowerhw.supervisor.process import set_priority

    set_priority(config.supervisor.estimation_nice, "the estimation process")
    tune_process()
    daemon = Daemon(config, mode, record, link=SupervisorLink(conn))
    raise SystemExit(asyncio.run(daemon.run()))
