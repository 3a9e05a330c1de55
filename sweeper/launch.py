"""``sweeper launch SPEC``: run a study, or resume it, on Ray; the driver is the only writer.

The driver validates everything first (spec, env and encoder options, storage URL, Ray
address), so a bad input exits with code 2 and writes nothing. Then it creates or loads the
study, gives every plan key that is not done a WAITING trial (``StudyStore.sync``), and
hands the keys to a pool of Ray worker actors, one trial per actor at a time. Reports
stream back as intermediate values; a finished trial is told its AUC.

Failures: a worker that dies, or stops answering for ``execution.stall_timeout`` s, is
replaced and the trial re-run from its checkpoint, with the same parameters and seed, in
the same Optuna trial, up to ``execution.retries`` times.
An exception inside a trial is not retried (a seeded trial fails the same way again): the
trial is FAIL with ``error`` and ``traceback``, and the next ``sweeper launch`` re-runs it.
Ctrl-C (or SIGTERM) stops the workers and marks the trials in flight ``interrupted``; a
relaunch resumes them from their checkpoints. Exit codes: 0 all done, 1 some trials
failed, 2 bad input, 3 another driver runs the study (busy), 130 interrupted. What trials print
goes to Ray's worker logs (``/tmp/ray/session_latest/logs``), not to the progress display.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import signal
import sys
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

if TYPE_CHECKING:
    from sweeper.artifacts import ArtifactStore
    from sweeper.execution import Recorded, WorkerPool
    from sweeper.plan import Plan, PlanEntry
    from sweeper.progress import Progress
    from sweeper.spec import StudySpec
    from sweeper.storage import Heartbeat, StudyStore

#: what a driver runs once it holds the study: its plan, bound to the study
Stage = Callable[["StudySpec", "StudyStore"], "Plan"]
#: seconds between the driver's heartbeats in the study
HEARTBEAT_SECONDS = 15.0
#: exit code of a launch refused because another live driver runs the study
EXIT_BUSY = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``sweeper launch``."""
    from sweeper.cli import add_spec_arguments

    add_spec_arguments(parser)
    parser.add_argument(
        "--address",
        metavar="ADDR",
        help="join the Ray cluster at ADDR ('auto' or 'host:6379') instead of starting a local Ray",
    )
    parser.add_argument(
        "--max-concurrent",
        metavar="N",
        type=_positive_int,
        help="trials at once, overriding the spec's execution.max_concurrent",
    )


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def prepare(
    path: str,
    storage: str | None = None,
    address: str | None = None,
    max_concurrent: int | None = None,
) -> tuple[StudySpec, Plan]:
    """Validate the spec with its overrides, build its plan and check the storage.

    Raises ``SpecError`` or ``StorageError`` (both ValueErrors naming the field); writes
    nothing anywhere.
    """
    from sweeper.plan import build_plan
    from sweeper.spec import load_spec
    from sweeper.storage import check_storage

    spec = load_spec(path)
    if (storage, address, max_concurrent) != (None, None, None):
        spec = spec.with_overrides(storage=storage, address=address, max_concurrent=max_concurrent)
    plan = build_plan(spec)
    check_storage(spec.storage_url)
    return spec, plan


def run(args: argparse.Namespace) -> int:
    """``sweeper launch``: returns the exit code."""
    try:
        try:
            spec, plan = prepare(args.spec, args.storage, args.address, args.max_concurrent)
        except ValueError as e:  # SpecError, StorageError
            print(f"sweeper launch: {e}", file=sys.stderr)
            return 2
        return launch(spec, plan)
    except KeyboardInterrupt:  # outside the driver loop, which handles its own
        print("\nsweeper launch: stopped", file=sys.stderr)
        return 130


def study_attrs(spec: StudySpec, plan: Plan) -> dict[str, Any]:
    """The study user attrs (docs/architecture.md, "Storage conventions")."""
    from sweeper.storage import code_revision, package_versions

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
    from agent.envs import env_class
    from agent.metrics import metric_key

    return tuple(metric_key(name) for name in env_class(env).metric_names)


@dataclass
class _Job:
    """A plan entry in flight: its Optuna trial and what it has reported so far."""

    entry: PlanEntry
    trial_id: int
    number: int
    attempts: int = 0
    deaths: list[str] = field(default_factory=list)
    points: dict[int, dict[str, float]] = field(default_factory=dict)
    artifacts: dict[str, str] = field(default_factory=dict)  # filename -> artifact id

    def curve(self) -> dict[str, list[Any]]:
        """The ``curve`` user attr: columnar, sorted by step, NaN/inf as null."""
        from sweeper.storage import json_safe

        steps = sorted(self.points)
        names = list(dict.fromkeys(k for s in steps for k in self.points[s]))
        columns: dict[str, list[Any]] = {"step": steps}
        for name in names:
            columns[name] = json_safe(self.points[s].get(name, float("nan")) for s in steps)
        return columns


