"""The control socket's commands (``mowerhw ctl``): what each does to a running daemon, and
the errors that name what is allowed."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Protocol

from mowerhw.config import Config
from mowerhw.map import MapError
from mowerhw.runtime.core import MODES, RuntimeCore
from mowerhw.runtime.pipelines import MowPipeline, TeachPipeline


class Controllable(Protocol):
    """What the commands need of the daemon."""

    cfg: Config
    core: RuntimeCore
    link: Any
    estimator_delay_s: float

    async def set_mode(
        self, mode: str, mow_areas: tuple[str, ...] | None = None
    ) -> dict[str, Any]: ...
    async def finish_teach(self) -> dict[str, Any]: ...
    async def save_map(self, path: Path) -> None: ...
    def status(self) -> dict[str, Any]: ...
    def live(self, since: int, landmarks: bool) -> dict[str, Any]: ...


async def handle_command(d: Controllable, cmd: str, args: dict[str, Any]) -> dict[str, Any]:
    """The reply to one command: ``{"ok": true, ...}`` or ``{"ok": false, "error": ...}``."""
    if cmd == "status":
        return {"ok": True, **d.status()}
    if cmd == "live":  # the status page (issue 19)
        since, landmarks = args.get("since", 0), args.get("landmarks", False)
        if not isinstance(since, int) or isinstance(since, bool) or not 0 <= since < 2**53:
            return {"ok": False, "error": "since: a trajectory index, an integer >= 0"}
        if not isinstance(landmarks, bool):
            return {"ok": False, "error": "landmarks: true or false"}
        return {"ok": True, **d.live(since, landmarks)}
    if cmd == "teach" and args.get("args"):  # ctl teach area NAME | keepout NAME | ... | dock
        words = [str(a) for a in args["args"]]
        if len(words) > 2:
            return {"ok": False, "error": "teach marks take a kind and at most one name"}
        problem = d.core.teach_mark(words[0], words[1] if len(words) > 1 else "")
        return {"ok": False, "error": problem} if problem else {"ok": True, "marked": words}
    if cmd in MODES:
        areas = args.get("areas")
        if areas is not None and (
            not isinstance(areas, list) or not areas or not all(isinstance(a, str) for a in areas)
        ):
            return {"ok": False, "error": "areas: a list of mowing area names"}
        return await d.set_mode(cmd, tuple(areas) if areas is not None else None)
    if cmd == "finish-teach":
        return await d.finish_teach()
    if cmd == "save-map":
        return await _save_map(d, args)
    if cmd == "fault":
        if not d.cfg.runtime.fault_injection:
            return {"ok": False, "error": "fault injection is off (runtime.fault_injection)"}
        words = [str(a) for a in (args.get("args") or [])]
        kind = str(args.get("kind") or (words or [""])[0])
        if kind == "can-down":  # the supervisor's CAN interface, taken away for a while
            if d.link is None:
                return {"ok": False, "error": "can-down needs the permit supervisor"}
            seconds = float(args.get("seconds") or (words[1:] or ["3"])[0])
            d.link.send(("fault", {"kind": kind, "seconds": seconds}))
            return {"ok": True, "injected": kind, "seconds": seconds}
        if kind == "estimator-delay":  # a slow estimator: blocked this long every 200 ms
            ms = float(args.get("ms") or (words[1:] or ["0"])[0])
            d.estimator_delay_s = max(0.0, ms) / 1e3
            return {"ok": True, "injected": kind, "ms": ms}
        problem = d.core.inject(kind)
        return {"ok": False, "error": problem} if problem else {"ok": True, "injected": kind}
    return {"ok": False, "error": f"unknown command {cmd!r}"}


async def _save_map(d: Controllable, args: dict[str, Any]) -> dict[str, Any]:
    if d.core.mode == "teach" and d.core.teach_state == "recording":
        return await d.finish_teach()
    target = args.get("path") or (args.get("args") or [None])[0]
    if d.core.map is None:
        return {"ok": False, "error": "no map loaded (mow mode loads one; teach makes one)"}
    try:
        path = map_save_path(Path(d.cfg.map.path), target)
    except ValueError as exc:
        return {"ok": False, "error": str(exc)}
    try:
        await d.save_map(path)
    except (MapError, OSError) as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "map": str(path)}


def map_save_path(map_path: Path, target: Any) -> Path:
    """Where ``save-map [target]`` may write: the configured map, or a ``.json`` file in its
    directory (relative names are taken there); ValueError naming the rule otherwise."""
    if target is None or target == "":
        return map_path
    if not isinstance(target, str) or "\0" in target or len(target) > 255:
        raise ValueError("save-map: the path must be a file name of at most 255 characters")
    folder = map_path.parent.resolve()
    path = (folder / target).resolve()
    if path.suffix != ".json" or path.parent != folder or path.name.startswith("."):
        raise ValueError(
            f"save-map: {target!r} is not allowed; maps are saved as NAME.json in the map "
            f"directory {folder}"
        )
    return path


def core_status(core: RuntimeCore, now: float) -> dict[str, Any]:
    """The core's part of the status command."""
    d = core.decision
    pipe = core.pipeline
    out: dict[str, Any] = {
        "mode": core.mode,
        "mow_areas": list(core.mow_areas) if core.mow_areas is not None else None,
        "permit": d.permit,
        "state": str(d.state),
        "reason": d.reason,
        "detail": d.detail,
        "signed_distance_m": None if math.isnan(d.signed_distance_m) else d.signed_distance_m,
        "sensor_age_s": {
            k: (None if v is None else round(now - v, 4)) for k, v in core.last_arrival.items()
        },
        "counts": dict(core.counts),
        "map_problem": core.map_problem,
        "fault": core.fault,
        "teach": {"state": core.teach_state, **core.last_teach},
        "halt_latencies": [vars(h) for h in core.halt_latencies[-200:]],
    }
    if isinstance(pipe, MowPipeline):
        t, x, y, h, sig = pipe.pose()
        out["pose"] = {"t": t, "x": x, "y": y, "heading": h, "sigma_xy_m": sig}
        out["localizer"] = pipe.status()
    elif isinstance(pipe, TeachPipeline):
        out["teach"].update(pipe.status())
    return out
