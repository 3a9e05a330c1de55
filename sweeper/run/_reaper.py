"""The reaper of a local Ray: no Ray process outlives the driver that started it.

Ray ties what ``ray.init`` starts (GCS, raylet, dashboard, monitors) to the driver with
``PR_SET_PDEATHSIG``, and its workers exit when their raylet does; but the raylet's own
children, ``ray::DashboardAgent`` and ``ray::RuntimeEnvAgent``, are not tied: when the
raylet dies unexpectedly they try to report it to the GCS, which is dead too, and wait for
its 60 s timeout (``ray._private.process_watcher.report_raylet_error_logs``), reparented
to init. A driver killed with SIGKILL left them behind, so a local Ray is started with this
reaper beside it (``sweeper.run._execution.start_ray``).

The reaper is a child of the driver, run from this file with the standard library only.
It holds the read end of a pipe whose write end only the driver holds: the end of file
means the driver is gone (however it went: exit, SIGKILL) or has shut its Ray down
(``stop_ray``). Until then it records, every ``INTERVAL`` seconds, the processes of the
driver's Ray: the roots the driver names on the pipe once ``ray.init`` returned (before
that, every child the driver started since the reaper did) and all their descendants,
each with its start time (so a recycled pid is never taken for one). Then it kills every
one of them still alive, waits for them to go, and exits. It ignores SIGINT and SIGTERM,
which a terminal or ``kill -- -PGID`` sends to the driver's whole process group: it must
outlive the driver to clean up after it.

The driver's side: ``python reaper.py FD``, then ``ROOT ROOT ...\\n`` on the pipe.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
import time
from collections.abc import Iterable

#: seconds between two looks at the driver's Ray processes, once it is up; quicker while
#: it starts, when the raylet forks its agents
INTERVAL = 1.0
START_INTERVAL = 0.2
START_SECONDS = 15.0
#: seconds the reaper waits for the processes it killed to be gone
KILL_WAIT = 5.0

#: a process: its pid and its start time (clock ticks after boot, /proc/PID/stat field 22)
Process = tuple[int, int]


def start_time(pid: int) -> int | None:
    """The start time of process ``pid``, or None when there is none (or a zombie: dead)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    fields = stat[stat.rfind(b")") + 2 :].split()
    if fields[0] == b"Z":
        return None
    return int(fields[19])


def children(pid: int) -> set[int]:
    """The children of process ``pid`` (of any of its threads)."""
    found: set[int] = set()
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return found
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children", "rb") as f:
                found.update(int(child) for child in f.read().split())
        except OSError:
            continue
    return found


def alive(process: Process) -> bool:
    """Whether ``process`` still runs (the same pid and start time, not a zombie)."""
    return start_time(process[0]) == process[1]


class Reaper:
    """The processes of one driver's Ray, recorded until the driver is gone."""

    def __init__(self, driver: int) -> None:
        self.driver = driver
        #: the driver's children before the reaper started: not its Ray's
        self.before = children(driver)
        self.roots: set[int] | None = None  # named by the driver once Ray is up
        self.known: set[Process] = set()

    def candidates(self) -> set[int]:
        """The driver's children that belong to its Ray: the roots it named, or, before it
        named them, every child it started since the reaper did."""
        if self.roots is not None:
            return self.roots
        return children(self.driver) - self.before - {os.getpid()}

    def look(self) -> None:
        """Record the driver's Ray processes alive now: the candidates and their descendants."""
        todo = list(self.candidates() | {p[0] for p in self.known if alive(p)})
        seen: set[int] = set()
        while todo:
            pid = todo.pop()
            if pid in seen or pid == os.getpid():
                continue
            seen.add(pid)
            started = start_time(pid)
            if started is None:
                continue
            self.known.add((pid, started))
            todo.extend(children(pid))
        self.known = {p for p in self.known if alive(p)}

    def name_roots(self, pids: Iterable[int]) -> None:
        """The driver's Ray is up: only these children (and their descendants) are its."""
        self.roots = set(pids)
        others = children(self.driver) - self.roots
        self.known = {p for p in self.known if p[0] not in others}

    def kill(self) -> None:
        """SIGKILL every recorded process still alive and wait (bounded) until they are gone."""
        self.look()
        for pid, started in sorted(self.known):
            if start_time(pid) == started:
                with contextlib.suppress(OSError):  # gone meanwhile
                    os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + KILL_WAIT
        while any(alive(p) for p in self.known) and time.monotonic() < deadline:
            time.sleep(0.05)


def main(argv: list[str]) -> int:
    """``reaper.py FD``: watch the driver (the parent) until FD reads end of file."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    fd = int(argv[1])
    reaper = Reaper(os.getppid())
    started, pending = time.monotonic(), b""
    while True:
        quick = time.monotonic() - started < START_SECONDS
        ready, _, _ = select.select([fd], [], [], START_INTERVAL if quick else INTERVAL)
        if ready:
            data = os.read(fd, 4096)
            if not data:
                break
            pending += data
            if b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                reaper.name_roots(int(pid) for pid in line.split())
        reaper.look()
    reaper.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
