"""Driving a study on Ray; the driver is the only writer.

``prepare`` validates everything first (spec, env and encoder options, storage URL), and
``launch`` checks that the database can be written and that Ray can be reached before it
opens the study, so a bad input exits with code 2 and writes nothing. Then it creates or
loads the study, gives every plan key that is not done a WAITING trial
(``StudyStore.sync``), and a ``Driver`` hands the keys to a pool of Ray worker actors, one
trial per actor at a time. Reports stream back as intermediate values; a finished trial is
told its AUC.

Failures: a worker that dies, or stops answering for ``execution.stall_timeout`` s, is
replaced and the trial re-run from its checkpoint, with the same parameters and seed, in
the same Optuna trial, up to ``execution.retries`` times.
An exception inside a trial is not retried (a seeded trial fails the same way again): the
trial is FAIL with ``error`` and ``traceback``, and the next launch re-runs it.
Ctrl-C or SIGTERM, at any moment of a launch, stops the workers and marks the trials in
flight ``interrupted``; a relaunch resumes them from their checkpoints. Exit codes: 0 all
done, 1 some trials failed, 2 bad input, 3 another driver runs the study (busy), 130
interrupted. What trials print goes to Ray's worker logs (``/tmp/ray/session_latest/logs``),
not to the progress display.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import signal
import sys
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import optuna
import ray

from agent.config import Outcome, TrialResult
from agent.envs import env_class
from agent.metrics import metric_key
from agent.storage_io import CHECKPOINT_FILE, exists, is_uri, join, remove
from sweeper import random_agent
from sweeper.artifacts import ArtifactStore, artifact_location, upload_once
from sweeper.execution import (
    Errored,
    Event,
    Finished,
    Lost,
    Recorded,
    Reported,
    Started,
    Unreachable,
    WorkerPool,
    one_line,
    resources_fit,
    start_ray,
)
from sweeper.plan import Plan, PlanEntry, build_plan
from sweeper.progress import LaunchProgress
from sweeper.spec import StudySpec, load_spec
from sweeper.storage import (
    Heartbeat,
    KeyStatus,
    StorageError,
    StudyBusy,
    StudyStore,
    check_storage,
    check_writable,
    code_revision,
    json_safe,
    ledger,
    package_versions,
    redact,
)
from sweeper.study import open_study

#: what a driver runs once it holds the study: its plan, bound to the study
Stage = Callable[[StudySpec, StudyStore], Plan]
#: seconds between the driver's heartbeats in the study
HEARTBEAT_SECONDS = 15.0
#: exit code of a launch refused because another live driver runs the study
EXIT_BUSY = 3
#: exit code of a launch stopped by Ctrl-C or SIGTERM
EXIT_INTERRUPTED = 130


def prepare(
    spec: StudySpec | str | os.PathLike[str],
    storage: str | None = None,
    address: str | None = None,
    max_concurrent: int | None = None,
) -> tuple[StudySpec, Plan]:
    """Validate the spec (or the spec file) with its overrides, build its plan and check
    the storage.

    Raises ``SpecError`` or ``StorageError`` (both ValueErrors naming the field); writes
    nothing anywhere.
    """
    if not isinstance(spec, StudySpec):
        spec = load_spec(spec)
    if (storage, address, max_concurrent) != (None, None, None):
        spec = spec.with_overrides(storage=storage, address=address, max_concurrent=max_concurrent)
    plan = build_plan(spec)
    check_storage(spec.storage_url)
    return spec, plan


def study_attrs(spec: StudySpec, plan: Plan) -> dict[str, Any]:
    """The study user attrs (docs/architecture.md, "Storage conventions")."""
    return {
        "spec": spec.model_dump(mode="json"),
        "plan_hash": plan.hash,
        "plan": plan.keys(),
        "versions": package_versions(),
        "revision": code_revision(),
        "env": spec.env.name,
        "metric_names": list(report_metric_names(spec.env.name)),
    }


def report_metric_names(env: str) -> tuple[str, ...]:
    """The metric keys a trial on ``env`` reports (docs/architecture.md, "One trial")."""
    return tuple(metric_key(name) for name in env_class(env).metric_names)


class Interrupted(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C."""


