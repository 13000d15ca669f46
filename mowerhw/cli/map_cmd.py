"""``mowerhw map check|show|plot|upgrade|add-keepout|remove-keepout|add-area|remove-area|
set-approach|export-geojson|import-geojson|import-openmower``: look at and edit lawn maps."""

from __future__ import annotations

import argparse
import datetime as dt
import math
import shutil
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from shapely.geometry import Polygon

from mowerhw.cli.common import output_file, print_json
from mowerhw.config import EX_CONFIG


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("map", help="check, show, plot and edit lawn maps")
    msub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    check = msub.add_parser("check", help="validate a map (exit 0, or 78 saying what is wrong)")
    check.add_argument("map", type=Path)
    check.set_defaults(handler=_check)
    show = msub.add_parser("show", help="summary: outline, area, keep-outs, landmarks, dock")
    show.add_argument("map", type=Path)
    show.add_argument("--json", action="store_true")
    show.set_defaults(handler=_show)
    plot = msub.add_parser("plot", help="draw a map to a PNG")
    plot.add_argument("map", type=Path)
    plot.add_argument(
        "-o", "--output", type=output_file, help="PNG path (default: next to the map)"
    )
    plot.set_defaults(handler=_plot)
    add = msub.add_parser(
        "add-keepout", help="add a keep-out zone (no re-driving; the old map is kept as a backup)"
    )
    add.add_argument("map", type=Path)
    add.add_argument(
        "--polygon", required=True, help='corners in map metres: "x,y x,y x,y ..." (at least 3)'
    )
    add.add_argument("--name", help="a name for the zone (default: keepout-N)")
    add.set_defaults(handler=_add)
    exp = msub.add_parser(
        "export-geojson",
        help="the outline, keep-outs and dock as GeoJSON (local metres), to edit in QGIS",
    )
    exp.add_argument("map", type=Path)
    exp.add_argument("-o", "--output", type=output_file, help="default: next to the map")
    exp.set_defaults(handler=_export_geojson)
    imp = msub.add_parser(
        "import-geojson",
        help="take the outline and keep-outs from an edited GeoJSON (landmarks kept; backup)",
    )
    imp.add_argument("map", type=Path)
    imp.add_argument("geojson", type=Path)
    imp.set_defaults(handler=_import_geojson)
    om = msub.add_parser(
        "import-openmower",
        help="an OpenMower map's areas, navigation areas and obstacles into a taught map",
        description="Read an OpenMower map backup (its outlines repaired and each repair "
        "said), align it to the taught map by the dock both have (or by --points), and add "
        "its mowing areas (all, or those named with --area), navigation areas and obstacles "
        "to MAP; the taught lawn and the landmarks stay, the old map is kept as a backup.",
    )
    om.add_argument("file", type=Path, help="the OpenMower map backup (JSON)")
    om.add_argument("--into", type=Path, required=True, metavar="MAP")
    om.add_argument(
        "--area", action="append", help="a mowing area to take (name or id; repeat for more)"
    )
    om.add_argument(
        "--points",
        help='reference points instead of the dock: "ox,oy:mx,my ..." (OpenMower → map, 2+)',
    )
    om.set_defaults(handler=_import_openmower)
    for command, what, handler in (
        ("remove-keepout", "a keep-out zone", _remove),
        ("remove-area", "an area", _remove_area),
    ):
        rem = msub.add_parser(command, help=f"remove {what} by name (with a backup)")
        rem.add_argument("map", type=Path)
        rem.add_argument("--name", required=True)
        rem.set_defaults(handler=handler)
    area = msub.add_parser(
        "add-area", help="add a mowing or navigation area (no re-driving; with a backup)"
    )
    area.add_argument("map", type=Path)
    area.add_argument("--name", required=True)
    area.add_argument("--kind", choices=("mow", "nav"), required=True)
    area.add_argument("--polygon", required=True, help='corners in map metres: "x,y x,y x,y ..."')
    area.set_defaults(handler=_add_area)
    way = msub.add_parser(
        "set-approach",
        help="the way from the dock into the garden, inside its areas (with a backup)",
    )
    way.add_argument("map", type=Path)
    way.add_argument("--path", required=True, help='"x,y x,y ..." from the dock, or "none"')
    way.set_defaults(handler=_set_approach)
    up = msub.add_parser(
        "upgrade",
        help="rewrite a map of an older format as the current one (with a backup)",
        description="Rewrite MAP in map format 2 (its outline becomes the mowing area "
        "'lawn'; outlines repaired where safe, each repair said); same decisions.",
    )
    up.add_argument("map", type=Path)
    up.set_defaults(handler=_upgrade)


