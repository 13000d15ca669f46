"""The vision front end in a process of its own (``runtime.frontend_process``).

On a worker thread, the front end's tracking shares the estimation process's GIL with the
event loop that reads the VN-100 and decides at every IMU sample: under load a frame's
Python work could hold the loop up (measured: an 80 ms block, a lease that ran out). Here
:class:`~mowerhw.frontend.FrontEnd` runs in a child interpreter, as the map loader does (a
subprocess: the estimation process is a daemonic child of the supervisor and may not have
multiprocessing children); the loop's thread only sends the frame and waits for the tracks.

Messages on the child's stdin/stdout: a 4-byte length and a pickle. A frame's pixels do not
go through the pipe (2.4 MB at 4 Hz was ~2 % of a core in pickling, copying and pipe writes on
both sides): they are written into a memory file both processes map (:class:`FrameSlot`,
``memfd``), and the message names the frame's shape. One frame is in flight at a time (the
sender waits for its tracks), so one slot is enough; the child copies the pixels out before it
answers (the front end keeps the previous image). The child is this process's own (killed
with it: PDEATHSIG); its answers are trusted like any of our code.
"""

from __future__ import annotations

import mmap
import os
import pickle
import select
import struct
import subprocess
import sys
import threading
import time
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from mowerhw.common.relocalization import SearchRequest
from mowerhw.common.samples import FrameSample
from mowerhw.frontend import FrameTracks
from mowerhw.runtime.process import cpu_seconds, die_with_parent
from mowerhw.vision.base import VisionBase

_LEN = struct.Struct("<I")
#: a worker that computes nothing (its CPU time does not grow) this long with a frame in hand
#: is hung — blocked, stopped or deadlocked — however long ``runtime.frontend_hang_s`` is
IDLE_HANG_S = 10.0
#: how often the wait for an answer looks at the worker's CPU time (s)
CHECK_S = 0.5


class HangWatch:
    """Whether a worker with a frame in hand is hung: it answered nothing for ``hang_s``
    (an endless loop), or its CPU time has not grown for ``idle_s`` (blocked, stopped,
    deadlocked: a slow search for the pose keeps computing, so only the long limit ends it)."""

    def __init__(self, now: float, cpu: float | None, hang_s: float, idle_s: float) -> None:
        self.start = self.progress_at = now
        self.cpu = cpu
        self.hang_s = hang_s
        self.idle_s = idle_s

    def hung(self, now: float, cpu: float | None) -> str:
        """Why the worker is taken for hung at ``now`` (its CPU time ``cpu``), or ""."""
        if now - self.start > self.hang_s:
            return f"answered no frame for {self.hang_s:g} s (runtime.frontend_hang_s)"
        if cpu is None or self.cpu is None or cpu > self.cpu:
            self.progress_at, self.cpu = now, cpu  # computing (or it cannot be told)
        elif now - self.progress_at > self.idle_s:
            return (
                f"computed nothing for {self.idle_s:g} s with a frame in hand (blocked, "
                "stopped or deadlocked)"
            )
        return ""