def _raise_interrupted(signum: int, frame: Any) -> None:
    raise Interrupted()


@contextlib.contextmanager
def sigterm_stops() -> Iterator[None]:
    """Inside the block SIGTERM raises ``Interrupted`` (a KeyboardInterrupt), so it stops a
    launch as Ctrl-C does; the handler before it comes back after. Outside the main
    thread, which alone receives signals, it changes nothing."""
    try:
        previous = signal.signal(signal.SIGTERM, _raise_interrupted)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def launch(
    spec: StudySpec,
    plan: Plan,
    *,
    train: Callable[..., Any] | None = None,
    stream: TextIO | None = None,
    stage: Stage | None = None,
) -> int:
    """Run (or resume) the study of a validated ``spec``; return the exit code.

    The database must be writable and Ray reachable before anything is written. A Ray that
    is already initialised is used and left running; otherwise one is started (local, or
    ``execution.address``) and shut down at the end. ``train`` replaces ``agent.train`` in
    the workers (tests). ``stage`` gives the plan to run once the study is claimed
    (default: the search plan; ``sweeper.confirm``: the confirmation stage); a StorageError
    from it exits 2. SIGTERM raises ``Interrupted`` throughout.
    """
    stream = sys.stderr if stream is None else stream
    execution = spec.execution
    with sigterm_stops():
        try:
            check_writable(spec.storage_url)
        except StorageError as e:
            print(f"sweeper launch: {e}", file=stream)
            return 2
        if stage is None and all_done(spec, plan):  # a relaunch with nothing left: no Ray
            total = len(plan.entries)
            print(
                f"study {spec.study!r} in {redact(spec.storage_url)}: {total} of {total} "
                "trials done, 0 to run",
                file=stream,
            )
            return 0
        cpus = math.ceil(execution.max_concurrent * execution.cpus_per_trial)
        try:
            started_ray = start_ray(execution.address, num_cpus=cpus)
        except SystemExit:  # Ray's own SIGTERM handlers, set while it starts, exit this way
            ray.shutdown()
            raise Interrupted() from None
        except Exception as e:  # ConnectionError, an auth error, ...
            print(cannot_reach_message(execution.address, e), file=stream)
            return 2
        try:
            return _launch_on_ray(spec, plan, train, stream, stage)
        finally:
            if started_ray:
                ray.shutdown()


def all_done(spec: StudySpec, plan: Plan) -> bool:
    """Whether the study already holds every key of ``plan`` done (and its random agent
    measured, if the spec asks for it), read read-only. Anything else, a study that does
    not exist or cannot be read included, is False: the launch then runs and reports it."""
    try:
        with open_study(
            spec.storage_url, spec.study, write=False, plan_hash=plan.hash, grace=0
        ) as store:
            trials, attrs = store.trials(), store.attrs
    except StorageError:  # NoStudy, another plan, an unreachable database
        return False
    if spec.random_episodes and random_agent.ATTR not in attrs:
        return False
    return all(c.done == c.planned for c in ledger(plan.keys(), trials, False).values())


