"""Ray execution: a pool of worker actors, each running one trial at a time.

Workers never touch the database. A worker runs ``agent.train`` (or any function with its
signature) and buffers what the trial reports and records (episode videos, as bytes); the
driver drains the buffers with small remote calls and learns of finished, failed and
lost trials through ``WorkerPool.poll``. An exception inside a trial comes back as a value
(message and traceback); a worker that dies (killed, out of memory, node lost) comes back
as a ``Lost`` event, and the pool replaces the actor. Its one job: running trials on Ray,
with Ray's own start, stop and output (``start_ray``, ``stop_ray``) beside it.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray
import ray._private.worker as ray_worker
from ray._private import ray_constants
from ray._private.authentication import authentication_token_setup

from sweeper.run import _reaper as reaper

#: Ray's switch between cluster mode (listen on every interface) and a single machine
LOOPBACK_VARIABLE = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
#: set it (to 1) to have a local Ray collect and export metrics
METRICS_VARIABLE = "RAY_enable_metrics_collection"


def start_ray(address: str | None, num_cpus: int | None = None) -> bool:
    """Connect to Ray; return True if this call started it (so the caller shuts it down,
    with ``stop_ray``).

    ``address=None`` starts a fresh local instance (``address="local"``: a plain
    ``ray.init()`` would attach to whatever cluster a stale /tmp/ray file names) that
    listens on 127.0.0.1 only and exports no metrics unless ``RAY_enable_metrics_collection``
    says so, with a reaper beside it (``sweeper.run._reaper``): none of its processes outlives
    this one, even after a SIGKILL. An already initialised Ray (e.g. in a notebook or a
    test) is used as it is. This process's SIGTERM handler is the same after the call
    (``_keep_sigterm``), and Ray's own noise stays out of the launch's output
    (``_quiet_ray``).
    """
    if ray.is_initialized():
        return False
    common = {"log_to_driver": False, "logging_level": "WARNING"}
    if address is None:
        metrics = {} if METRICS_VARIABLE in os.environ else {"enable_metrics_collection": False}
        with _loopback_only(), _keep_sigterm(), _quiet_ray(), _reaped():
            ray.init(
                address="local",
                num_cpus=num_cpus,
                include_dashboard=False,
                _node_ip_address="127.0.0.1",
                _system_config=metrics,
                **common,
            )
    else:
        _check_reachable(address)
        with _keep_sigterm(), _quiet_ray():
            ray.init(address=address, **common)
    return True


def stop_ray() -> None:
    """Shut down the Ray ``start_ray`` started; its reaper then kills what is left of it
    (a process slow to go) and exits, before this returns."""
    try:
        ray.shutdown()
    finally:
        _stop_reaper()


#: the reaper of the local Ray this process started, and the write end of its pipe
_reaper: tuple[subprocess.Popen, int] | None = None


def _children() -> set[int]:
    """This process's children."""
    return reaper.children(os.getpid())


@contextlib.contextmanager
def _reaped() -> Iterator[None]:
    """Start a reaper (``sweeper.run._reaper``) before the block starts a local Ray, and name
    it the processes the block started, the Ray's roots, after it."""
    global _reaper
    _stop_reaper()  # one from a Ray shut down without stop_ray
    before = _children()
    read, write = os.pipe()  # the write end is this process's alone (not inherited)
    try:
        process = subprocess.Popen(
            [sys.executable, "-I", str(Path(reaper.__file__)), str(read)],
            pass_fds=(read,),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
        )
    except BaseException:
        os.close(write)
        raise
    finally:
        os.close(read)
    _reaper = process, write
    try:
        yield
    except BaseException:  # a Ray that failed to start: the reaper kills what it left
        _stop_reaper()
        raise
    roots = _children() - before - {process.pid}
    with contextlib.suppress(OSError):  # a reaper that died: nothing to tell it
        os.write(write, (" ".join(map(str, sorted(roots))) + "\n").encode())


