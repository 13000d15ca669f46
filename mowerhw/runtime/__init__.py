"""The on-board runtime (docs/design.md §8): the asyncio daemon that wires drivers to estimators.

* :mod:`.pipelines` — teach and mow estimator chains fed sample by sample (no I/O);
* :mod:`.gate` — the fail-safe permit decision: every condition, one reason;
* :mod:`.control` — the control socket (JSON lines over a Unix socket) and its client;
* :mod:`.sdnotify` — systemd's notify protocol (READY, STATUS, WATCHDOG);
* :mod:`.daemon` — the event loop: device tasks, estimator loop, permit sender, watchdog.
"""