class _Interrupted(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C."""


def launch(
    spec: StudySpec,
    plan: Plan,
    *,
    train: Callable[..., Any] | None = None,
    stream: TextIO | None = None,
    stage: Stage | None = None,
) -> int:
    """Run (or resume) the study of a validated ``spec``; return the exit code.

    Ray comes first, so a bad address writes nothing. A Ray that is already initialised is
    used and left running; otherwise one is started (local, or ``execution.address``) and
    shut down at the end. ``train`` replaces ``agent.train`` in the workers (tests).
    ``stage`` gives the plan to run once the study is claimed (default: the search plan;
    ``sweeper.confirm``: the confirmation stage); a StorageError from it exits 2.
    """
    import ray

    from sweeper.execution import WorkerPool, resources_fit, start_ray

    stream = sys.stderr if stream is None else stream
    execution = spec.execution
    cpus, gpus = execution.cpus_per_trial, execution.gpus_per_trial
    try:
        started_ray = start_ray(
            execution.address, num_cpus=math.ceil(execution.max_concurrent * cpus)
        )
    except Exception as e:  # ConnectionError, an auth error, ...
        print(cannot_reach_message(execution.address, e), file=stream)
        return 2
    try:
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
    finally:
        if started_ray:
            ray.shutdown()


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
    from sweeper.execution import Unreachable, one_line

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
    import optuna

    from sweeper.storage import StorageError, StudyBusy, StudyStore, open_storage

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    attrs = study_attrs(spec, plan)
    storage = open_storage(spec.storage_url)
    try:
        try:
            store = StudyStore.open_or_create(storage, spec.study, attrs)
            store.claim_driver()
        except (StorageError, StudyBusy) as e:
            print(f"sweeper launch: {e}", file=stream)
            return 2 if isinstance(e, StorageError) else EXIT_BUSY
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
    finally:
        storage.remove_session()
        storage.engine.dispose()


def _sync_and_drive(
    spec: StudySpec,
    store: StudyStore,
    pool: WorkerPool,
    beat: Heartbeat,
    stream: TextIO,
    stage: Stage | None = None,
) -> int:
    """Give the plan's keys their trials, then run what is left."""
    from sweeper.plan import build_plan
    from sweeper.progress import Progress
    from sweeper.storage import redact

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
    progress = Progress(spec.study, plan.keys(), spec.budget.env_steps, stream)
    return _drive(spec, store, todo, pool, progress, beat, stream)


def _measure_random_agent(spec: StudySpec, store: StudyStore, stream: TextIO) -> None:
    """Measure the random agent's success rate once per study (the 0 of its normalised
    scores, ``sweeper.random_agent``); a study that has it is not measured again. A
    measurement that fails is a note, not a failure: the study is then not normalised."""
    from sweeper.random_agent import ATTR, measure_random_agent

    if not spec.random_episodes or ATTR in store.attrs:
        return
    print(
        f"measuring a random agent's success rate on {spec.env.name} "
        f"({spec.random_episodes} episodes)",
        file=stream,
    )
    try:
        measured = measure_random_agent(spec)
    except Exception as e:  # e.g. no renderer on the driver's host
        print(f"sweeper launch: note: could not measure the random agent: {e}", file=stream)
        return
    store.set_study_attr(ATTR, measured)
    print(
        f"random agent: success rate {measured['success_rate']:.3f} in {measured['seconds']:.1f} s",
        file=stream,
    )


def _drive(
    spec: StudySpec,
    store: StudyStore,
    todo: list[tuple[PlanEntry, Any]],
    pool: WorkerPool,
    progress: Progress,
    beat: Heartbeat,
    stream: TextIO,
) -> int:
    """The driver loop: dispatch keys to workers, write what comes back."""
    from agent.storage_io import is_uri
    from sweeper.artifacts import ArtifactStore, artifact_location
    from sweeper.execution import Errored, Finished, Lost, Recorded, Reported, Started

    execution = spec.execution
    artifacts = ArtifactStore(artifact_location(spec))
    jobs: dict[str, _Job] = {}
    previous_handler = _sigterm_to_interrupt()
    try:
        queue = deque(todo)
        failed = 0
        for entry, _ in todo:
            progress.set_state(entry.key, "left")

        def dispatch(job: _Job) -> None:
            job.attempts += 1
            store.set_attrs(job.trial_id, {"attempts": job.attempts})
            config = job.entry.trial_config
            local = config.checkpoint_dir is not None and not is_uri(config.checkpoint_dir)
            if local:  # workers may run in another directory; a URI is the same everywhere
                config = dataclasses.replace(
                    config, checkpoint_dir=str(Path(config.checkpoint_dir).absolute())
                )
            pool.submit(job.entry.key, config)
            progress.set_state(job.entry.key, "running")

        def give_up(job: _Job, attrs: dict[str, Any]) -> None:
            nonlocal failed
            store.fail(job.trial_id, {"outcome": "failed", "curve": job.curve(), **attrs})
            del jobs[job.entry.key]
            failed += 1
            progress.set_state(job.entry.key, "failed")
            progress.note(f"{job.entry.key} failed: {attrs['error']}")

        retry: deque[_Job] = deque()  # lost trials wait here for a started worker
        while queue or jobs:
            while pool.idle and (retry or queue):
                if retry:
                    dispatch(retry.popleft())
                    continue
                entry, trial = queue.popleft()
                job = _Job(entry, trial._trial_id, trial.number)
                store.start(job.trial_id)
                jobs[entry.key] = job
                dispatch(job)
            for event in pool.poll(timeout=1.0):
                job = jobs[event.token]
                if isinstance(event, Started):
                    store.set_attrs(job.trial_id, {"worker": event.where})
                elif isinstance(event, Reported):
                    job.points[event.step] = event.metrics
                    store.report(job.trial_id, {event.step: event.metrics["success_rate"]})
                    store.set_attrs(job.trial_id, {"curve": job.curve()})
                    progress.set_step(job.entry.key, event.step)
                elif isinstance(event, Recorded):
                    _store_artifact(store, artifacts, job, event, progress)
                elif isinstance(event, Finished):
                    _record_result(store, job, event.result)
                    del jobs[event.token]
                    if not execution.keep_checkpoints:
                        _remove_checkpoint(job.entry, progress)
                    outcome = event.result.outcome
                    progress.set_state(job.entry.key, outcome)
                    progress.note(f"{job.entry.key} {outcome}: AUC {event.result.auc:.3f}")
                elif isinstance(event, Errored):
                    give_up(job, {"error": event.error, "traceback": event.traceback})
                elif isinstance(event, Lost):
                    job.deaths.append(event.error)
                    store.set_attrs(job.trial_id, {"worker_deaths": job.deaths})
                    if job.attempts <= execution.retries:
                        progress.note(f"{job.entry.key}: worker lost ({event.error}); re-running")
                        progress.set_state(job.entry.key, "left")
                        retry.append(job)
                    else:
                        error = f"worker died {job.attempts} times; last: {event.error}"
                        give_up(job, {"error": error})
            beat.check()  # stops this driver if another one took the study over
            progress.refresh()
        progress.refresh(force=True)
        progress.close()
        if failed:
            print(
                f"sweeper launch: {failed} trial(s) failed (see `sweeper status`); "
                "launching again re-runs them",
                file=stream,
            )
            return 1
        return 0
    except KeyboardInterrupt:
        pool.shutdown()  # stops the trials in flight at once
        for job in jobs.values():
            # it may have been stopped while being told; then the next sync reaps it
            with contextlib.suppress(Exception):
                store.interrupt(job.trial_id, "stopped by the user", None)
        progress.close()
        print(
            f"\nsweeper launch: stopped; {len(jobs)} trial(s) in flight were interrupted and "
            "resume from their checkpoints when you launch again",
            file=stream,
        )
        return 130
    finally:
        _restore_sigterm(previous_handler)


def _store_artifact(
    store: StudyStore, artifacts: ArtifactStore, job: _Job, event: Recorded, progress: Progress
) -> None:
    """Upload a trial's file (an episode video) once per trial: a retried worker's second
    recording is dropped. A failed upload is noted and the trial goes on."""
    from sweeper.artifacts import upload_once

    try:
        artifact_id = upload_once(
            store.storage, job.trial_id, event.filename, event.data, artifacts
        )
    except Exception as e:  # an unreachable object store must not fail the trial
        progress.note(f"{job.entry.key}: could not store {event.filename}: {e}")
        return
    if artifact_id is not None:
        job.artifacts[event.filename] = artifact_id
        store.set_attrs(job.trial_id, {"videos": dict(job.artifacts)})


def _record_result(store: StudyStore, job: _Job, result: Any) -> None:
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
    if result.outcome == "diverged":
        attrs["diverged_step"] = result.diverged_step
        attrs["diverged_loss"] = result.diverged_loss
    store.complete(job.trial_id, result.auc, attrs)


def _remove_checkpoint(entry: PlanEntry, progress: Progress) -> None:
    """Delete a recorded trial's checkpoint folder: it is never resumed again, and a
    study of thousands of trials would otherwise keep every replay buffer on disk."""
    from agent.storage_io import remove

    location = entry.trial_config.checkpoint_dir
    if location is None:
        return
    try:
        remove(location)
    except Exception as e:  # the result is recorded: a checkpoint left over is no error
        progress.note(f"{entry.key}: could not remove its checkpoint {location}: {e}")


def _sigterm_to_interrupt() -> Any:
    """Make SIGTERM stop the driver like Ctrl-C (main thread only); return the old handler."""

    def handler(signum: int, frame: Any) -> None:
        raise _Interrupted()

    try:
        return signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        return None


def _restore_sigterm(handler: Any) -> None:
    if handler is not None:
        signal.signal(signal.SIGTERM, handler)
