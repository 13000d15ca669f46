"""One poll kept between waits: what ``multiprocessing.connection.wait`` answered."""

from __future__ import annotations

import multiprocessing
import os
import select
import socket
import time

from mowerhw.supervisor.fdwait import FdWaiter


def test_ready_descriptors_timeouts_hang_ups_and_a_changing_extra() -> None:
    a, b = multiprocessing.Pipe()
    r, w = os.pipe()
    waiter = FdWaiter((a.fileno(), r))
    started = time.monotonic()
    assert waiter.wait(0.05) == set()  # nothing: it waits the timeout out
    assert time.monotonic() - started >= 0.045
    assert not waiter.ready_now()
    b.send(("lease", 1))
    assert waiter.wait(1.0) == {a.fileno()} and waiter.ready_now()
    a.recv()
    os.write(w, b"!")
    assert waiter.wait(0.0) == {r}
    os.read(r, 16)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    other = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        listener.bind("\0mowerhw-fdwait-test")
        listener.listen()
        other.bind("\0mowerhw-fdwait-test-other")
        other.listen()  # (an unconnected socket reads as hung up)
        client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        client.connect("\0mowerhw-fdwait-test")
        assert waiter.wait(1.0, listener.fileno()) == {listener.fileno()}  # a client waits
        assert waiter.wait(0.0, other.fileno()) == set()  # swapped: the listener left out
        assert waiter.wait(0.0, listener.fileno()) == {listener.fileno()}  # and back
        assert waiter.wait(0.0) == set()
        client.close()
    finally:
        listener.close()
        other.close()
    room = FdWaiter((w,), select.POLLOUT)  # for writing: an empty pipe has room
    assert room.ready_now() and not FdWaiter((w,)).ready_now()
    os.close(w)  # the writer gone: a hang-up is ready too (the reader finds EOF)
    assert waiter.wait(1.0) == {r}
    b.close()
    assert waiter.wait(1.0) == {a.fileno(), r}
    os.close(r)