def _launch_on_ray(
    spec: StudySpec,
    plan: Plan,
    train: Callable[..., Any] | None,
    stream: TextIO,
    stage: Stage | None,
) -> int:
    """Size the worker pool to the Ray cluster, start it and run the study."""
    execution = spec.execution
    cpus, gpus = execution.cpus_per_trial, execution.gpus_per_trial
    fit = resources_fit(cpus, gpus)
    if fit < 1:
        print(
            f"sweeper launch: execution: a trial needs {cpus:g} CPUs and {gpus:g} GPUs, "
            f"more than the Ray cluster has ({ray.cluster_resources()})",
            file=stream,
        )
        return 2
    if fit < execution.max_concurrent:
        print(
            f"sweeper launch: note: the Ray cluster holds {fit} trials at once, "
            f"not execution.max_concurrent={execution.max_concurrent}",
            file=stream,
        )
    size = min(fit, execution.max_concurrent, len(plan.entries))
    threads = execution.threads_per_trial
    refusal = oversubscription(threads, size, ray.cluster_resources().get("CPU", 0))
    if refusal is not None:
        print(f"sweeper launch: execution: {refusal}", file=stream)
        return 2
    cores = len(os.sched_getaffinity(0))
    if execution.address is None and threads * size > cores:
        print(
            f"sweeper launch: note: {oversubscription(threads, size, cores, 'here')}",
            file=stream,
        )
    # the workers start (importing torch and the env) while the driver opens the study
    pool = WorkerPool(
        size,
        cpus=cpus,
        gpus=gpus,
        train=train,
        env=spec.env.name,
        stall_timeout=execution.stall_timeout,
    )
    try:
        return _run_study(spec, plan, pool, stream, stage)
    finally:
        pool.shutdown()


def oversubscription(
    threads: int, trials: int, cpus: float, where: str = "Ray reports"
) -> str | None:
    """Why ``trials`` at once with ``threads`` torch threads each do not fit ``cpus``, and
    the fix; None when they fit. Torch threads beyond the cores make every trial several
    times slower (9x measured), not just the extra ones."""
    if threads * trials <= cpus:
        return None
    if threads > cpus:
        fix = f"lower threads_per_trial to at most {cpus:g}"
    else:
        fix = (
            f"run fewer at once (max_concurrent, --max-concurrent {int(cpus // threads)}), "
            f"lower threads_per_trial, or reserve them (cpus_per_trial: {threads})"
        )
    return (
        f"threads_per_trial {threads} x {trials} trials at once = {threads * trials} torch "
        f"threads, more than the {cpus:g} CPUs {where}: every trial would run several times "
        f"slower; {fix}"
    )


def cannot_reach_message(address: str | None, error: BaseException) -> str:
    """The one-line error for a Ray that cannot be started or joined.

    Ray reports a cluster that refuses the driver's token only in its own log lines
    ("InvalidAuthToken"), then fails with a bare "Failed to connect", so the message says
    what to set when the driver is not in token mode.
    """
    where = f"the Ray cluster at {address!r}" if address else "local Ray"
    message = f"sweeper launch: execution.address: cannot reach {where}: {one_line(error, 500)}"
    token_mode = os.environ.get("RAY_AUTH_MODE") == "token"
    if address and not token_mode and not isinstance(error, Unreachable):
        message += (
            "; if Ray's lines above say InvalidAuthToken, the cluster uses token "
            "authentication: set RAY_AUTH_MODE=token and its token (RAY_AUTH_TOKEN or "
            "~/.ray/auth_token), see docs/cluster.md"
        )
    return message