def _stop_reaper(timeout: float = 2 * reaper.KILL_WAIT) -> None:
    """Close the reaper's pipe and wait for it to have killed what is left and exited."""
    global _reaper
    if _reaper is None:
        return
    process, write = _reaper
    _reaper = None
    os.close(write)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


#: how Ray's raylet reports a dead worker to the driver (the driver's own line about the
#: lost trial says it, ``Lost``; the full text stays in the trial's ``worker_deaths``)
WORKER_DIED = "A worker died or was killed"


def _without_worker_deaths(print_to_stdstream: Callable[..., None]) -> Callable[..., None]:
    """Ray's printer of the errors its raylet sends the driver, without worker deaths."""

    @functools.wraps(print_to_stdstream)
    def printer(data: dict[str, Any], *args: Any, **kwargs: Any) -> None:
        if data.get("pid") == "raylet" and "".join(data.get("lines", ())).startswith(WORKER_DIED):
            return
        print_to_stdstream(data, *args, **kwargs)

    printer.sweeper_quiet = True  # type: ignore[attr-defined]
    return printer


@contextlib.contextmanager
def _quiet_ray() -> Iterator[None]:
    """Keep Ray's noise out of a launch's output while the block connects to Ray, and
    after: the warning that token authentication is on, which a new local Ray prints at
    every start (the mode is left as Ray sets it: on, unless ``RAY_AUTH_MODE`` says
    otherwise), and the multi-line text the raylet sends for every dead worker, which the
    driver's thread listening for Ray's errors prints beside sweeper's own line (that
    thread runs whatever ``log_to_driver`` says; other errors are still printed).
    """
    if not getattr(ray_worker.print_to_stdstream, "sweeper_quiet", False):
        ray_worker.print_to_stdstream = _without_worker_deaths(ray_worker.print_to_stdstream)
    auth = logging.getLogger(authentication_token_setup.__name__)
    level = auth.level
    auth.setLevel(logging.ERROR)
    try:
        yield
    finally:
        auth.setLevel(level)


@contextlib.contextmanager
def _keep_sigterm() -> Iterator[None]:
    """Give this process its SIGTERM handler back after ``ray.init``, which sets its own:
    Python ones that exit (status 15 or 1: a SIGTERM while Ray starts raises SystemExit),
    and, in its core worker, a C++ failure handler that prints a stack dump and may abort.
    That one is not installed in this process at all (Ray reads the switch when it creates
    the core worker; the processes Ray starts keep theirs), so a SIGTERM at any moment
    reaches the caller's handler or SystemExit. The cost: no C++ stack dump if the
    driver's own core worker crashes.
    """
    saved = ray_constants.RAY_DISABLE_FAILURE_SIGNAL_HANDLER
    handler = signal.getsignal(signal.SIGTERM)
    ray_constants.RAY_DISABLE_FAILURE_SIGNAL_HANDLER = True
    try:
        yield
    finally:
        ray_constants.RAY_DISABLE_FAILURE_SIGNAL_HANDLER = saved
        if handler is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, handler)


@contextlib.contextmanager
def _loopback_only() -> Iterator[None]:
    """Start Ray in its single-machine mode (the one it uses on macOS and Windows): every
    Ray process binds to 127.0.0.1, where by default they listen on all interfaces and
    anyone who reaches one can run code here.

    The switch is an environment variable read by each Ray process when it starts, and by
    this one when it imported ray (then copied into ``ray_constants``), so both are set
    while Ray starts; its processes keep it, this one gets its own values back.
    """
    saved = os.environ.get(LOOPBACK_VARIABLE), ray_constants.ENABLE_RAY_CLUSTER
    os.environ[LOOPBACK_VARIABLE] = "0"
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        if saved[0] is None:
            os.environ.pop(LOOPBACK_VARIABLE, None)
        else:
            os.environ[LOOPBACK_VARIABLE] = saved[0]
        ray_constants.ENABLE_RAY_CLUSTER = saved[1]