def _write(out: IO[bytes], obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    out.write(_LEN.pack(len(data)) + data)
    out.flush()


def _read(inp: IO[bytes]) -> Any:
    """One message, waited for (the sender's deadline: ``FrontendWorker._wait_for_answer``)."""
    head = inp.read(_LEN.size)
    if len(head) < _LEN.size:
        raise EOFError("the front-end worker's pipe closed")
    (n,) = _LEN.unpack(head)
    data = inp.read(n)
    if len(data) < n:
        raise EOFError("the front-end worker's pipe closed mid-message")
    return pickle.loads(data)


class FrameSlot:
    """A memory file (``memfd``) that holds one frame's pixels, mapped by the sender (which
    writes) and by the worker (which reads, given the file's descriptor number)."""

    def __init__(self, fd: int | None = None) -> None:
        self.fd = os.memfd_create("mowerhw-frame", 0) if fd is None else fd
        self._map: mmap.mmap | None = None

    def _mapped(self, nbytes: int, grow: bool) -> mmap.mmap:
        if self._map is None or len(self._map) < nbytes:
            if self._map is not None:
                self._map.close()
            if grow:
                os.ftruncate(self.fd, nbytes)
            self._map = mmap.mmap(self.fd, nbytes)
        return self._map

    def put(self, image: NDArray[np.uint8]) -> tuple[tuple[int, ...], str]:
        """Copy ``image`` in; what :meth:`take` needs to read it back."""
        image = np.ascontiguousarray(image)
        view = np.frombuffer(self._mapped(image.nbytes, grow=True), np.uint8, image.nbytes)
        view[:] = image.reshape(-1).view(np.uint8)
        return image.shape, image.dtype.str

    def take(self, shape: tuple[int, ...], dtype: str) -> NDArray[Any]:
        """A copy of the frame :meth:`put` wrote (``shape``, ``dtype`` as it returned)."""
        dt = np.dtype(dtype)
        nbytes = int(np.prod(shape)) * dt.itemsize
        raw = np.frombuffer(self._mapped(nbytes, grow=False), np.uint8, nbytes)
        return raw.view(dt).reshape(shape).copy()

    def close(self) -> None:
        if self._map is not None:
            self._map.close()
            self._map = None
        os.close(self.fd)


class FrontendWorkerDied(RuntimeError):
    """The worker process ended: crash-only, the daemon ends too (a new front end in the
    same chain would hand out track ids the chain already knows)."""


class FrontendWorker:
    """``track(key, args, t, image, r, search)`` in the child: one FrontEnd (and, for a mow
    chain, one global relocalizer) per ``key`` (the chain's serial: a new chain starts a new
    front end, as it does on a thread)."""

    def __init__(self, hang_s: float = 300.0, idle_hang_s: float = IDLE_HANG_S) -> None:
        #: a frame not answered within this is a hung worker (``runtime.frontend_hang_s``)
        self.hang_s = hang_s
        #: nor one it computes nothing on for this long (:class:`HangWatch`)
        self.idle_hang_s = idle_hang_s
        self._proc: subprocess.Popen[bytes] | None = None
        self._key: Any = None
        self._lock = threading.Lock()
        self._slot: FrameSlot | None = None

    def _start(self) -> subprocess.Popen[bytes]:
        if self._proc is None:
            self._slot = slot = FrameSlot()
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "mowerhw.runtime.frontend_worker", str(slot.fd)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                preexec_fn=die_with_parent,
                pass_fds=(slot.fd,),
            )
        elif self._proc.poll() is not None:
            raise FrontendWorkerDied(
                f"the front-end worker process ended (exit status {self._proc.returncode})"
            )
        return self._proc

    def track(
        self,
        key: Any,
        args: tuple[tuple[Any, ...], tuple[Any, ...] | None],
        t: float,
        image: NDArray[np.uint8],
        r_prev_cur: Any,
        search: SearchRequest | None = None,
    ) -> FrameTracks:
        """The frame's tracks (blocking: call it off the event loop); RuntimeError if the
        front end failed on it, :class:`FrontendWorkerDied` if the process is gone."""
        with self._lock:
            proc = self._start()
            assert proc.stdin is not None and proc.stdout is not None and self._slot is not None
            try:
                if key != self._key:
                    _write(proc.stdin, ("reset", *args))
                    self._key = key
                shape, dtype = self._slot.put(image)
                _write(proc.stdin, ("frame", t, shape, dtype, r_prev_cur, search))
                self._wait_for_answer(proc)
                kind, body = _read(proc.stdout)
            except TimeoutError as exc:
                proc.kill()
                proc.wait()
                raise FrontendWorkerDied(
                    f"the front-end worker process {exc}: hung, killed"
                ) from None
            except (OSError, EOFError, pickle.PickleError) as exc:
                proc.kill()
                proc.wait()
                raise FrontendWorkerDied(f"the front-end worker process failed ({exc})") from None
        if kind != "tracks":
            raise RuntimeError(f"front end: {body}")
        tracks: FrameTracks = body
        return tracks

    def _wait_for_answer(self, proc: subprocess.Popen[bytes]) -> None:
        """Until the worker's answer begins; TimeoutError saying why it is taken for hung."""
        assert proc.stdout is not None
        watch = HangWatch(time.monotonic(), cpu_seconds(proc.pid), self.hang_s, self.idle_hang_s)
        while not select.select([proc.stdout], [], [], CHECK_S)[0]:
            why = watch.hung(time.monotonic(), cpu_seconds(proc.pid))
            if why:
                raise TimeoutError(why)

    def close(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait(timeout=5.0)
        if self._slot is not None:
            self._slot.close()
            self._slot = None


def track_frame(
    worker: FrontendWorker | None,
    key: Any,
    vision: VisionBase,
    frame: FrameSample,
    r: Any,
    search: SearchRequest | None = None,
) -> FrameTracks:
    """A frame's tracks for ``vision``'s chain (``key``: its serial), with a relocalization
    if ``search`` asks for one: in ``worker``'s process, or on this thread without one
    (blocking: call it off the event loop)."""
    if worker is None:
        return vision.track(frame.t, frame.image, r, search)
    t = frame.t + vision.time_shift_s
    args = (vision.frontend_args, vision.search_args)
    return vision.tracked(worker.track(key, args, t, frame.image, r, search))


def main() -> None:  # pragma: no cover - the child; exercised through FrontendWorker
    import cv2

    from mowerhw.frontend import FrontEnd
    from mowerhw.vision.mow import FrameSearch

    cv2.setNumThreads(1)
    slot = FrameSlot(int(sys.argv[1]))
    with os.fdopen(0, "rb") as inp, os.fdopen(1, "wb") as out:
        frontend: FrontEnd | None = None
        searcher: FrameSearch | None = None
        while True:
            try:
                msg = _read(inp)
            except EOFError:
                return
            if msg[0] == "reset":
                frontend = FrontEnd(*msg[1])
                searcher = None if msg[2] is None else FrameSearch(*msg[2])
                continue
            _, t, shape, dtype, r, search = msg
            try:
                assert frontend is not None, "a frame before the front end was set up"
                image = slot.take(shape, dtype)
                tracks = frontend.process(t, image, r, search is not None and search.carried)
                if search is not None and searcher is not None:
                    tracks = searcher(tracks, search)
                _write(out, ("tracks", tracks))
            except Exception as exc:
                _write(out, ("error", f"{type(exc).__name__}: {exc}"))


if __name__ == "__main__":
    main()