def _run_study(
    spec: StudySpec, plan: Plan, pool: WorkerPool, stream: TextIO, stage: Stage | None = None
) -> int:
    """Open the study as its driver, its heartbeat beating until it lets go; run it."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    attrs = study_attrs(spec, plan)
    grace = spec.execution.storage_grace
    try:
        with open_study(
            spec.storage_url, spec.study, write=True, attrs=attrs, grace=grace
        ) as store:
            try:
                store.claim_driver()
            except StudyBusy as e:
                print(f"sweeper launch: {e}", file=stream)
                return EXIT_BUSY
            try:
                with store.heartbeats(HEARTBEAT_SECONDS) as beat:
                    if store.attrs.get("revision") != attrs["revision"]:
                        print(
                            f"sweeper launch: note: the study began at code revision "
                            f"{store.attrs.get('revision')}; this is {attrs['revision']}",
                            file=stream,
                        )
                    return _sync_and_drive(spec, store, pool, beat, stream, stage)
            except StorageError as e:  # the stage cannot be run (sweeper confirm)
                print(f"sweeper {'launch' if stage is None else 'confirm'}: {e}", file=stream)
                return 2
            except StudyBusy as e:  # a heartbeat found another driver: this one looked dead
                print(f"sweeper launch: stopped: {e}", file=stream)
                return EXIT_BUSY
            finally:
                store.release_driver()
    except StorageError as e:  # opening or creating the study
        print(f"sweeper launch: {e}", file=stream)
        return 2


def _sync_and_drive(
    spec: StudySpec,
    store: StudyStore,
    pool: WorkerPool,
    beat: Heartbeat,
    stream: TextIO,
    stage: Stage | None = None,
) -> int:
    """Give the plan's keys their trials, then run what is left."""
    # bound to the study: its checkpoints are its own
    plan = build_plan(spec, study_uid=store.study_uid) if stage is None else stage(spec, store)
    todo = store.sync(plan.entries, plan.hash)
    _measure_random_agent(spec, store, stream)
    total = len(plan.entries)
    print(
        f"study {spec.study!r} in {redact(spec.storage_url)}: {total - len(todo)} of {total} "
        f"trials done, {len(todo)} to run",
        file=stream,
    )
    if not todo:
        return 0
    pool.shrink(len(todo))
    progress = LaunchProgress(spec.study, plan.keys(), spec.budget.env_steps, stream)
    return Driver(spec, store, pool, progress, beat, stream).run(todo)


def _measure_random_agent(spec: StudySpec, store: StudyStore, stream: TextIO) -> None:
    """Measure the random agent's success rate once per study (the 0 of its normalised
    scores, ``sweeper.random_agent``); a study that has it is not measured again. A
    measurement that fails is a note, not a failure: the study is then not normalised."""
    if not spec.random_episodes or random_agent.ATTR in store.attrs:
        return
    print(
        f"measuring a random agent's success rate on {spec.env.name} "
        f"({spec.random_episodes} episodes)",
        file=stream,
    )
    try:
        measured = random_agent.measure_random_agent(spec)
    except Exception as e:  # e.g. no renderer on the driver's host
        print(f"sweeper launch: note: could not measure the random agent: {e}", file=stream)
        return
    store.set_study_attr(random_agent.ATTR, measured)
    print(
        f"random agent: success rate {measured['success_rate']:.3f} in {measured['seconds']:.1f} s",
        file=stream,
    )


@dataclass
class Job:
    """A plan entry in flight: its Optuna trial and what it has reported so far."""

    entry: PlanEntry
    trial_id: int
    number: int
    attempts: int = 0
    deaths: list[str] = field(default_factory=list)
    points: dict[int, dict[str, float]] = field(default_factory=dict)
    artifacts: dict[str, str] = field(default_factory=dict)  # filename -> artifact id

    @property
    def key(self) -> str:
        return self.entry.key

    def curve(self) -> dict[str, list[Any]]:
        """The ``curve`` user attr: columnar, sorted by step, NaN/inf as null."""
        steps = sorted(self.points)
        names = list(dict.fromkeys(k for s in steps for k in self.points[s]))
        columns: dict[str, list[Any]] = {"step": steps}
        for name in names:
            columns[name] = json_safe(self.points[s].get(name, float("nan")) for s in steps)
        return columns


def run_order(entry: PlanEntry) -> tuple[int, int, str]:
    """Where a key starts in a launch: by configuration, then seed, then method."""
    return (entry.config_id, entry.seed, entry.method)


