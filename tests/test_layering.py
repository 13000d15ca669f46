"""The architecture of DESIGN.md §2, checked on every module's imports.

* Estimators and other pure modules never import drivers, asyncio, serial or CAN.
* Drivers never import estimators (they may use samples, clock sync, config, geometry,
  the camera model and the simulator that mock hardware is driven by).
* Only the runtime layer (CLI, daemon, bench) wires the two.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Modules of mowerhw that are allowed to do I/O and wire drivers to estimators.
RUNTIME_LAYER = (
    "mowerhw.cli",
    "mowerhw.runtime",
    "mowerhw.bench",
    "mowerhw.recording.replay",
    "mowerhw.record",
)
IO_MODULES = {"asyncio", "serial", "can", "drivers", "socket", "termios", "pty", "select"}
# What drivers may import from mowerhw.
DRIVER_MAY_USE = (
    "mowerhw.common.samples",
    "mowerhw.common.clocksync",
    "mowerhw.config",
    "mowerhw.common.geometry",
    "mowerhw.camera",
    "mowerhw.sim",
    "mowerhw.io",
)


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
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


def in_package(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def test_pure_modules_do_no_device_io():
    offenders = []
    for path in sorted((ROOT / "mowerhw").rglob("*.py")):
        mod = module_name(path)
        if in_package(mod, RUNTIME_LAYER):
            continue
        bad = {i for i in imports_of(path) if i.split(".")[0] in IO_MODULES}
        if bad:
            offenders.append(f"{mod} imports {sorted(bad)}")
    assert not offenders, "estimators/pure modules must not do device I/O:\n" + "\n".join(offenders)


def test_drivers_never_import_estimators():
    offenders = []
    for path in sorted((ROOT / "drivers").rglob("*.py")):
        for name in imports_of(path):
            if (
                name.split(".")[0] == "mowerhw"
                and name != "mowerhw"
                and not in_package(name, DRIVER_MAY_USE)
            ):
                offenders.append(f"{module_name(path)} imports {name}")
    assert not offenders, "drivers must not import estimators:\n" + "\n".join(offenders)


def test_the_check_can_fail(tmp_path):
    # The guard itself sees an offending import.
    bad = tmp_path / "x.py"
    bad.write_text("import asyncio\nfrom drivers.imu.vn100 import Vn100Parser\n")
    assert {"asyncio", "drivers.imu.vn100"} <= imports_of(bad)
