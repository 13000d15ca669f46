"""The bench's own hygiene: what it started does not outlive it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys


def test_a_bench_cut_short_stops_its_daemon_when_python_exits(tmp_path) -> None:
    """A bench whose run never reached its end (its test failed, its thread was abandoned)
    still stops the daemon it started when the Python process exits: the daemon runs in a
    session of its own and would otherwise go on after the test session."""
    code = (
        "import subprocess\n"
        "from mowerhw.bench import Bench\n"
        f"bench = Bench(duration_s=1.0, out_dir={str(tmp_path)!r})\n"
        "bench.proc = subprocess.Popen(['sleep', '120'], start_new_session=True,\n"
        "                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
        "print(bench.proc.pid, flush=True)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    pid = int(out.stdout.split()[0])
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return  # stopped (and reaped) at exit
    os.kill(pid, signal.SIGKILL)
    raise AssertionError(f"the bench's daemon (pid {pid}) outlived the Python that started it")