class Driver:
    """The driver loop of a claimed study: hands keys to idle workers, writes what comes
    back (one method per event of ``WorkerPool.poll``), and beats."""

    def __init__(
        self,
        spec: StudySpec,
        store: StudyStore,
        pool: WorkerPool,
        progress: LaunchProgress,
        beat: Heartbeat,
        stream: TextIO,
    ) -> None:
        self.execution = spec.execution
        self.store, self.pool, self.progress = store, pool, progress
        self.beat, self.stream = beat, stream
        self.artifacts = ArtifactStore(artifact_location(spec))
        self.queue: deque[tuple[PlanEntry, Any]] = deque()  # keys not started yet
        self.retry: deque[Job] = deque()  # lost trials wait here for a started worker
        self.jobs: dict[str, Job] = {}  # in flight, by key
        self.failed = 0

    def run(self, todo: list[tuple[PlanEntry, Any]]) -> int:
        """Run ``todo`` (plan entries with their WAITING trials); return the exit code.

        Keys start round by round, one (config_id, seed) pair of every method per round,
        so a study stopped part-way is still paired and balanced across its methods."""
        self.queue.extend(sorted(todo, key=lambda item: run_order(item[0])))
        for entry, _ in todo:
            self.progress.set_state(entry.key, KeyStatus.LEFT)
        try:
            while self.queue or self.jobs:
                self.fill_idle_workers()
                for event in self.pool.poll(timeout=1.0):
                    self.handle(event)
                self.beat.check()  # stops this driver if another one took the study over
                self.progress.refresh()
            self.progress.refresh(force=True)
            self.progress.close()
        except KeyboardInterrupt:
            return self.stop()
        if self.failed:
            print(
                f"sweeper launch: {self.failed} trial(s) failed (see `sweeper status`); "
                "launching again re-runs them",
                file=self.stream,
            )
            return 1
        return 0

    def fill_idle_workers(self) -> None:
        """Give every idle worker a trial: a lost one to re-run first, else the next key."""
        while self.pool.idle and (self.retry or self.queue):
            if self.retry:
                self.dispatch(self.retry.popleft())
                continue
            entry, trial = self.queue.popleft()
            job = Job(entry, trial._trial_id, trial.number)
            self.store.start(job.trial_id)
            self.jobs[job.key] = job
            self.dispatch(job)

    def dispatch(self, job: Job) -> None:
        job.attempts += 1
        self.store.set_attrs(job.trial_id, {"attempts": job.attempts})
        config = job.entry.trial_config
        if config.checkpoint_dir is not None and not is_uri(config.checkpoint_dir):
            # workers may run in another directory; a URI is the same everywhere
            config = dataclasses.replace(
                config, checkpoint_dir=str(Path(config.checkpoint_dir).absolute())
            )
        self.pool.submit(job.key, config)
        self.progress.set_state(job.key, KeyStatus.RUNNING)

    def handle(self, event: Event) -> None:
        job = self.jobs[event.token]
        match event:
            case Started():
                self.started(job, event)
            case Reported():
                self.reported(job, event)
            case Recorded():
                self.recorded(job, event)
            case Finished():
                self.finished(job, event)
            case Errored():
                self.errored(job, event)
            case Lost():
                self.lost(job, event)

    def started(self, job: Job, event: Started) -> None:
        self.store.set_attrs(job.trial_id, {"worker": event.where})

    def reported(self, job: Job, event: Reported) -> None:
        job.points[event.step] = event.metrics
        self.store.report(job.trial_id, {event.step: event.metrics["success_rate"]})
        self.store.set_attrs(job.trial_id, {"curve": job.curve()})
        self.progress.set_step(job.key, event.step)

    def recorded(self, job: Job, event: Recorded) -> None:
        store_artifact(self.store, self.artifacts, job, event, self.progress)

    def finished(self, job: Job, event: Finished) -> None:
        record_result(self.store, job, event.result)
        del self.jobs[job.key]
        if not self.execution.keep_checkpoints:
            remove_checkpoint(job.entry, self.progress)
        outcome = event.result.outcome
        self.progress.set_state(job.key, outcome)
        self.progress.note(f"{job.key} {outcome}: AUC {event.result.auc:.3f}")

    def errored(self, job: Job, event: Errored) -> None:
        self.give_up(job, {"error": event.error, "traceback": event.traceback})

    def lost(self, job: Job, event: Lost) -> None:
        job.deaths.append(event.error)
        self.store.set_attrs(job.trial_id, {"worker_deaths": job.deaths})
        if job.attempts <= self.execution.retries:
            self.progress.note(f"{job.key}: worker lost ({event.error}); re-running")
            self.progress.set_state(job.key, KeyStatus.LEFT)
            self.retry.append(job)
        else:
            self.give_up(job, {"error": f"worker died {job.attempts} times; last: {event.error}"})

    def give_up(self, job: Job, attrs: dict[str, Any]) -> None:
        """Record the trial FAIL; the next launch re-runs its key."""
        self.store.fail(job.trial_id, {"outcome": Outcome.FAILED, "curve": job.curve(), **attrs})
        del self.jobs[job.key]
        self.failed += 1
        self.progress.set_state(job.key, Outcome.FAILED)
        self.progress.note(f"{job.key} failed: {attrs['error']}")

    def stop(self) -> int:
        """Ctrl-C or SIGTERM: stop the workers, mark the trials in flight interrupted."""
        self.pool.shutdown()  # stops the trials in flight at once
        for job in self.jobs.values():
            # it may have been stopped while being told; then the next sync reaps it
            with contextlib.suppress(Exception):
                self.store.interrupt(job.trial_id, "stopped by the user", None)
        self.progress.close()
        resumable = sum(has_checkpoint(job.entry) for job in self.jobs.values())
        fresh = len(self.jobs) - resumable
        print(
            f"\nsweeper launch: stopped; {len(self.jobs)} trial(s) in flight were interrupted; "
            f"the next launch resumes {resumable} from their checkpoints"
            + (
                f" and starts {fresh} again from step 0 (no checkpoint written yet)"
                if fresh
                else ""
            ),
            file=self.stream,
        )
        return EXIT_INTERRUPTED