def _load(path: Path, strict: bool = True):
    """The map; ``strict=False``: also one unfit for mowing (shown with its problems)."""
    from mowerhw.map import MapError, load

    try:
        return load(path, strict=strict)
    except MapError as exc:
        print(f"mowerhw: {exc}", file=sys.stderr)
        raise SystemExit(EX_CONFIG) from None


def _areas(m: Any) -> str:
    """``N mowing and M navigation area(s)``."""
    mowing = len(m.area_names("mow"))
    return f"{mowing} mowing and {len(m.all_areas()) - mowing} navigation area(s)"


def _report_problems(problems: list[str], path: Path) -> int:
    """Say that the map is unfit (its problems shown already): exit status 78 if so."""
    if problems:
        print(
            f"mowerhw: {path}: unfit for mowing ({len(problems)} problem(s), shown above)",
            file=sys.stderr,
        )
    return EX_CONFIG if problems else 0


def _mowable_m2(m) -> float | None:
    try:
        return round(float(m.lawn_polygon().area), 2)
    except Exception:  # an outline that is no polygon: no area to speak of
        return None


def _summary(m, path: Path) -> dict:
    outline = m.outline_polygon()
    return {
        "map": str(path),
        "version": m.version,
        "created_utc": m.created_utc,
        "checksum": m.checksum,
        "boundary_points": m.boundary.shape[0],
        "perimeter_m": round(outline.length, 2),
        "area_m2": round(outline.area, 2),
        "mowable_area_m2": _mowable_m2(m),
        "areas": [
            {
                "name": a.name,
                "kind": a.kind,
                "points": len(a.polygon),
                "area_m2": round(Polygon(a.polygon).area, 2),
            }
            for a in m.all_areas()
        ],
        "problems": m.problems(),
        "warnings": m.warnings(),
        "keepout_zones": [
            {"name": z.name, "points": len(z.polygon), "area_m2": round(Polygon(z.polygon).area, 2)}
            for z in m.keepouts
        ],
        "landmarks": len(m.landmarks),
        "landmark_sigma_median_m": round(
            float(np.median(np.sqrt(np.trace(m.landmark_covariances(), axis1=1, axis2=2) / 3))), 4
        )
        if m.landmarks
        else None,
        # the error the map's frame shares with every landmark and edge point, against the
        # ground (1σ; a map taught before stop 51 has none: its landmark σ hold it)
        "frame_sigma": None
        if m.frame_covariance is None
        else dict(
            zip(
                ("shift_x_m", "shift_y_m", "turn_deg", "scale_percent"),
                (
                    round(float(v), 5)
                    for v in np.sqrt(np.maximum(np.diag(m.frame_covariance), 0.0))
                    * np.array([1.0, 1.0, math.degrees(1.0), 100.0])
                ),
                strict=True,
            )
        ),
        "dock_position": [round(v, 3) for v in m.dock_position.tolist()],
        "dock_approach_points": None if m.dock_approach is None else len(m.dock_approach),
        "camera": (m.camera or {}).get("camera_model"),
        "compass": None
        if m.compass is None
        else {
            "north_deg": round(math.degrees(m.compass.north_rad), 1),
            "sigma_deg": round(math.degrees(m.compass.sigma_rad), 1),
            "strength_ut": round(m.compass.strength_t * 1e6, 1),
            "dip_deg": round(math.degrees(m.compass.dip_rad), 1),
            "readings": m.compass.samples,
        },
        "teach": m.teach,
    }


