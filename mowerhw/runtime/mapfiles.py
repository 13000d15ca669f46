"""The daemon's files: the lawn map (checked load, atomic save with its picture) and the pose
saved for a restart to resume from (docs/design.md §8)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import math
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np

from mowerhw.common.fileio import FileStamp, file_stamp, write_atomic
from mowerhw.config import Config
from mowerhw.map import MAX_MAP_BYTES, LawnMap, MapError, check_map_file
from mowerhw.runtime.chains import RESUME_SIGMA_RESTART
from mowerhw.runtime.pipelines import StartPose, TeachPipeline

log = logging.getLogger("mowerhw.daemon")

#: a pose saved by a previous run is resumed from if it is at most this old (s)
RESUME_MAX_AGE_S = 120.0
#: a saved gyro bias larger than this (rad/s) is not one (a garbled file): learnt again
MAX_SAVED_BIAS_RAD_S = 1.0


@functools.cache
def boot_id() -> str | None:
    """This boot's identity (Linux: a random UUID per boot), None where there is none."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip() or None
    except OSError:
        return None


class MapFile:
    """The map file the daemon mows on: loaded and checked in a separate process, and watched
    for changes (an edited keep-out takes effect; a bad file halts until it is fixed).

    Whatever is wrong with the file — not there, not a regular file (a FIFO would block a
    reader for good, ``/dev/zero`` never ends), over ``map.max_bytes``, not JSON, nested or
    numbered beyond the limits, invalid, or a load that takes over ``map.load_timeout_s`` or
    kills its process — is a problem string (MAP_INVALID), never an exception, and never a
    stall of the event loop: the parse runs in a child process that is killed when late.
    A failed load is tried again every :attr:`RETRY_S` (a transient failure clears by itself).
    """

    RETRY_S = 2.0

    def __init__(self, path: Path, max_bytes: int = MAX_MAP_BYTES, timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self._stamp: FileStamp | None = None
        self._loading = False
        self._failed_at: float | None = None

    @classmethod
    def of(cls, cfg: Config) -> MapFile:
        """The map file the config names, with its limits (``map.*``)."""
        return cls(Path(cfg.map.path), cfg.map.max_bytes, cfg.map.load_timeout_s)

    def changed(self) -> bool:
        """The file is not the one last loaded, or the last load failed :attr:`RETRY_S` ago
        (and no load is under way)."""
        if self._loading:
            return False
        if file_stamp(self.path) != self._stamp:
            return True
        return self._failed_at is not None and time.monotonic() - self._failed_at >= self.RETRY_S

    def retrying(self) -> bool:
        """The next load is a retry of a failed one (the file itself did not change)."""
        return self._failed_at is not None and file_stamp(self.path) == self._stamp

    async def load(self, pool: Executor) -> LawnMap | str:
        """The checked map, or the problem that makes it unusable (logged as MAP_INVALID)."""
        self._stamp = file_stamp(self.path)
        self._loading = True
        try:
            loop = asyncio.get_running_loop()
            got: LawnMap = await loop.run_in_executor(
                pool, load_map_isolated, self.path, self.max_bytes, self.timeout_s
            )
            self._failed_at = None
            return got
        except Exception as exc:  # anything: the map is unusable, the daemon carries on
            problem = str(exc) if isinstance(exc, MapError) else f"{self.path}: {exc!r}"
            if self._failed_at is None:
                log.error("MAP_INVALID: %s", problem)
            self._failed_at = time.monotonic()
            return problem
        finally:
            self._loading = False


def load_map_isolated(path: Path, max_bytes: int, timeout_s: float) -> LawnMap:
    """:func:`mowerhw.map.load` in a child interpreter (blocking: call it from a worker thread),
    so a huge, hostile or endless file costs that process, not the daemon's event loop;
    :class:`MapError` for every failure."""
    path = Path(path)
    check_map_file(path, max_bytes)  # the cheap refusals first, without a process
    # a child interpreter (not multiprocessing: the estimation process is a daemonic child
    # of the supervisor, which may not have children of its own)
    cmd = [sys.executable, "-m", "mowerhw.runtime.maploader", str(path), str(max_bytes)]
    child = subprocess.Popen(
        cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    try:
        out, err = child.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()
        raise MapError(f"{path}: loading took over {timeout_s:g} s (map.load_timeout_s)") from None
    try:
        kind, body = pickle.loads(out)  # written by our own child (runtime/maploader.py)
    except Exception:
        tail = err.decode(errors="replace").strip().splitlines()[-1:] or ["no output"]
        raise MapError(
            f"{path}: the map loader failed (exit code {child.returncode}: {tail[0][:200]})"
        ) from None
    if kind != "ok":
        raise MapError(str(body))
    if not isinstance(body, LawnMap):
        raise MapError(f"{path}: the map loader returned {type(body).__name__}")
    return body


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
    instead of the dock. Renamed into place (no fsync: at worst an older pose).

    Its age is judged on the boot's own clock (``CLOCK_BOOTTIME``: it never steps) when the
    pose was saved in this boot — a mower computer without a real-time clock has its wall
    clock stepped by hours when NTP first syncs, which would refuse a pose saved seconds ago,
    or take one from before a long power-off as fresh — and by the wall clock only across a
    reboot, where nothing else spans the gap."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.errors = 0

    def save(self, pose: StartPose, map_checksum: str) -> None:
        doc = {
            "wall_time": time.time(),
            "boot_id": boot_id(),
            "boot_time": time.clock_gettime(time.CLOCK_BOOTTIME),
            "map_checksum": map_checksum,
            "position": np.asarray(pose.position).tolist(),
            "quaternion": np.asarray(pose.quaternion).tolist(),
        }
        if pose.gyro_bias is not None:
            doc["gyro_bias"] = np.asarray(pose.gyro_bias).tolist()
        try:
            write_atomic(self.path, json.dumps(doc).encode(), durable=False)
        except OSError as exc:
            self.errors += 1
            if self.errors == 1:
                log.warning("cannot save the pose for restarts: %s", exc)

    def load(self, lawn_map: LawnMap) -> StartPose | None:
        """The pose saved by a previous run, if it is recent and of this map (else None, and
        the log says why it was not taken)."""
        try:
            doc: Any = json.loads(self.path.read_text())
            this_boot = boot_id()
            same_boot = this_boot is not None and doc.get("boot_id") == this_boot
            if same_boot:
                age = time.clock_gettime(time.CLOCK_BOOTTIME) - float(doc["boot_time"])
            else:
                age = time.time() - float(doc["wall_time"])
            pos = np.asarray(doc["position"], dtype=np.float64).reshape(3)
            quat = np.asarray(doc["quaternion"], dtype=np.float64).reshape(4)
            saved_bias = doc.get("gyro_bias")
            bias = None if saved_bias is None else np.asarray(saved_bias, np.float64).reshape(3)
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            log.warning("not resuming from %s: unreadable (%s)", self.path, exc)
            return None
        clock = "this boot's clock" if same_boot else "the wall clock (saved before a reboot)"
        if doc.get("map_checksum") != lawn_map.checksum:
            log.info("not resuming from %s: it was saved on another map", self.path)
            return None
        if not 0 <= age <= RESUME_MAX_AGE_S:
            log.info(
                "not resuming from %s: saved %.1f s ago by %s (resumed only within %.0f s)",
                self.path,
                age,
                clock,
                RESUME_MAX_AGE_S,
            )
            return None
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))) or not np.any(quat):
            log.warning("not resuming from %s: its pose is not finite or not a rotation", self.path)
            return None
        # the gyro bias the previous run had learnt (its landmarks refined it): within this
        # boot only — the IMU may have been switched off with the computer
        if bias is not None and not (same_boot and np.all(np.abs(bias) < MAX_SAVED_BIAS_RAD_S)):
            bias = None
        log.info(
            "resuming from the pose saved %.1f s ago by %s (σ widened to %.2f m, %.0f°; %s)",
            age,
            clock,
            RESUME_SIGMA_RESTART[0],
            math.degrees(RESUME_SIGMA_RESTART[1]),
            "the gyro bias it had"
            if bias is not None
            else "the gyro bias learnt again while the mower stands",
        )
        return StartPose(pos, quat / np.linalg.norm(quat), bias)
