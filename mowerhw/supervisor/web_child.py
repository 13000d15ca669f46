"""The status page's process as the supervisor starts it (``web.enabled``). A module of its
own, importing nothing heavy: the page's process unpickles its entry point from here, and
everything this module imports is in its memory (the estimation side's modules would add
about 80 MB to a process that needs none of them)."""

from __future__ import annotations

from mowerhw.config import Config


def web_child_main(config: Config, log_level: int) -> None:
    """Entry point of the page's process: it dies with the supervisor (a page left behind
    would keep the port from the next one), then serves (:func:`mowerhw.web.server.web_main`)."""
    from mowerhw.runtime.process import die_with_parent

    die_with_parent()
    from mowerhw.web.server import web_main

    web_main(config, log_level)