def _check(args: argparse.Namespace) -> int:
    m = _load(args.map)
    print(
        f"{args.map}: ok (version {m.version}; {len(m.landmarks)} landmarks, {_areas(m)}, "
        f"{m.lawn_polygon().area:.1f} m² to mow, {len(m.keepouts)} keep-out zone(s), checksum "
        "verified)"
    )
    for warning in m.warnings():
        print(f"WARNING      {warning}")
    return 0


def _show(args: argparse.Namespace) -> int:
    m = _load(args.map, strict=False)
    s = _summary(m, args.map)
    if args.json:
        print_json(s)
        return _report_problems(s["problems"], args.map)
    print(f"map          {s['map']}  (version {s['version']}, created {s['created_utc']})")
    if len(s["areas"]) == 1:
        print(
            f"outline      {s['boundary_points']} points, perimeter {s['perimeter_m']} m, "
            f"area {s['area_m2']} m² (mowable {s['mowable_area_m2']} m²)"
        )
    else:
        mowing = sum(a["kind"] == "mow" for a in s["areas"])
        print(
            f"areas        {mowing} mowing, {len(s['areas']) - mowing} navigation; mowable "
            f"{s['mowable_area_m2']} m² (keep-outs taken out)"
        )
        for a in s["areas"]:
            kind = "mowing" if a["kind"] == "mow" else "navigation"
            print(f"area         {a['name']!r} ({kind}): {a['points']} points, {a['area_m2']} m²")
    for z in s["keepout_zones"]:
        print(f"keep-out     {z['name']!r}: {z['points']} points, {z['area_m2']} m²")
    print(f"landmarks    {s['landmarks']} (median σ {s['landmark_sigma_median_m']} m)")
    f = s["frame_sigma"]
    print(
        "frame        not measured (each landmark's σ holds the map frame's error)"
        if f is None
        else f"frame        against the ground, 1σ: shift {f['shift_x_m']} / {f['shift_y_m']} m, "
        f"turn {f['turn_deg']}°, scale {f['scale_percent']} %"
    )
    way = s["dock_approach_points"]
    print(f"dock         {s['dock_position']}" + (f", approach of {way} points" if way else ""))
    c = s["compass"]
    print(
        "compass      none (the teach drive read no magnetic field)"
        if c is None
        else f"compass      the field points {c['north_deg']}° ± {c['sigma_deg']}° in the map "
        f"({c['strength_ut']} µT, dip {c['dip_deg']}°, {c['readings']} readings)"
    )
    print(f"checksum     {s['checksum']}")
    for warning in s["warnings"]:
        print(f"WARNING      {warning}")
    for problem in s["problems"]:
        print(f"PROBLEM      {problem}")
    return _report_problems(s["problems"], args.map)


def _plot(args: argparse.Namespace) -> int:
    from mowerhw.plots import map_figure

    m = _load(args.map, strict=False)
    out = args.output or args.map.with_suffix(".png")
    title = f"{args.map.name}: {len(m.landmarks)} landmarks"
    problems = m.problems()
    map_figure(m, out, title=title, problems=problems)
    print(out)
    for problem in problems:
        print(f"PROBLEM      {problem}")
    return _report_problems(problems, args.map)


def parse_polygon(text: str, min_points: int = 3) -> np.ndarray:
    """``"x,y x,y x,y"`` → (N, 2); a ValueError says what is wrong."""
    pts = []
    for k, tok in enumerate(text.replace(";", " ").split()):
        parts = tok.split(",")
        if len(parts) != 2:
            raise ValueError(f"corner {k + 1} {tok!r} is not x,y")
        try:
            x, y = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"corner {k + 1} {tok!r} is not two numbers") from None
        if not (np.isfinite(x) and np.isfinite(y)):
            raise ValueError(f"corner {k + 1} {tok!r} is not finite")
        pts.append((x, y))
    if len(pts) < min_points:
        what = "a keep-out zone or area" if min_points == 3 else "it"
        raise ValueError(f"{what} needs at least {min_points} corners, got {len(pts)}")
    return np.array(pts)