def store_artifact(
    store: StudyStore,
    artifacts: ArtifactStore,
    job: Job,
    event: Recorded,
    progress: LaunchProgress,
) -> None:
    """Upload a trial's file (an episode video) once per trial: a retried worker's second
    recording is dropped. A failed upload is noted and the trial goes on."""
    try:
        artifact_id = upload_once(
            store.storage, job.trial_id, event.filename, event.data, artifacts
        )
    except Exception as e:  # an unreachable object store must not fail the trial
        progress.note(f"{job.key}: could not store {event.filename}: {e}")
        return
    if artifact_id is not None:
        job.artifacts[event.filename] = artifact_id
        store.set_attrs(job.trial_id, {"videos": dict(job.artifacts)})


def record_result(store: StudyStore, job: Job, result: TrialResult) -> None:
    """Write a finished trial: every grid point, the curve, the outcome, then COMPLETE."""
    for index, step in enumerate(result.steps):
        job.points[int(step)] = {name: values[index] for name, values in result.metrics.items()}
    store.report(job.trial_id, {s: p["success_rate"] for s, p in job.points.items()})
    attrs: dict[str, Any] = {
        "outcome": result.outcome,
        "curve": job.curve(),
        "seconds": float(result.seconds),
        "resumed_from": result.resumed_from,
        "reward_scale": result.reward_scale,
        "video_seconds": result.video_seconds,
    }
    if result.outcome == Outcome.DIVERGED:
        attrs["diverged_step"] = result.diverged_step
        attrs["diverged_loss"] = result.diverged_loss
    store.complete(job.trial_id, result.auc, attrs)


def has_checkpoint(entry: PlanEntry) -> bool:
    """Whether the trial of ``entry`` has written a checkpoint (a relaunch resumes it)."""
    location = entry.trial_config.checkpoint_dir
    try:
        return location is not None and exists(join(location, CHECKPOINT_FILE))
    except Exception:  # an unreachable object store: say nothing was kept
        return False


def remove_checkpoint(entry: PlanEntry, progress: LaunchProgress) -> None:
    """Delete a recorded trial's checkpoint folder: it is never resumed again, and a
    study of thousands of trials would otherwise keep every replay buffer on disk."""
    location = entry.trial_config.checkpoint_dir
    if location is None:
        return
    try:
        remove(location)
    except Exception as e:  # the result is recorded: a checkpoint left over is no error
        progress.note(f"{entry.key}: could not remove its checkpoint {location}: {e}")
