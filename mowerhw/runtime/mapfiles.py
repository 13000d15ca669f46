"""The daemon's files: the lawn map (checked load, atomic save with its picture) and the pose
saved for a restart to resume from (docs/design.md §8)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import tempfile
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np

from mowerhw.common.fileio import write_atomic
from mowerhw.map import LawnMap, MapError
from mowerhw.map import load as load_map
from mowerhw.runtime.pipelines import StartPose, TeachPipeline

log = logging.getLogger("mowerhw.daemon")

#: a pose saved by a previous run is resumed from if it is at most this old (s)
RESUME_MAX_AGE_S = 120.0

FileStamp = tuple[int, int, int]


def file_stamp(path: Path) -> FileStamp | None:
    """(mtime, size, inode) of ``path``, None if it cannot be read: a change means reload."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


class MapFile:
    """The map file the daemon mows on: loaded and checked off the event loop, and watched
    for changes (an edited keep-out takes effect; a corrupt file halts until it is fixed)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._stamp: FileStamp | None = None
        self._loading = False

    def changed(self) -> bool:
        """The file is not the one last loaded (and no load is under way)."""
        return not self._loading and file_stamp(self.path) != self._stamp

    async def load(self, pool: Executor) -> LawnMap | str:
        """The checked map, or the problem that makes it unusable (logged as MAP_INVALID)."""
        self._stamp = file_stamp(self.path)
        self._loading = True
        try:
            loop = asyncio.get_running_loop()
            return await loop.run_in_executor(pool, load_checked_map, self.path)
        except MapError as exc:
            log.error("MAP_INVALID: %s", exc)
            return str(exc)
        finally:
            self._loading = False


def load_checked_map(path: Path) -> LawnMap:
    """The map at ``path``, or :class:`MapError` naming every problem it has."""
    lawn_map = load_map(path)
    problems = lawn_map.problems()
    if problems:
        raise MapError(f"{path}: " + "; ".join(problems))
    return lawn_map


def save_map(lawn_map: LawnMap, path: Path) -> None:
    """Write the map atomically (keeping the previous one as ``.bak``) and its PNG."""
    path = Path(path)
    if path.exists():
        with contextlib.suppress(OSError):
            shutil.copy2(path, path.with_name(path.name + ".bak"))
    lawn_map.save(path)
    try:
        from mowerhw.plots import map_figure

        with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
            png = map_figure(lawn_map, Path(tmp) / "map.png", title=f"Lawn map {path.name}")
            write_atomic(path.with_suffix(".png"), png.read_bytes())
    except Exception as exc:
        log.warning("map picture not written: %s", exc)


def teach_to_map_file(pipe: TeachPipeline, path: Path) -> dict[str, Any]:
    """Finish a teach drive (loop closure, boundary: seconds of work), save the map, and say
    what it holds."""
    t0 = time.monotonic()
    result, lawn_map = pipe.finish()
    save_map(lawn_map, path)
    return {
        "map": str(path),
        "png": str(path.with_suffix(".png")),
        "landmarks": len(lawn_map.landmarks),
        "boundary_points": int(lawn_map.boundary.shape[0]),
        "area_m2": round(float(lawn_map.lawn_polygon().area), 2),
        "loop_closure": result.closure.reason,
        "finish_s": round(time.monotonic() - t0, 3),
        "checksum": lawn_map.checksum,
    }


class PoseFile:
    """The newest localized pose, for a restart (a crash, SIGKILL, power loss) to resume from
    instead of the dock. Renamed into place (no fsync: at worst an older pose)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.errors = 0

    def save(self, pose: StartPose, map_checksum: str) -> None:
        doc = {
            "wall_time": time.time(),
            "map_checksum": map_checksum,
            "position": np.asarray(pose.position).tolist(),
            "quaternion": np.asarray(pose.quaternion).tolist(),
        }
        try:
            write_atomic(self.path, json.dumps(doc).encode(), durable=False)
        except OSError as exc:
            self.errors += 1
            if self.errors == 1:
                log.warning("cannot save the pose for restarts: %s", exc)

    def load(self, lawn_map: LawnMap) -> StartPose | None:
        """The pose saved by a previous run, if it is recent and of this map."""
        try:
            doc: Any = json.loads(self.path.read_text())
            age = time.time() - float(doc["wall_time"])
            pos = np.asarray(doc["position"], dtype=np.float64).reshape(3)
            quat = np.asarray(doc["quaternion"], dtype=np.float64).reshape(4)
        except (OSError, ValueError, KeyError, TypeError):
            return None
        if doc.get("map_checksum") != lawn_map.checksum or not 0 <= age <= RESUME_MAX_AGE_S:
            return None
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
            return None
        log.info("resuming from the pose saved %.1f s ago (σ widened to 0.12 m, 6°)", age)
        return StartPose(pos, quat / np.linalg.norm(quat))