def _check_reachable(address: str, timeout: float = 10.0) -> None:
    """Raise ``Unreachable`` if ``host:port`` does not accept connections: ``ray.init``
    would retry for minutes. Other forms ("auto") are left to Ray."""
    host, _, port = address.split("://")[-1].rpartition(":")
    if not host or not port.isdigit():
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise Unreachable(f"nothing answers at {host}:{port} ({e})") from None


class Unreachable(ConnectionError):
    """Nothing accepts connections at the Ray address."""


@ray.remote
class TrialWorker:
    """Runs one trial at a time; a second thread answers ``drain`` while a trial runs.

    With ``train=None`` it runs ``agent.train``, imported here with the module of ``env``
    (torch, MuJoCo: seconds), so the import overlaps the driver's start-up instead of
    delaying the first trial.
    """

    def __init__(self, train: Callable[..., Any] | None = None, env: str | None = None) -> None:
        # headless rendering unless the node says otherwise; set here, not as a Ray
        # runtime_env, which would cost each actor a fresh worker process (~1 s)
        os.environ.setdefault("MUJOCO_GL", "egl")
        if train is None:
            # an import that fails here fails again in run(), which reports it as the error
            with contextlib.suppress(Exception):
                import agent.trial  # noqa: F401  (torch and the SAC agent)
                from agent.envs import env_class

                if env is not None:
                    env_class(env)
        self._train = train
        self._lock = threading.Lock()
        self._events: list[tuple[str, Any, Any]] = []

    def ping(self) -> bool:
        """Answers once the actor is placed and started (the pool counts only those)."""
        return True

    def run(self, token: str, config: Any) -> dict[str, Any]:
        """Run ``train(config, report)``: ``{"result"}`` or ``{"error", "traceback"}``, and
        ``"events"``: the reports not drained yet."""
        with self._lock:
            self._events = []
        where = {"node": ray.util.get_node_ip_address(), "pid": os.getpid()}
        self._push(token, "where", where)
        try:
            train = self._train
            if train is None:
                from agent import train
            calls: dict[str, Any] = {
                "report": lambda step, metrics: self._push(token, step, metrics)
            }
            parameters = inspect.signature(train).parameters
            if "record" in parameters:  # agent.train's videos
                calls["record"] = lambda name, data: self._push(
                    token, "recorded", {"filename": name, "data": data}
                )
            if "notice" in parameters:  # agent.train's corrupt checkpoint, discarded
                calls["notice"] = lambda message: self._push(token, "notice", {"message": message})
            result = train(config, **calls)
            outcome: dict[str, Any] = {"result": result}
        except Exception as e:
            outcome = {"error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
        outcome["events"] = self.drain()  # what no drain call has fetched yet
        return outcome

    def drain(self) -> list[tuple[str, Any, Any]]:
        """Events since the last drain: ``(token, "where", {...})``, ``(token, step, metrics)``,
        ``(token, "recorded", {"filename", "data"})``, ``(token, "notice", {"message"})``."""
        with self._lock:
            events, self._events = self._events, []
        return events

    def _push(self, token: str, step: Any, payload: Any) -> None:
        with self._lock:
            self._events.append((token, step, dict(payload)))


def _last_error_line(error: BaseException) -> str:
    """The line of a Ray error that names the cause (``ModuleNotFoundError: ...``)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    causes = [line for line in lines if "Error:" in line and not line.startswith("ray.")]
    return (causes or lines or [type(error).__name__])[-1]


@dataclass(frozen=True)
class Started:
    token: str
    where: dict[str, Any]  # {"node": ip, "pid": worker pid}


@dataclass(frozen=True)
class Reported:
    token: str
    step: int
    metrics: dict[str, float]


@dataclass(frozen=True)
class Recorded:
    token: str
    filename: str
    data: bytes  # a file the trial made (an episode video)


@dataclass(frozen=True)
class Noticed:
    token: str
    message: str  # one line the user should see (a corrupt checkpoint discarded)


@dataclass(frozen=True)
class Finished:
    token: str
    result: Any  # what train returned


@dataclass(frozen=True)
class Errored:
    token: str
    error: str
    traceback: str


@dataclass(frozen=True)
class Lost:
    token: str
    error: str  # why Ray says the worker is gone


Event = Started | Reported | Recorded | Noticed | Finished | Errored | Lost


@dataclass
class _Slot:
    actor: Any
    ready_ref: Any  # ping(): answers once the actor runs; None once it has
    token: str | None = None
    run_ref: Any = None
    drain_ref: Any = None
    answered: float = 0.0  # monotonic time of the trial's start or its last drain answer

    def stalled(self, now: float, timeout: float) -> str | None:
        """Why the trial looks hung, or None: its worker's second thread answers ``drain``
        within milliseconds while the process runs, so ``timeout`` s without an answer
        means a stopped process or node (which Ray never reports as dead)."""
        if now - self.answered > timeout:
            return f"no answer from the worker for {now - self.answered:.0f} s"
        return None


class WorkersCannotStart(RuntimeError):
    """The worker actors fail to start, again and again (``WorkerPool.START_FAILURES`` in
    a row with none started): an import error in the workers, say, which no retry cures."""


class WorkerPool:
    """``size`` actors with ``cpus``/``gpus`` each; one trial per actor at a time.

    Only actors that have started count as idle: after a node is lost, a replacement
    actor may wait for resources indefinitely, and a trial handed to it would wait too.
    ``train`` and ``env`` are passed to each ``TrialWorker``. A busy actor that stalls
    (``_Slot.stalled`` with ``stall_timeout``) is killed and reported ``Lost``, as Ray
    never notices a stopped process. An actor that dies while starting is replaced; after
    ``START_FAILURES`` such deaths in a row, ``idle`` raises ``WorkersCannotStart``.
    """

    START_FAILURES = 5

    def __init__(
        self,
        size: int,
        cpus: float = 1,
        gpus: float = 0,
        train: Callable[..., Any] | None = None,
        env: str | None = None,
        stall_timeout: float = 600.0,
    ) -> None:
        self._stall_timeout = stall_timeout
        self._options = {
            "num_cpus": cpus,
            "num_gpus": gpus,
            "max_concurrency": 2,  # run + drain
        }
        self._train, self._env = train, env
        self._start_failures = 0  # actors that died starting, since one last started
        self._slots = [self._new_slot() for _ in range(size)]

    def _new_slot(self) -> _Slot:
        actor = TrialWorker.options(**self._options).remote(self._train, self._env)
        return _Slot(actor, actor.ping.remote())

    def shrink(self, size: int) -> None:
        """Keep at most ``size`` actors, killing idle ones (e.g. when few trials are left)."""
        excess = max(0, len(self._slots) - size)
        for slot in [slot for slot in self._slots if slot.token is None][:excess]:
            ray.kill(slot.actor)
            self._slots.remove(slot)

    def __len__(self) -> int:
        return len(self._slots)

    def _ready(self, index: int) -> bool:
        """Whether slot ``index``'s actor has started; one that died is replaced."""
        slot = self._slots[index]
        if slot.ready_ref is None:
            return True
        if not ray.wait([slot.ready_ref], timeout=0)[0]:
            return False
        try:
            ray.get(slot.ready_ref)
        except ray.exceptions.RayError as e:
            ray.kill(slot.actor)
            self._start_failures += 1
            if self._start_failures >= self.START_FAILURES:
                raise WorkersCannotStart(
                    f"the trial workers failed to start {self._start_failures} times in a "
                    f"row; the last: {_last_error_line(e)}"
                ) from e
            self._slots[index] = self._new_slot()
            return False
        self._start_failures = 0
        slot.ready_ref = None
        return True

    def _idle_slots(self) -> list[_Slot]:
        return [
            self._slots[i]
            for i in range(len(self._slots))
            if self._slots[i].token is None and self._ready(i)
        ]

    @property
    def idle(self) -> int:
        """How many started actors have no trial."""
        return len(self._idle_slots())

    def submit(self, token: str, config: Any) -> None:
        """Start ``config`` on an idle actor; ``token`` names it in the events."""
        slot = self._idle_slots()[0]
        slot.token, slot.run_ref = token, slot.actor.run.remote(token, config)
        slot.answered = time.monotonic()

    def poll(self, timeout: float = 1.0) -> list[Event]:
        """Wait up to ``timeout`` s for a trial to end or an actor to start; return what
        happened meanwhile.

        Each busy actor has at most one ``drain`` call in flight, collected when it
        answers, so no report is dropped and a slow actor never blocks the others.
        """
        busy = [slot for slot in self._slots if slot.token is not None]
        starting = [self._slots[i].ready_ref for i in range(len(self)) if not self._ready(i)]
        for slot in busy:
            if slot.drain_ref is None:
                slot.drain_ref = slot.actor.drain.remote()
        refs = [slot.run_ref for slot in busy]
        if not refs + starting:
            time.sleep(timeout)
        else:
            ray.wait(refs + starting, num_returns=1, timeout=timeout)
        if not refs:
            return []
        done, _ = ray.wait(refs, num_returns=len(refs), timeout=0)
        events: list[Event] = []
        for slot in busy:
            if slot.run_ref in done:  # a drain in flight holds reports older than run's
                ray.wait([slot.drain_ref], timeout=10)
            events += self._collect_drain(slot)
        now = time.monotonic()
        for index, slot in enumerate(self._slots):
            why = slot.token and slot.run_ref not in done and slot.stalled(now, self._stall_timeout)
            if why:
                events.append(Lost(slot.token, f"{why}: hung or stopped; killed"))
                ray.kill(slot.actor)
                self._slots[index] = self._new_slot()
        for index, slot in enumerate(self._slots):
            if slot.token is None or slot.run_ref not in done:
                continue
            token = slot.token
            try:
                outcome = ray.get(slot.run_ref)
            except ray.exceptions.RayError as e:
                events.append(Lost(token, f"{type(e).__name__}: {one_line(e)}"))
                ray.kill(slot.actor)
                self._slots[index] = self._new_slot()
                continue
            events += self._events(slot, outcome["events"])
            slot.token, slot.run_ref = None, None
            if "error" in outcome:
                events.append(Errored(token, outcome["error"], outcome["traceback"]))
            else:
                events.append(Finished(token, outcome["result"]))
        return events

    def _collect_drain(self, slot: _Slot) -> list[Event]:
        """The slot's drained events, if its drain call has answered."""
        ready, _ = ray.wait([slot.drain_ref], timeout=0)
        if not ready:
            return []
        slot.drain_ref = None
        try:
            drained = ray.get(ready[0])
        except ray.exceptions.RayError:
            return []  # the worker is gone; its run ref says so
        slot.answered = time.monotonic()
        return self._events(slot, drained)

    @staticmethod
    def _events(slot: _Slot, drained: list[tuple[str, Any, Any]]) -> list[Event]:
        events: list[Event] = []
        for token, step, payload in drained:
            if token != slot.token:
                continue
            if step == "where":
                events.append(Started(token, payload))
            elif step == "recorded":
                events.append(Recorded(token, payload["filename"], payload["data"]))
            elif step == "notice":
                events.append(Noticed(token, payload["message"]))
            else:
                events.append(Reported(token, int(step), payload))
        return events

    def shutdown(self) -> None:
        """Kill every actor (a trial in flight stops at once; its checkpoint stays)."""
        for slot in self._slots:
            ray.kill(slot.actor)
        self._slots = []


def one_line(error: BaseException, limit: int = 2000) -> str:
    """The message of ``error`` (Ray's are long, coloured, multi-line) on one line, without
    terminal colours, cut at ``limit`` characters."""
    text = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", str(error)).split())
    return (text[:limit] + " ...") if len(text) > limit else text or "no message"


def resources_fit(cpus: float, gpus: float) -> int:
    """How many trials of ``cpus``/``gpus`` the connected cluster can hold at once."""
    total = ray.cluster_resources()
    fits = int(total.get("CPU", 0) // cpus) if cpus else 1 << 30
    if gpus:
        fits = min(fits, int(total.get("GPU", 0) // gpus))
    return fits