def _backup(path: Path) -> Path:
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%S%fZ")
    backup = path.with_name(f"{path.name}.{stamp}.bak")
    shutil.copy2(path, backup)
    return backup


def _polygon(args: argparse.Namespace) -> np.ndarray | None:
    """``--polygon``, or None after saying what is wrong with it."""
    try:
        return parse_polygon(args.polygon)
    except ValueError as exc:
        print(f'mowerhw: --polygon: {exc}; expected "x,y x,y x,y ..."', file=sys.stderr)
        return None


def _edit(path: Path, edit: Callable[[Any], Any], verb: str, what: str, m: Any = None) -> int:
    """Load the map (unless given), apply ``edit`` (a MapError says why not: exit 78,
    nothing written), and save the result over it with a backup; ``verb`` ("add"/"remove")
    ``what``."""
    from mowerhw.map import MapError

    m = _load(path) if m is None else m
    try:
        new = edit(m)
    except MapError as exc:
        print(f"mowerhw: cannot {verb} {what}: {exc}", file=sys.stderr)
        return EX_CONFIG
    done = {"add": "added", "remove": "removed"}[verb]
    return _replace(path, new, [], f"{done} {what}")


def _add(args: argparse.Namespace) -> int:
    poly = _polygon(args)
    if poly is None:
        return 2
    lawn = _load(args.map)
    name = args.name or f"keepout-{len(lawn.keepouts) + 1}"
    what = f"keep-out {name!r}"
    return _edit(args.map, lambda m: m.with_keepout(name, poly), "add", what, lawn)


def _add_area(args: argparse.Namespace) -> int:
    poly = _polygon(args)
    if poly is None:
        return 2
    what = f"{args.kind} area {args.name!r}"
    return _edit(args.map, lambda m: m.with_area(args.name, args.kind, poly), "add", what)


def _set_approach(args: argparse.Namespace) -> int:
    if args.path.strip().lower() == "none":
        return _edit(args.map, lambda m: m.with_dock_approach(None), "remove", "the dock approach")
    try:
        way = parse_polygon(args.path, min_points=2)
    except ValueError as exc:
        print(f'mowerhw: --path: {exc}; expected "x,y x,y ..."', file=sys.stderr)
        return 2
    return _edit(args.map, lambda m: m.with_dock_approach(way), "add", "a dock approach")


def _remove_area(args: argparse.Namespace) -> int:
    return _edit(args.map, lambda m: m.without_area(args.name), "remove", f"area {args.name!r}")


def _upgrade(args: argparse.Namespace) -> int:
    from mowerhw.map import VERSION, MapError
    from mowerhw.zones import ZoneError

    m = _load(args.map)
    if m.version == VERSION:
        print(f"{args.map}: already map format {VERSION}; nothing to do")
        return 0
    try:
        garden = _cleaned(m)
        new = m.with_zones(garden)
    except (ZoneError, MapError) as exc:
        print(f"mowerhw: cannot upgrade {args.map}: {exc}", file=sys.stderr)
        return EX_CONFIG
    return _replace(args.map, new, garden.repairs, f"map format {m.version} → {VERSION}")


def _cleaned(m):
    """The map's zones with their outlines repaired where safe (each repair said)."""
    from mowerhw.zones import Garden, Zone, clean_outline

    zones, repairs = [], []
    for a in m.all_areas():
        kind = "mowing" if a.kind == "mow" else "navigation"
        poly, said = clean_outline(a.polygon, f"{kind} area {a.name!r}")
        zones.append(Zone(a.name, a.kind, poly))
        repairs += said
    for z in m.keepouts:
        poly, said = clean_outline(z.polygon, f"keep-out {z.name!r}")
        zones.append(Zone(z.name, "keepout", poly))
        repairs += said
    return Garden(zones, m.dock_position[:2], m.dock_heading(), repairs)


