"""The supervisor process (docs/design.md §8): what systemd starts as ``mowerhw run``.

It owns the CAN bus and is the only writer of the permit frames; it starts the estimation
process (:func:`mowerhw.supervisor.child.estimator_main`) and talks to it over one pipe:
the frames of the PGNs the child's speed reader reads go down (the child decodes them; while
it records, every frame received and sent), every decision comes up as a lease, with the
IMU's specific force that lift and tilt are judged by. One plain loop, no numpy, no asyncio: it
wakes when a lease arrives, when the newest lease runs out, when a frame is due, when the
ground speed or the specific force it watches would go stale, when a switch frame of the
mower's controller changes a safety latch (the CAN receive thread says so through a pipe),
and at least every 0.1 s.

Crash-only: the estimation process dying (or not starting, or hanging: silent for
``supervisor.child_hang_s`` once it has leased, then killed), or its own CAN receive thread
dying, halts the deck, announces the fault (heartbeat 254), names it in the log and ends the
service with exit status 1, for systemd to restart it. A CAN bus that fails is reopened with
backoff; if it stays unusable for ``supervisor.can_down_restart_s`` the watchdog is no longer
fed.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Collection
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.can.address_claim import PGN_ADDRESS_CLAIMED, PGN_REQUEST, AddressClaim, serve
from drivers.can.isobus import parse_id, pgn_filters
from drivers.can.permit import PermitSender, Status
from drivers.can.speed import SpeedReader
from drivers.can.switches import decode_switches
from mowerhw.common.reasons import Reason
from mowerhw.config import Config
from mowerhw.estimation.safety import SafetyMonitor
from mowerhw.mow.gate import PermitGate
from mowerhw.runtime.sdnotify import Notifier
from mowerhw.supervisor.canport import CanPort, address_claim, permit_sender
from mowerhw.supervisor.fdwait import FdWaiter
from mowerhw.supervisor.lease import Lease, SupervisorGate
from mowerhw.supervisor.status_socket import StatusSocket
from mowerhw.supervisor.web_child import web_child_main
from mowerhw.web.process import WebProcess

if TYPE_CHECKING:
    import can

log = logging.getLogger("mowerhw.supervisor")

#: the loop late or busy longer than this (ms) is a stall (issue 15: goal 0 on the bench)
LOOP_STALL_MS = 20.0
TICK_MAX_S = 0.1  # the watchdog, the status down to the child, the web process
STATUS_PERIOD_S = 0.5  # the supervisor's status, down to the child (for `mowerhw ctl status`)
LATENCIES_KEPT = 2000  # the newest latencies its status gives percentiles of
#: the CAN receive thread's longest wait for a frame: how soon it sees a stop or a bus
#: reopened under it (the shutdown waits 0.5 s for it). Each wait that ends empty is a
#: wake-up for nothing (0.05 s woke it about 10 times a second between 10-Hz speed frames)
RX_WAIT_S = 0.25
#: the stream of the IMU's specific force, as the leases carry it (its halt names it)
FORCE = "imu specific force"
NO_FORCE = (
    "the IMU sends no acceleration: lift and tilt cannot be checked (the VN-100 needs an "
    "acceleration output: imu.configure_sensor true sets one)"
)


def set_priority(nice: int, who: str) -> None:
    """Run this process at ``nice`` (Linux); say so once if that is not allowed. Nothing is
    asked when it runs at ``nice`` already (systemd's ``Nice=`` for the supervisor)."""
    if os.getpriority(os.PRIO_PROCESS, 0) == nice:
        return
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (PermissionError, OSError) as exc:
        log.warning(
            "%s: cannot run at nice %d (%s); it keeps nice %d (a lower nice needs "
            "CAP_SYS_NICE or RLIMIT_NICE: systemd's LimitNICE=; under a system-call filter, "
            "setpriority allowed: systemd/mowerhw@.service)",
            who,
            nice,
            exc,
            os.getpriority(os.PRIO_PROCESS, 0),
        )


def set_session_priority(nice: int) -> None:
    """With the kernel's autogroup scheduling (``kernel.sched_autogroup_enabled``: the
    processes of one session share one CPU share, outside systemd), a nice value acts only
    among the session's own processes: give the session the same nice, so other work on the
    computer does not take the daemon's share. Under systemd the unit's ``CPUWeight=`` does
    this; nothing happens where there is no autogroup. Only a daemon that leads its own
    session does it: started from a shell (or a test) it would renice the user's whole
    session — found on the bench, where a session left at −10 that way starved the daemon's."""
    if os.getsid(0) != os.getpid():
        log.debug("not a session leader: the session's nice is left as it is")
        return
    path = Path("/proc/self/autogroup")
    try:
        if path.exists():
            path.write_text(str(nice))
    except PermissionError:  # a service user: its cgroup's CPUWeight= is what counts
        log.debug("the daemon's session keeps its nice (no CAP_SYS_NICE)")
    except OSError as exc:
        log.warning("cannot give the daemon's session nice %d (%s)", nice, exc)


def set_realtime(priority: int) -> None:
    """SCHED_FIFO at ``priority`` (Linux), reset on fork: the estimation process it starts
    runs normally. Said once if not allowed."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return
    if os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_FIFO:
        return  # systemd's CPUSchedulingPolicy=fifo did it
    try:
        policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except (PermissionError, OSError) as exc:
        log.warning("the permit supervisor: cannot run SCHED_FIFO %d (%s)", priority, exc)


class Supervisor:
    """``Supervisor(config).run()`` until SIGTERM / SIGINT; the exit status."""

    def __init__(
        self,
        config: Config,
        mode: str | None = None,
        record: Path | None = None,
        child_target: Any = None,
        duration_s: float | None = None,
    ) -> None:
        self.cfg = config
        self.duration_s = duration_s
        self.mode = mode
        self.record = record
        self.child_target = child_target
        self.gate = SupervisorGate(config.supervisor.lease_s, config.supervisor.settle_s)
        #: the streams it checks itself while mowing: the ground speed it reads from CAN, and
        #: the IMU's specific force the leases carry (lift and tilt are judged by it)
        self.stream_gate = PermitGate(
            {"speed": config.speed.stale_after_s, FORCE: config.safety.specific_force_stale_s},
            log_changes=False,
        )
        self._speed = SpeedReader(
            config.speed.source, config.speed.sensor_address, config.speed.ccvs1_direction
        )
        #: the frames it reads (the speed's, the switches'), unless it records every frame:
        #: on SocketCAN the kernel drops the rest of a busy bus before the thread wakes
        reads = self._speed.pgns | {config.safety.switches_pgn}
        #: its source address, claimed on every bus it opens (ISO 11783-5; None: not claimed)
        self.claim: AddressClaim | None = address_claim(config)
        if self.claim is not None:
            reads |= {PGN_ADDRESS_CLAIMED, PGN_REQUEST}
        self.port = CanPort(config, None if record is not None else pgn_filters(reads))
        self.safety = SafetyMonitor(config.safety)
        self._safety_lock = threading.Lock()
        #: the permit frames' sender, while the address is ours on the bus open now
        self.sender: PermitSender | None = None
        self._bus_claimed: can.BusABC | None = None  # the bus the address was claimed on
        self.notifier = Notifier()
        self.stop_requested = ""
        self.child: Any = None
        self.conn: Connection | None = None
        self.child_ready = False
        self._child_heard = -math.inf  # when the estimation process last sent anything
        self._child_hung = False
        self.counts = {
            "leases": 0,
            "frames_forwarded": 0,
            "send_errors": 0,
            "loop_stalls_over_20ms": 0,
        }
        #: decision → frames sent, the newest ``LATENCIES_KEPT``
        self.lease_to_frame_ms: deque[float] = deque(maxlen=LATENCIES_KEPT)
        #: its own halts (a stream it watches silent past its limit): limit → stop frame sent
        self.own_halt_ms: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self.max_loop_lag_ms = 0.0
        self._arrival: dict[str, float | None] = {"speed": None, FORCE: None}
        self._notes: dict[str, tuple[float, str]] = {}  # why a stream's newest data is no use
        self._own_stale = "speed"  # the stream of its newest own halt
        self._send_lock = threading.Lock()
        self._rx: threading.Thread | None = None
        self._rx_died = ""  # why the CAN receive thread ended, if it did
        # the CAN receive thread wakes the loop when a switch frame changes a safety latch
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        #: the estimation process's pipe, readable now? (:meth:`_drain`: per lease)
        self._conn_news: tuple[int, FdWaiter] | None = None
        self._next_status = 0.0
        self._status_permit = False  # the permit of the last status sent down
        self._lifted_told = False  # what the estimation side was last told about a lift
        self._next_watchdog = 0.0
        self.web: WebProcess | None = (
            WebProcess(config, web_child_main) if config.web.enabled else None
        )
        #: what it says when the estimation process (the control socket's server) cannot
        self.status_socket = StatusSocket(config.runtime.control_socket, config.runtime.socket_mode)

    # -------------------------------------------------------------------------- child

    def _start_child(self) -> None:
        from mowerhw.supervisor.child import estimator_main

        ctx = multiprocessing.get_context("spawn")
        parent, child_end = ctx.Pipe(duplex=True)
        target = self.child_target or estimator_main
        self.child = ctx.Process(
            target=target,
            args=(self.cfg, self.mode, self.record, child_end, logging.getLogger().level),
            name="mowerhw-estimation",
            daemon=True,
        )
        self.child.start()
        child_end.close()
        self.conn = parent
        log.info("estimation process started (pid %d)", self.child.pid)

    def _to_child(self, msg: tuple[str, Any]) -> None:
        conn = self.conn
        if conn is None:
            return
        # a dead child: the loop notices it by its sentinel
        with self._send_lock, contextlib.suppress(OSError, EOFError, ValueError):
            conn.send(msg)

    # ----------------------------------------------------------------------------- CAN

    def _receive_crash_only(self) -> None:
        """The CAN receive thread. Crash-only: if it dies, the supervisor ends the service
        (exit 1) rather than go on blind to the ground speed, the switches and the claims."""
        try:
            self._receive()
        except BaseException as exc:
            log.error(
                "the CAN receive thread died (%r): halting the deck and ending the service",
                exc,
                exc_info=exc,
            )
            self._rx_died = f"the CAN receive thread died ({exc!r})"
            with contextlib.suppress(BlockingIOError, OSError):
                os.write(self._wake_w, b"!")

    def _receive(self) -> None:
        """CAN receive loop: the frames the child reads (every frame while it records) down
        to the child; the speed's freshness and the switches here."""
        own = self.cfg.can.source_address
        switches_from = self.cfg.safety.switches_address
        while not self.stop_requested:
            bus = self.port.bus
            if bus is None:
                time.sleep(0.05)
                continue
            try:
                msg = bus.recv(timeout=RX_WAIT_S)
            except Exception as exc:
                if self.port.bus is bus:  # not the one just closed on purpose
                    self.port.failed(time.monotonic(), f"receive failed ({exc})")
                continue
            if msg is None or not msg.is_extended_id:
                continue
            now = time.monotonic()
            data = bytes(msg.data)
            pgn = parse_id(msg.arbitration_id).pgn
            # claims and requests for them (another ECU's claim of our address included)
            if self.claim is not None and pgn in (PGN_ADDRESS_CLAIMED, PGN_REQUEST):
                if self.record is not None:
                    self._to_child(("can", (now, msg.arbitration_id, data, True)))
                if self.claim.received(msg.arbitration_id, data, now):
                    with contextlib.suppress(BlockingIOError, OSError):
                        os.write(self._wake_w, b"!")  # an answer may be due
                continue
            if (msg.arbitration_id & 0xFF) == own:
                continue  # a bus that echoes our own frames (the bench's)
            # the child decodes the ground speed (from every frame its reader reads: the
            # speed's, and the gear's that signs a CCVS1 speed), and records every frame when
            # it records (only what it needs: each frame forwarded is a wake-up of both)
            if pgn in self._speed.pgns or self.record is not None:
                self._to_child(("can", (now, msg.arbitration_id, data, True)))
                self.counts["frames_forwarded"] += 1
            if pgn == self.cfg.safety.switches_pgn:
                if switches_from is not None and msg.arbitration_id & 0xFF != switches_from:
                    continue  # the same proprietary PGN from another ECU: not our switches
                sw = decode_switches(data)
                if sw is not None:
                    with self._safety_lock:
                        before = self.safety.halt(now) is None
                        self.safety.switches(now, sw.lifted, sw.bumped, sw.stop)
                        changed = (self.safety.halt(now) is None) != before
                    if changed:  # the loop decides at once, not at its next deadline
                        with contextlib.suppress(BlockingIOError, OSError):
                            os.write(self._wake_w, b"!")
                continue
            s = self._speed.handle(msg.arbitration_id, data, now)
            if s is not None and s.valid:
                self._arrival["speed"] = now

    def _record_sent(self, msg: can.Message) -> None:
        self._to_child(("can", (time.monotonic(), msg.arbitration_id, bytes(msg.data), True)))

    def _send_frames(self, d: Lease, now: float) -> bool:
        """The frames of decision ``d``; True when this sent the stop of a running deck."""
        if not self.port.ensure(now):
            self.sender = None
            return False
        bus = self.port.bus
        assert bus is not None
        if bus is not self._bus_claimed:  # a bus (re)opened: the address is claimed first
            self._bus_claimed, self.sender = bus, None
            if self.claim is not None:
                self.claim.begin(now)
        on_sent = self._record_sent if self.record is not None else None
        if self.claim is not None and not serve(self.claim, bus, now, on_sent):
            self.sender = None  # the address is not ours (yet): no frame from it
            return False
        if self.sender is None:  # never waits for room on the bus: the loop must not block
            self.sender = permit_sender(self.cfg, bus, now, 0.0, on_sent)
        sender = self.sender
        errors = sender.stats.send_errors
        status = Status(
            d.state, d.permit, d.reason or "NONE", d.signed_distance_m, d.x, d.y, d.heading
        )
        sender.fault = d.reason in (Reason.FAULT, Reason.ESTIMATOR_LATE) and self.child_ready
        stopped = sender.set(d.permit, now, status) and not d.permit
        if stopped and d.decided_at > 0:
            self.lease_to_frame_ms.append(round((time.monotonic() - d.decided_at) * 1e3, 3))
        sender.tick(now)
        if sender.stats.send_errors > errors:
            self.counts["send_errors"] += sender.stats.send_errors - errors
            if sender.stats.send_errors - errors >= 3:
                self.port.failed(now, "sending failed")
        return stopped

    # --------------------------------------------------------------------------- loop

    def _own_halt(self, now: float) -> tuple[str, str] | None:
        if self.stop_requested:
            return Reason.SHUTTING_DOWN, f"the supervisor is stopping ({self.stop_requested})"
        with self._safety_lock:
            unsafe = self.safety.halt(now)
        if unsafe is not None:
            return unsafe
        if self.claim is not None and self.claim.state == "lost":
            holder = self.claim.holder
            return Reason.FAULT, (
                f"CAN source address 0x{self.claim.address:02X} is held by another ECU"
                + (f" ({holder.describe()})" if holder is not None else "")
            )
        if self.lease_mow():
            stale = self.stream_gate.stale(now, self._arrival, self._notes)
            if stale is not None and stale[0] == FORCE and now > self.gate.lease_expires():
                stale = None  # the force comes with the leases: the lease's halt says why
            if stale is not None:
                self._own_stale = stale[0]
                return Reason.SENSOR_STALE, f"{stale[1]} (seen by the supervisor)"
        return None

    def lease_mow(self) -> bool:
        """The estimator is mowing (its newest lease is about mowing, permitted or not)."""
        return self.gate.lease.reason not in (Reason.NOT_MOWING, Reason.SHUTTING_DOWN)

    def request_stop(self, why: str) -> None:
        if not self.stop_requested:
            log.warning("supervisor: stopping (%s): halting the deck", why)
        self.stop_requested = why

    def run(self) -> int:
        previous = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                previous[sig] = signal.signal(
                    sig, lambda s, f: self.request_stop(signal.Signals(s).name)
                )
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        try:
            return self._run()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            with contextlib.suppress(OSError):  # as it was (a test runs it in-process)
                os.setpriority(os.PRIO_PROCESS, 0, nice)
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    def _run(self) -> int:
        set_priority(self.cfg.supervisor.nice, "the permit supervisor")
        set_session_priority(self.cfg.supervisor.nice)
        set_realtime(self.cfg.supervisor.realtime_priority)
        self.port.ensure(time.monotonic())
        self._rx = threading.Thread(target=self._receive_crash_only, name="can-rx", daemon=True)
        self._rx.start()
        self.status_socket.open()
        self._start_child()
        if self.web is not None:
            self.web.start()
        assert self.conn is not None and self.child is not None
        conn_fd, child_fd = self.conn.fileno(), self.child.sentinel
        waiter = FdWaiter((conn_fd, child_fd, self._wake_r))
        started = time.monotonic()
        status = 0
        while True:
            now = time.monotonic()
            due = now + TICK_MAX_S
            if self.sender is not None:
                due = min(due, self.sender.next_due())
            if self.claim is not None and self.port.bus is not None:
                due = min(due, self.claim.next_due())
            expires = self.gate.lease_expires()
            if expires > now:
                due = min(due, expires + 1e-4)
            if self.lease_mow():
                due = min(due, self.stream_gate.next_stale_deadline(now, self._arrival) + 1e-4)
            listener = self.status_socket.listener(now)
            listener_fd = None if listener is None else listener.fileno()
            ready = waiter.wait(max(0.0005, due - now), listener_fd)
            before, now = now, time.monotonic()
            if now - before > 1.0:
                # this process itself did not run for a second (the computer paused): the
                # estimation process's silence is not its own; it gets a new window
                self._child_heard = max(self._child_heard, now)
            if self._wake_r in ready:
                with contextlib.suppress(BlockingIOError, OSError):
                    os.read(self._wake_r, 4096)
            if not ready:  # woke on its own deadline: how late (a busy or starved process)
                self._loop_lag((now - due) * 1e3)
            if conn_fd in ready:
                self._drain(now)
            if child_fd in ready or not self.child.is_alive():
                self.child.join(timeout=1.0)  # for its exit code
                if not self.stop_requested:
                    log.error(
                        "the estimation process died (exit code %s): halting the deck and "
                        "ending the service",
                        self.child.exitcode,
                    )
                    status = 1
                self.request_stop("the estimation process ended")
                break
            if self._rx_died:
                self.request_stop(self._rx_died)
                status = 1
                break
            if self.duration_s is not None and now - started > self.duration_s:
                self.request_stop("duration")
            if self.stop_requested:
                break
            if not self.child_ready and now - started > self.cfg.supervisor.child_start_timeout_s:
                log.error(
                    "the estimation process did not start within %.0f s",
                    self.cfg.supervisor.child_start_timeout_s,
                )
                self.request_stop("estimation start-up timed out")
                status = 1
                break
            silent = now - self._child_heard
            if self.counts["leases"] and silent > self.cfg.supervisor.child_hang_s:
                # alive but hung (a deadlock, a blocked read): the lease halted the deck
                # long ago; only a restart brings it back
                log.error(
                    "the estimation process has sent nothing for %.1f s (limit %g s, "
                    "supervisor.child_hang_s): it is hung; killing it, halting the deck and "
                    "ending the service",
                    silent,
                    self.cfg.supervisor.child_hang_s,
                )
                self._child_hung = True
                self.request_stop("the estimation process hung")
                status = 1
                break
            self._decide(now)
            if listener_fd is not None and listener_fd in ready:  # after the decision: it says it
                self.status_socket.serve(lambda: self.socket_status(time.monotonic()))
            if self.web is not None:
                self.web.check(now)
            # the loop's own work holds everything else up as long (a lateness the wake-up
            # on a message cannot show: the message's wait is not measured)
            self._loop_lag((time.monotonic() - now) * 1e3)
        self._shutdown(status)
        return status

    def _loop_lag(self, lag_ms: float) -> None:
        """Count ``lag_ms`` the loop ran late (woken past its deadline, or busy that long)."""
        self.max_loop_lag_ms = max(self.max_loop_lag_ms, lag_ms)
        if lag_ms > LOOP_STALL_MS:
            self.counts["loop_stalls_over_20ms"] += 1

    def _drain(self, now: float) -> None:
        assert self.conn is not None
        try:
            fd = self.conn.fileno()
            if self._conn_news is None or self._conn_news[0] != fd:
                self._conn_news = (fd, FdWaiter((fd,)))
            while self._conn_news[1].ready_now():
                kind, body = self.conn.recv()
                self._child_heard = now
                if kind == "lease":
                    lease = Lease.from_wire(body)
                    self.gate.renew(lease, now)
                    self.counts["leases"] += 1
                    with self._safety_lock:  # every sample's force, the lease's last
                        for t, fx, fy, fz in lease.earlier_forces:
                            self.safety.imu(t, (fx, fy, fz))
                        self.safety.imu(lease.decided_at, lease.accel)
                    if all(math.isfinite(a) for a in lease.accel):
                        self._arrival[FORCE] = now
                    else:
                        self._notes[FORCE] = (now, NO_FORCE)
                elif kind == "fault" and body.get("kind") == "can-down":
                    self.port.take_away(now, float(body.get("seconds", 3.0)))
                elif kind == "ready":
                    self.child_ready = True
                    self.notifier.ready("supervisor: estimation running")
                    log.info("estimation process running; permit supervisor ready")
        except (OSError, EOFError):
            pass  # a dead child: its sentinel says so

    def _decide(self, now: float) -> None:
        own = self._own_halt(now)
        d = self.gate.decide(now, own)
        if self._send_frames(d, now) and own is not None and own[0] == Reason.SENSOR_STALE:
            # the deck ran until the supervisor's own check stopped it: how long after the limit
            stream = (self._own_stale, "")
            limit = self.stream_gate.revealed_at(now, stream, self._arrival, None)
            self.own_halt_ms.append(round((time.monotonic() - limit) * 1e3, 3))
        lifted = own is not None and own[0] == Reason.LIFTED
        if lifted != self._lifted_told:  # the localizer gives its pose up while lifted
            self._lifted_told = lifted
            self._to_child(("lifted", lifted))
        if now >= self._next_status or d.permit != self._status_permit:
            # every STATUS_PERIOD_S, and at once when the deck's permit changes: the status
            # page shows the supervisor's own halts (tilt, a bump, a late estimator) by it
            self._next_status, self._status_permit = now + STATUS_PERIOD_S, d.permit
            self._to_child(("status", self.status(now)))
        self._watchdog(now)

    def _watchdog(self, now: float) -> None:
        period = self.notifier.watchdog_period_s
        if period is None or now < self._next_watchdog:
            return
        down = self.port.down_since
        if down is not None and now - down > self.cfg.supervisor.can_down_restart_s:
            if self._next_watchdog != math.inf:
                log.error(
                    "CAN unusable for %.0f s: no more watchdog pings (systemd restarts "
                    "the service)",
                    now - down,
                )
            self._next_watchdog = math.inf
            return
        self._next_watchdog = now + period
        self.notifier.watchdog()

    def status(self, now: float) -> dict[str, Any]:
        d = self.gate.current
        age = None if self.gate.received_at is None else round(now - self.gate.received_at, 4)
        return {
            "permit": d.permit,
            "reason": d.reason,
            "detail": d.detail,
            "lease_age_s": age,
            "lease_s": self.gate.lease_s,
            "can_up": self.port.bus is not None,
            "can_reopens": max(0, self.port.reopens - 1),
            "can_errors": self.port.errors,
            "can_address": self.claim.status() if self.claim is not None else None,
            "lease_to_frame_ms": _percentiles(self.lease_to_frame_ms),
            "own_halt_ms": _percentiles(self.own_halt_ms),
            "max_loop_lag_ms": round(self.max_loop_lag_ms, 2),
            "tilt_deg": round(self.safety.tilt_deg, 1),
            "lease_expired": self.gate.expired,
            "permit_sender": vars(self.sender.stats) if self.sender else {},
            "web": self.web.status() if self.web is not None else None,
            "status_socket": {
                "answered": self.status_socket.answered,
                "dropped": self.status_socket.dropped,
            },
            **self.counts,
        }

    def socket_status(self, now: float) -> dict[str, Any]:
        """What its status socket answers: its status, and the estimation process's state
        (the control socket is that process's: this is heard when it is silent)."""
        child = self.child
        alive = child is not None and child.is_alive()
        heard = self._child_heard
        return {
            "ok": True,
            "who": "supervisor",
            "pid": os.getpid(),
            **self.status(now),
            "estimation": {
                "pid": child.pid if alive else None,
                "alive": alive,
                "ready": self.child_ready,
                "silent_s": round(now - heard, 3) if math.isfinite(heard) else None,
                "hang_limit_s": self.cfg.supervisor.child_hang_s,
            },
        }

    def _shutdown(self, status: int) -> None:
        now = time.monotonic()
        self.notifier.stopping()
        held = self.claim is None or self.claim.holds(now)  # else: not ours to send from
        if self.sender is not None and held:
            if status:
                self.sender.fault = True
                self.sender.error(now)
            else:
                self.sender.shutdown(now)
        self._to_child(("stop", None))
        self.status_socket.close()
        if self.web is not None:
            self.web.stop()
        if self.child is not None:
            if self._child_hung:  # it would not stop: no time lost on it (logged above)
                self.child.kill()
            self.child.join(timeout=3.0)  # within systemd's TimeoutStopSec (5 s)
            if self.child.is_alive():  # stalled: it cannot even handle a SIGTERM
                log.error("the estimation process did not stop: killing it")
                self.child.kill()
                self.child.join(timeout=1.0)
        if self._rx is not None:  # before the bus closes under it (no "receive failed")
            self._rx.join(timeout=2 * RX_WAIT_S)  # it sees stop_requested within RX_WAIT_S
        if self.port.bus is not None:
            with contextlib.suppress(Exception):
                self.port.bus.shutdown()
        if self._rx is None or not self._rx.is_alive():  # else it may still write: left open
            for fd in (self._wake_r, self._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)
        log.info("supervisor stopped")


def run_supervised(
    config: Config,
    mode: str | None = None,
    record: Path | None = None,
    duration_s: float | None = None,
) -> int:
    """``mowerhw run`` with the permit supervisor: the exit status."""
    return Supervisor(config, mode, record, duration_s=duration_s).run()


def _percentiles(values: Collection[float]) -> dict[str, float | int | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    v = sorted(values)
    return {
        "p50": v[len(v) // 2],
        "p99": v[min(len(v) - 1, int(0.99 * len(v)))],
        "max": v[-1],
        "n": len(v),
    }
