"""The architecture (docs/design.md §2), checked on every module's imports.

Layers, lowest first; a module may import its own layer and the ones below, never above:

0. ``mowerhw.common`` — types and conventions;
1. foundation — the config, the camera model, the map format, the IMU grades;
2. estimation — estimator parts, teach, mow, front end, the vision glue, baselines;
3. analysis — simulator, evaluation, plots, the Allan analysis, MCAP files;
4. runtime — the runtime core and daemon, replay, bench, CLI.

Besides: layers 0–3 never import device I/O (drivers, asyncio, serial, CAN, sockets); the
front end never imports an estimator and teach and mow never import each other; the runtime
core has no I/O, threads or clock of its own; drivers import nothing of mowerhw but
``mowerhw.common``; the status page (``mowerhw.web``) never imports the runtime or the
supervisor: it is a client of the control socket.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

LAYERS: tuple[tuple[str, ...], ...] = (
    ("mowerhw.common",),
    (
        "mowerhw.config",
        "mowerhw.camera",
        "mowerhw.map",
        "mowerhw.zones",
        "mowerhw.imu.grades",
        "mowerhw.imu",
    ),
    (
        "mowerhw.estimation",
        "mowerhw.teach",
        "mowerhw.mow",
        "mowerhw.frontend",
        "mowerhw.vision",
        "mowerhw.baselines",
    ),
    (
        "mowerhw.sim",
        "mowerhw.evaluation",
        "mowerhw.plots",
        "mowerhw.imu.allan",
        "mowerhw.recording.mcap",
    ),
    (
        "mowerhw.runtime",
        "mowerhw.supervisor",
        "mowerhw.web",
        "mowerhw.recording",
        "mowerhw.bench",
        "mowerhw.cli",
        "mowerhw.__main__",
    ),
)
RUNTIME_LAYER = len(LAYERS) - 1
IO_MODULES = {"asyncio", "serial", "can", "drivers", "socket", "termios", "pty", "select"}
#: pairs (importer, imported) within a layer that must not happen
FORBIDDEN = (
    ("mowerhw.frontend", "mowerhw.teach"),
    ("mowerhw.frontend", "mowerhw.mow"),
    ("mowerhw.frontend", "mowerhw.vision"),
    ("mowerhw.teach", "mowerhw.mow"),
    ("mowerhw.mow", "mowerhw.teach"),
    ("mowerhw.estimation", "mowerhw.teach"),
    ("mowerhw.estimation", "mowerhw.mow"),
    # the status page reads the daemon only through the control socket (issue 19)
    ("mowerhw.web", "mowerhw.runtime"),
    ("mowerhw.web", "mowerhw.supervisor"),
)
#: the runtime core: synchronous, no I/O, no threads, no clock
CORE_MODULES = ("mowerhw.runtime.core", "mowerhw.runtime.journal", "mowerhw.runtime.pipelines")
CORE_FORBIDDEN = {"asyncio", "threading", "socket", "select", "time", "os", "concurrent", "drivers"}
DRIVER_MAY_USE = ("mowerhw.common",)


def module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return found


def in_package(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def layer_of(name: str) -> int | None:
    """The layer of a mowerhw module: the longest matching prefix wins."""
    best: tuple[int, int] | None = None
    for k, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if in_package(name, (p,)) and (best is None or len(p) > best[1]):
                best = (k, len(p))
    return None if best is None else best[0]


def violations(root: Path) -> list[str]:
    """Every import in ``root``'s mowerhw/ and drivers/ that breaks a rule of the module doc."""
    found = []
    for path in sorted((root / "mowerhw").rglob("*.py")):
        mod = module_name(path, root)
        if mod == "mowerhw":
            continue
        mine = layer_of(mod)
        if mine is None:
            found.append(f"{mod}: in no layer (add it to LAYERS)")
            continue
        for name in sorted(imports_of(path)):
            top = name.split(".")[0]
            if mine < RUNTIME_LAYER and top in IO_MODULES:
                found.append(f"{mod} (layer {mine}) imports device I/O {name}")
            if mod in CORE_MODULES and top in CORE_FORBIDDEN:
                found.append(f"{mod} (the runtime core) imports {name}")
            if top != "mowerhw" or name == "mowerhw":
                continue
            theirs = layer_of(name)
            if theirs is not None and theirs > mine:
                found.append(f"{mod} (layer {mine}) imports {name} (layer {theirs})")
            for a, b in FORBIDDEN:
                if in_package(mod, (a,)) and in_package(name, (b,)):
                    found.append(f"{mod} imports {name}")
    for path in sorted((root / "drivers").rglob("*.py")):
        for name in sorted(imports_of(path)):
            if name.split(".")[0] == "mowerhw" and not in_package(name, DRIVER_MAY_USE):
                found.append(f"{module_name(path, root)} (a driver) imports {name}")
    return found


def test_the_tree_keeps_its_layers() -> None:
    assert not violations(ROOT), "layering broken:\n" + "\n".join(violations(ROOT))


def test_the_check_fails_on_every_kind_of_violation(tmp_path: Path) -> None:
    def write(rel: str, text: str) -> None:
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)

    write("mowerhw/__init__.py", "")
    write("mowerhw/common/geometry.py", "import mowerhw.config\n")
    write("mowerhw/mow/localizer.py", "import asyncio\nfrom mowerhw.teach import Teacher\n")
    write("mowerhw/frontend/tracker.py", "from mowerhw.vision import MowVision\n")
    write("mowerhw/teach/teacher.py", "from mowerhw.sim import world\n")
    write("mowerhw/runtime/core.py", "import threading\n")
    write("mowerhw/newthing.py", "")
    write("drivers/imu/vn100.py", "from mowerhw.mow import Localizer\n")
    got = "\n".join(violations(tmp_path))
    assert "mowerhw.common.geometry (layer 0) imports mowerhw.config (layer 1)" in got
    assert "mowerhw.mow.localizer (layer 2) imports device I/O asyncio" in got
    assert "mowerhw.mow.localizer imports mowerhw.teach" in got
    assert "mowerhw.frontend.tracker imports mowerhw.vision" in got
    assert "mowerhw.teach.teacher (layer 2) imports mowerhw.sim (layer 3)" in got
    assert "mowerhw.runtime.core (the runtime core) imports threading" in got
    assert "mowerhw.newthing: in no layer" in got
    assert "drivers.imu.vn100 (a driver) imports mowerhw.mow" in got
    write("mowerhw/newthing.py", "")  # the good tree passes
    clean = tmp_path / "clean"
    write("clean/mowerhw/__init__.py", "")
    write("clean/mowerhw/mow/localizer.py", "from mowerhw.common.geometry import x\n")
    write("clean/drivers/imu/vn100.py", "from mowerhw.common.samples import ImuSample\n")
    assert violations(clean) == []
