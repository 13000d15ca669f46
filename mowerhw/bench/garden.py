"""``mowerhw bench --scenario garden``: a whole garden taught in one drive, then both lawns
mowed in turn (issue 17).

The yard is :mod:`mowerhw.sim.garden`: two lawns joined by a path, the dock in the path, a
flower bed across the front lawn's edge. Teach: the operator drives it once and marks, over the
control socket as ``mowerhw ctl teach …`` does, the dock, the path (``nav``), the two lawns
(``area``) and the bed (``keepout``). Mow: the daemon is asked to mow the front lawn only
(``mow --area front``); the mower's own controller drives from the dock through the path
(deck off: TRANSIT) into the front lawn and covers it; part-way, the bench asks for the back
lawn (``mow --area back``: the same localizer goes on), and the controller drives through the
path into the back lawn and covers that. The controller steers by the daemon's status frame
only, never the truth; its route (a few waypoints through the path) is what an integrator
would program.

Scored against the truth (each zone's true outline is the track the operator drove around
it): ``missed_halts`` against the lawn being mowed at the time (minus the bed), keep-out
entries with the deck running, the time the daemon said TRANSIT, the false-halt fraction,
each taught zone against its track, coverage of each lawn, and a figure of the run.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import shapely

from mowerhw.bench.hil import Bench, _boundary_errors
from mowerhw.common.geometry import wrap_angle
from mowerhw.runtime.control_protocol import request

#: the share of the mowing time spent on the front lawn before the bench asks for the back one
FRONT_SHARE = 0.45
#: scoring against the back lawn starts this long after the daemon acknowledged the switch
#: (its next decision reaching the mower's controller on CAN); in between neither a running
#: nor a stopped deck is scored (the switch is in flight). How long the deck really ran on
#: after the switch is measured apart.
SWITCH_GRACE_S = 0.1
WAYPOINT_REACHED_M = 0.35
COVERAGE_CELL_M = 0.5


class RouteThenCover:
    """The mower's controller in the garden: drive a route of waypoints (deck off, whatever the
    state but UNKNOWN), then cover a lawn with bang-bang edge turns. Steers by the estimate."""

    def __init__(self, seed: int, speed_mps: float = 0.45) -> None:
        self.rng = np.random.default_rng([seed, 31])
        self.speed = speed_mps
        self.route: list[np.ndarray] = []
        self.cover: Any = None  # BangBangMower of the lawn being covered
        self.phase = "wait"
        self.lawn = ""

    def go(self, lawn: str, route: list[np.ndarray], inward: Any) -> None:
        from mowerhw.sim.controller import BangBangMower

        self.route = list(route)
        self.lawn = lawn
        self.cover = BangBangMower(inward, self.rng, speed_mps=self.speed, start_after_s=0.0)
        self.phase = "route"

    def command(
        self, t: float, x: float, y: float, yaw: float, state: str, deck: bool
    ) -> tuple[float, float]:
        if state == "UNKNOWN" or self.phase == "wait":
            return 0.0, 0.0
        if self.phase == "route":
            while self.route and math.hypot(*(self.route[0] - (x, y))) < WAYPOINT_REACHED_M:
                self.route.pop(0)
            if not self.route:
                self.phase = "cover"
            else:
                d = self.route[0] - (x, y)
                err = wrap_angle(math.atan2(d[1], d[0]) - yaw)
                if abs(err) > 0.35:
                    return 0.0, float(np.clip(2.0 * err, -0.8, 0.8))
                return 0.4, float(np.clip(1.5 * err, -0.5, 0.5))
        # covering: TRANSIT means past the lawn's edge (into the path): turn as at OUTSIDE
        if state == "TRANSIT":
            state = "OUTSIDE"
        if not deck and state not in ("NEAR_EDGE", "OUTSIDE"):
            state = "UNKNOWN"  # halted for another reason: stand
        return self.cover.command(t, x, y, yaw, state)


class GardenBench(Bench):
    """One garden bench run (see the module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs["scenario"] = "garden"
        super().__init__(**kwargs)
        self.transit_s = 0.0
        self.state_s: dict[str, float] = {}
        self.switch_at: float | None = None  # host time the back lawn was asked for
        self.mark_replies: list[dict[str, Any]] = []

    # ------------------------------------------------------------------------------ teach

    def _teach_truth(self, world: Any) -> Any:
        from mowerhw.sim.garden import garden_drive

        sc = world.scenario
        drive = garden_drive(sc.speed_mps, sc.camera_height_m, standstill_s=1.0)
        self.marks = drive.marks
        return drive.truth

    def _drive_teach(self, truth: Any) -> None:
        """The operator's marks, each while the mower stands at it."""
        t0 = self.mower.teach_t0
        for at, kind, name in self.marks:
            delay = t0 + at - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            words = [kind, name] if name else [kind]
            reply = request(self.sock, "teach", timeout=5.0, args=words)
            self.mark_replies.append({"mark": " ".join(words), **reply})
            if not reply.get("ok"):
                raise RuntimeError(f"the daemon refused teach {' '.join(words)}: {reply}")
        super()._drive_teach(truth)

    def _true_zone(self, name: str) -> np.ndarray:
        from mowerhw.sim.garden import zone_outline

        return np.asarray(self.mower.true_outline(zone_outline(name)))

    def _teach_scores(self, world: Any, lawn_map: Any) -> dict[str, Any]:
        """Each taught zone against the track driven around it; the dock against the truth."""
        taught = {a.name: a.polygon for a in lawn_map.all_areas()}
        taught.update({k.name: k.polygon for k in lawn_map.keepouts})
        zones: dict[str, dict[str, float] | None] = {}
        for name in ("front", "back", "path", "bed"):
            if name not in taught:
                zones[name] = None
                continue
            true = self._true_zone(name)
            err = _boundary_errors(taught[name], true)
            zones[name] = {
                "rmse_m": round(float(np.sqrt(np.mean(err**2))), 4),
                "max_m": round(float(err.max()), 4),
                "area_m2": round(float(shapely.Polygon(taught[name]).area), 2),
                "true_area_m2": round(float(shapely.Polygon(true).area), 2),
            }
        dock = np.asarray(lawn_map.dock_position, dtype=np.float64)[:2]
        return {
            "zones": zones,
            "dock_error_m": round(float(np.hypot(*dock)), 4),  # the drive began on the dock
            "marks": [r["mark"] for r in self.mark_replies],
        }

    # -------------------------------------------------------------------------------- mow

    def _route(self, lawn: str) -> list[np.ndarray]:
        from mowerhw.sim.garden import ROUTES

        return list(self.mower.true_outline(np.asarray(ROUTES[lawn], dtype=np.float64)))

    def _mow_driver(self, lawn_map: Any) -> Any:
        from mowerhw.mow import LawnGeometry

        self.lawn_map = lawn_map
        self.garden_ctl = plan = RouteThenCover(self.seed)
        self.inward = {
            name: LawnGeometry.of_map(lawn_map, (name,)).inward_direction
            for name in ("front", "back")
        }
        plan.go("front", self._route("front"), self.inward["front"])
        ctl = self.controller
        last: list[float | None] = [None]

        def drive(now: float, _xy: Any, _yaw: float) -> tuple[float, float]:
            st = ctl.state.status
            before = last[0]
            if before is not None and st is not None:
                dt = now - before
                self.state_s[st.state] = self.state_s.get(st.state, 0.0) + dt
            last[0] = now
            if st is None or ctl.why_not(now) in ("ISB timeout", "heartbeat timeout"):
                return 0.0, 0.0  # the daemon is silent: stand
            if not math.isfinite(st.x_m) or not math.isfinite(st.heading_rad):
                return 0.0, 0.0
            v, w = plan.command(
                now - self.t_mow0, st.x_m, st.y_m, st.heading_rad, st.state, ctl.deck_running
            )
            return float(v), float(w)

        return drive

    def _mow_request(self) -> dict[str, Any]:
        return {"areas": ["front"]}

    def _mow_tick(self, now: float) -> None:
        if self.switch_at is None and now - self.t_mow0 >= FRONT_SHARE * self.duration_s:
            reply = request(self.sock, "mow", timeout=10.0, areas=["back"])
            if not reply.get("ok"):
                raise RuntimeError(f"the daemon refused mow --area back: {reply}")
            self.switch_at = time.monotonic()  # acknowledged: the daemon mows back only now
            self.garden_ctl.go("back", self._route("back"), self.inward["back"])

    def _regions(self) -> tuple[Any, Any, Any]:
        """True front lawn minus the bed, true back lawn, true bed (shapely, world frame)."""
        bed = shapely.Polygon(self._true_zone("bed"))
        front = shapely.Polygon(self._true_zone("front")).difference(bed)
        back = shapely.Polygon(self._true_zone("back")).difference(bed)
        return front, back, bed

    def _scoring_switch(self) -> float:
        return self.switch_at + SWITCH_GRACE_S if self.switch_at is not None else math.inf

    def _true_signed_distance(self, world: Any, t: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """Against the lawn being mowed at the time (the front one, then the back one)."""
        front, back, _ = self._regions()
        switch = self._scoring_switch()
        pts = shapely.points(xy)
        out = np.empty(len(xy))
        for region, sel in ((front, t < switch - SWITCH_GRACE_S), (back, t >= switch)):
            d = shapely.distance(region.boundary, pts[sel])
            out[sel] = np.where(shapely.contains(region, pts[sel]), d, -d)
        out[(t >= switch - SWITCH_GRACE_S) & (t < switch)] = np.nan  # not scored (in flight)
        return out

    def _score_mow(  # type: ignore[no-untyped-def]
        self, world, t_mow0, windows, latencies, mow_s
    ) -> dict[str, Any]:
        metrics = super()._score_mow(world, t_mow0, windows, latencies, mow_s)
        log_arr = self.mower.log_array()
        sel = log_arr[:, 6] == 2
        t, xy, deck = log_arr[sel, 0], log_arr[sel, 1:3], log_arr[sel, 5] > 0
        front, back, bed = self._regions()
        pts = shapely.points(xy)
        depth_in_bed = np.where(
            shapely.contains(bed, pts), shapely.distance(bed.boundary, pts), -np.inf
        )
        in_bed = deck & (depth_in_bed > 0.10)
        entries = int(np.count_nonzero(in_bed[1:] & ~in_bed[:-1]) + int(in_bed[:1].sum()))
        dt = 1.0 / self.mower.STEP_HZ
        switch = self.switch_at if self.switch_at is not None else math.inf
        after = (t >= switch) & ~deck
        ran_on = float(t[np.argmax(after)] - switch) if after.any() else None
        metrics["garden"] = {
            "keepout_entries_while_permitted": entries,
            "keepout_steps_permitted_any_depth": int(np.count_nonzero(deck & (depth_in_bed > 0))),
            "time_in_transit_s": round(self.state_s.get("TRANSIT", 0.0), 1),
            "time_by_state_s": {k: round(v, 1) for k, v in sorted(self.state_s.items())},
            "back_lawn_asked_at_s": round(switch - t_mow0, 1) if math.isfinite(switch) else None,
            # acknowledged → the deck stopped in the front lawn, now transit (as the truth saw)
            "deck_ran_on_after_switch_ms": round(1e3 * ran_on, 1) if ran_on is not None else None,
            "mowing_s": {
                "front": round(float(np.count_nonzero(deck & (t < switch))) * dt, 1),
                "back": round(float(np.count_nonzero(deck & (t >= switch))) * dt, 1),
            },
            "coverage": {
                "front": _coverage(front, xy[deck & (t < switch)]),
                "back": _coverage(back, xy[deck & (t >= switch)]),
            },
            "time_truly_in_path_only_s": round(
                float(
                    np.count_nonzero(
                        shapely.contains(shapely.Polygon(self._true_zone("path")), pts)
                        & ~shapely.contains(front, pts)
                        & ~shapely.contains(back, pts)
                    )
                )
                * dt,
                1,
            ),
        }
        png = self.out / "garden-run.png"
        _figure(png, self, t, xy, deck, switch - t_mow0 if math.isfinite(switch) else None)
        metrics["garden"]["figure"] = str(png)
        return metrics


def _coverage(region: Any, xy: np.ndarray) -> float:
    """Share of the region's cells (COVERAGE_CELL_M squares, centre inside) the mower's centre
    passed with the deck running."""
    minx, miny, maxx, maxy = region.bounds
    gx = np.arange(minx + COVERAGE_CELL_M / 2, maxx, COVERAGE_CELL_M)
    gy = np.arange(miny + COVERAGE_CELL_M / 2, maxy, COVERAGE_CELL_M)
    cx, cy = np.meshgrid(gx, gy)
    inside = shapely.contains_xy(region, cx, cy)
    if not inside.any():
        return 0.0
    hit = np.zeros_like(inside)
    if len(xy):
        i = np.clip(((xy[:, 1] - miny) // COVERAGE_CELL_M).astype(int), 0, len(gy) - 1)
        j = np.clip(((xy[:, 0] - minx) // COVERAGE_CELL_M).astype(int), 0, len(gx) - 1)
        hit[i, j] = True
    return round(float(np.count_nonzero(hit & inside) / np.count_nonzero(inside)), 3)


def _figure(
    path: Any,
    bench: GardenBench,
    t: np.ndarray,
    xy: np.ndarray,
    deck: np.ndarray,
    switch_s: float | None,
) -> None:
    """The run: true zones (thin), taught zones (dashed), the mower's path with the deck
    running (green) or halted (grey), the dock."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, ax = plt.subplots(figsize=(11, 4.8), dpi=110)
    colours = {"mow": "tab:green", "nav": "tab:blue", "keepout": "tab:red"}
    taught = [(a.kind, a.name, a.polygon) for a in bench.lawn_map.all_areas()]
    taught += [("keepout", k.name, k.polygon) for k in bench.lawn_map.keepouts]
    for kind, name, poly in taught:
        ring = np.vstack([poly, poly[:1]])
        ax.plot(ring[:, 0], ring[:, 1], "--", color=colours[kind], lw=1.4, label=f"taught {name}")
    for name in ("front", "back", "path", "bed"):
        ring = bench._true_zone(name)
        ring = np.vstack([ring, ring[:1]])
        ax.plot(ring[:, 0], ring[:, 1], "-", color="k", lw=0.5)
    ax.plot(xy[~deck, 0], xy[~deck, 1], ".", ms=1.0, color="0.55", label="deck halted")
    ax.plot(xy[deck, 0], xy[deck, 1], ".", ms=1.0, color="tab:olive", label="deck running")
    for _, name, poly in taught:
        c = shapely.Polygon(poly).representative_point()
        ax.annotate(name, (c.x, c.y), fontsize=8, color="k", ha="center", alpha=0.8)
    dock = np.asarray(bench.lawn_map.dock_position)[:2]
    ax.plot(dock[0], dock[1], "ks", ms=6, label="dock")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, taught world frame)")
    ax.set_ylabel("y (m)")
    title = "garden bench: teach once, mow front then back"
    if switch_s is not None:
        title += f" (back asked for at {switch_s:.0f} s)"
    ax.set_title(title + "; thin black: true tracks")
    legend = ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)
    for handle in legend.legend_handles:  # the path's dots drawn visibly in the legend
        if isinstance(handle, Line2D) and handle.get_marker() == ".":
            handle.set_markersize(8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