def _remove(args: argparse.Namespace) -> int:
    what = f"keep-out {args.name!r}"
    return _edit(args.map, lambda m: m.without_keepout(args.name), "remove", what)


def _replace(path: Path, new, repairs: list[str], what: str) -> int:
    """Save ``new`` over the map at ``path`` (the old one kept as a backup), saying each
    repair made to what came in and what the map holds now."""
    for repair in repairs:
        print(f"repaired     {repair}")
    backup = _backup(path)
    new.save(path)
    print(
        f"{path}: {what}; {_areas(new)}, "
        f"{len(new.keepouts)} keep-out(s) ({new.lawn_polygon().area:.1f} m² to mow); "
        f"previous map kept as {backup}"
    )
    for warning in new.warnings():
        print(f"WARNING      {warning}")
    return 0


def _export_geojson(args: argparse.Namespace) -> int:
    import json

    from mowerhw.common.fileio import write_atomic
    from mowerhw.zones import to_geojson

    m = _load(args.map, strict=False)
    out = args.output or args.map.with_suffix(".geojson")
    doc = to_geojson(m.garden(), {"map": str(args.map), "map_checksum": m.checksum})
    write_atomic(out, (json.dumps(doc, indent=1) + "\n").encode())
    print(out)
    problems = m.problems()
    for problem in problems:
        print(f"PROBLEM      {problem}")
    return _report_problems(problems, args.map)


def _import_geojson(args: argparse.Namespace) -> int:
    from mowerhw.map import MapError
    from mowerhw.zones import ZoneError, read_geojson

    m = _load(args.map, strict=False)
    try:
        garden = read_geojson(args.geojson)
        new = m.with_zones(garden)
    except (ZoneError, MapError) as exc:
        print(f"mowerhw: {exc}", file=sys.stderr)
        return EX_CONFIG
    return _replace(args.map, new, garden.repairs, f"outline and keep-outs from {args.geojson}")


def _import_openmower(args: argparse.Namespace) -> int:
    from mowerhw.map import MapError
    from mowerhw.zones import Garden, ZoneError, align_by_dock, align_by_points, read_openmower

    m = _load(args.into, strict=False)
    try:
        garden = read_openmower(args.file)
        if args.points:
            pairs = [tok.split(":") for tok in args.points.split()]
            src = [[float(v) for v in a.split(",")] for a, _ in pairs]
            dst = [[float(v) for v in b.split(",")] for _, b in pairs]
            garden, rms = align_by_points(garden, src, dst)
            print(f"aligned      by {len(src)} reference points (RMS {rms:.3f} m)")
        else:
            garden = align_by_dock(garden, m.dock_position[:2], m.dock_heading())
            print("aligned      by the dock")
        mow = {z.name for z in garden.of_kind("mow")}
        unknown = sorted(set(args.area or ()) - mow)
        if unknown:
            raise ZoneError(
                f"no mowing area {', '.join(map(repr, unknown))} in {args.file} (its mowing "
                f"areas: {', '.join(map(repr, sorted(mow)))})"
            )
        taken = [z for z in garden.zones if z.kind != "mow" or not args.area or z.name in args.area]
        mine = m.garden()
        clash = sorted({z.name for z in mine.zones} & {z.name for z in taken})
        if clash:
            raise ZoneError(f"{', '.join(map(repr, clash))}: already in {args.into}")
        merged = Garden([*mine.zones, *taken], mine.dock_xy, mine.dock_heading_rad)
        new = m.with_zones(merged)
    except (ZoneError, MapError, ValueError) as exc:
        print(f"mowerhw: {exc}", file=sys.stderr)
        return EX_CONFIG
    kinds = {k: sum(z.kind == k for z in taken) for k in ("mow", "nav", "keepout")}
    what = (
        f"imported {kinds['mow']} mowing area(s), {kinds['nav']} navigation area(s) and "
        f"{kinds['keepout']} obstacle(s) from {args.file}"
    )
    return _replace(args.into, new, garden.repairs, what)
