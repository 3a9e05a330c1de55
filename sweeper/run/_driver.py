"""The driver loop of a claimed study; the driver is the only writer.

``Driver`` hands the keys ``sweeper.run._launch`` synced to a pool of Ray worker actors, one
trial per actor at a time, in ``run_order`` (round by round, so a study stopped part-way
stays paired), and writes what comes back, one method per event of ``WorkerPool.poll``:
reports stream in as intermediate values and the ``curve`` attr, a recorded video is
stored once per trial (``store_artifact``), what a trial says (a corrupt checkpoint it
discarded) is shown and kept in its ``notices`` attr, and a finished trial is told its
AUC (``record_result``), its checkpoint then removed.

Failures: a worker that dies, or stops answering for ``execution.stall_timeout`` s, is
replaced and the trial re-run from its checkpoint, with the same parameters and seed, in
the same Optuna trial, up to ``execution.retries`` times.
An exception inside a trial is not retried (a seeded trial fails the same way again): the
trial is FAIL with ``error`` and ``traceback``, and the next launch re-runs it.
Ctrl-C or SIGTERM stops the workers and marks the trials in flight ``interrupted``
(``Driver.stop``, exit code 130); a relaunch resumes them from their checkpoints.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

# Everything the driver runs is imported when the launch starts, never in the middle of a
# study: code changed under a running launch (a git pull) would otherwise be half-loaded
# (a lazy import of the new sweeper.results beside the old sweeper.storage once stopped
# a 10-hour study with an ImportError after a trial; tests/test_ray_cleanup.py).
from agent.checkpoint import saved_step
from agent.config import Outcome, TrialResult
from agent.metrics import normalized_auc
from agent.storage_io import is_uri, remove
from sweeper.plan import HALVING_ATTR, Curves, Ladder, PlanEntry, in_spec_order, run_order
from sweeper.results import after_trial
from sweeper.run._execution import (
    Errored,
    Event,
    Finished,
    Lost,
    Noticed,
    Recorded,
    Reported,
    Started,
    WorkerPool,
    WorkersCannotStart,
)
from sweeper.run._progress import LaunchProgress
from sweeper.run._signals import raise_if_stopped
from sweeper.spec import StudySpec, plural
from sweeper.storage import (
    ArtifactStore,
    Heartbeat,
    KeyStatus,
    StudyStore,
    artifact_location,
    json_safe,
    upload_once,
)

#: exit code of a launch stopped by Ctrl-C or SIGTERM
EXIT_INTERRUPTED = 130


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
    notices: list[str] = field(default_factory=list)  # what its runs said (Noticed)

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
        ladder: Ladder | None = None,
        curves: Curves | None = None,
    ) -> None:
        """``ladder`` (a plan with successive halving): its decisions so far, and
        ``curves`` those of the study's done keys."""
        self.execution, self.methods = spec.execution, list(spec.methods)
        self.store, self.pool, self.progress = store, pool, progress
        self.beat, self.stream = beat, stream
        self.artifacts = ArtifactStore(artifact_location(spec))
        self.queue: deque[tuple[PlanEntry, Any]] = deque()  # keys not started yet
        self.retry: deque[Job] = deque()  # lost trials wait here for a started worker
        self.jobs: dict[str, Job] = {}  # in flight, by key
        self.failed = 0
        # successive halving: the ladder, the curves its decisions read, the trials paused
        # at a rung until their method's decision there
        self.ladder, self.curves = ladder, dict(curves or {})
        self.paused: dict[str, Job] = {}

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
                raise_if_stopped()  # a Ctrl-C whose exception Python dropped
                self.beat.check()  # stops this driver if another one took the study over
                self.progress.refresh()
            self.progress.refresh(force=True)
            self.progress.close()
        except KeyboardInterrupt:
            return self.stop()
        except WorkersCannotStart as e:
            self.stop()
            print(f"sweeper launch: {e}", file=self.stream)
            return 2
        self.leave_paused()
        if self.failed:
            print(
                f"sweeper launch: {plural(self.failed, 'trial')} failed (see `sweeper status`); "
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
        if self.ladder is not None:
            stop, _ = self.ladder.target(job.entry.method, job.entry.config_id)
            config = dataclasses.replace(
                config, stop_at=stop if stop < config.total_steps else None
            )
        if config.checkpoint_dir is not None and not is_uri(config.checkpoint_dir):
            # workers may run in another directory; a URI is the same everywhere
            config = dataclasses.replace(
                config, checkpoint_dir=str(Path(config.checkpoint_dir).absolute())
            )
        self.pool.submit(job.key, config)
        resumed_from = checkpoint_step(job.entry) or 0
        self.progress.set_state(job.key, KeyStatus.RUNNING, from_step=resumed_from)

    def handle(self, event: Event) -> None:
        job = self.jobs[event.token]
        match event:
            case Started():
                self.started(job, event)
            case Reported():
                self.reported(job, event)
            case Recorded():
                self.recorded(job, event)
            case Noticed():
                self.noticed(job, event)
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

    def noticed(self, job: Job, event: Noticed) -> None:
        """What a trial said (it discarded a corrupt checkpoint): in the launch's output,
        and in the trial's ``notices`` attr."""
        job.notices.append(event.message)
        self.store.set_attrs(job.trial_id, {"notices": job.notices})
        self.progress.note(f"{job.key}: {event.message}")

    def finished(self, job: Job, event: Finished) -> None:
        result = event.result
        if result.outcome == Outcome.PAUSED:
            self.paused_at_rung(job, result)
            return
        if self.ladder is not None:  # a diverged trial's curve also counts at the rungs
            self.remember_curve(job.entry, result)
        record_result(self.store, job, result)
        del self.jobs[job.key]
        if not self.execution.keep_checkpoints:
            remove_checkpoint(job.entry, self.progress)
        outcome = event.result.outcome
        self.progress.set_state(job.key, outcome)
        self.progress.note(f"{job.key} {outcome}: AUC {event.result.auc:.3f}")
        last = not (self.queue or self.jobs or self.retry)
        after_trial(self.store, final=last, say=self.progress.note)

    # ---- successive halving --------------------------------------------------------
    def remember_curve(self, entry: PlanEntry, result: TrialResult) -> None:
        """Keep a trial's success curve so far for the ladder's decisions."""
        key = (entry.method, entry.config_id, entry.seed)
        self.curves[key] = (list(result.steps), list(result.metrics["success_rate"]))

    def paused_at_rung(self, job: Job, result: TrialResult) -> None:
        """A trial reached its rung: it waits there (its Optuna trial RUNNING, its
        checkpoint kept) until its method's decision, taken as soon as the curves allow."""
        step = result.steps[-1]
        del self.jobs[job.key]
        self.paused[job.key] = job
        self.remember_curve(job.entry, result)
        attrs = {"paused_at": step, "resumed_from": result.resumed_from, "curve": job.curve()}
        self.store.set_attrs(job.trial_id, attrs)
        self.progress.set_state(job.key, KeyStatus.LEFT)
        self.progress.note(f"{job.key} paused at step {step:,}: AUC so far {result.auc:.3f}")
        new = self.ladder.decide(self.curves)
        if new:
            self.store.set_study_attr(HALVING_ATTR, self.ladder.as_attr())
            for stop, chosen in sorted(new.items()):
                for method in in_spec_order(chosen, self.methods):
                    configs = chosen[method]
                    self.progress.note(
                        f"halving: {method} goes on from step {stop:,} with "
                        f"{plural(len(configs), 'configuration')} ({', '.join(map(str, configs))})"
                    )
        for key in sorted(self.paused):
            self.after_rung(self.paused[key])

    def after_rung(self, job: Job) -> None:
        """Move a paused trial on as its method's decision says: on to the next rung (the
        same Optuna trial, from its checkpoint), or PRUNED; undecided, it waits."""
        entry, step = job.entry, max(job.points)
        stop, dropped = self.ladder.target(entry.method, entry.config_id)
        if stop == step and not dropped:
            return  # undecided
        del self.paused[job.key]
        if stop > step:
            job.attempts = 0  # a new run of the trial: its retries start again
            self.jobs[job.key] = job
            self.retry.append(job)
            return
        steps, success = self.curves[(entry.method, entry.config_id, entry.seed)]
        self.store.prune(
            job.trial_id,
            {
                "outcome": Outcome.PRUNED,
                "rung": step,
                "auc_at_rung": normalized_auc(steps, success),
                "curve": job.curve(),
            },
        )
        if not self.execution.keep_checkpoints:
            remove_checkpoint(entry, self.progress)
        self.progress.set_state(job.key, Outcome.PRUNED)
        self.progress.note(f"{job.key} pruned at step {step:,}")

    def leave_paused(self) -> None:
        """Trials still paused when nothing else can run (a trial of their method failed):
        interrupted, so the next launch resumes them at their rung from the checkpoint."""
        for job in self.paused.values():
            self.store.interrupt(
                job.trial_id, f"paused at step {max(job.points):,}, its method undecided", None
            )
        if self.paused:
            print(
                f"sweeper launch: {plural(len(self.paused), 'trial')} left waiting at a rung for "
                "their method's failed trials; launching again runs those, then decides",
                file=self.stream,
            )

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
            died = f"worker died {plural(job.attempts, 'time')}; last: {event.error}"
            self.give_up(job, {"error": died})

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
        stopped = {**self.jobs, **self.paused}  # paused at a rung: RUNNING trials too
        for job in stopped.values():
            # it may have been stopped while being told; then the next sync reaps it
            with contextlib.suppress(Exception):
                self.store.interrupt(job.trial_id, "stopped by the user", None)
        self.progress.close()
        print(
            f"\nsweeper launch: stopped; {plural(len(stopped), 'trial')} in flight interrupted; "
            "the next launch:",
            file=self.stream,
        )
        for key, job in sorted(stopped.items()):
            step = checkpoint_step(job.entry)
            print(
                f"  {key}: resumes from step {step:,} (its checkpoint)"
                if step is not None
                else f"  {key}: restarts from step 0 (no checkpoint written yet)",
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
        "machines": list(result.machines),
    }
    if result.encoder_fit:
        attrs["encoder_fit"] = result.encoder_fit
    if result.outcome == Outcome.DIVERGED:
        attrs["diverged_step"] = result.diverged_step
        attrs["diverged_loss"] = result.diverged_loss
    store.complete(job.trial_id, result.auc, attrs)


def checkpoint_step(entry: PlanEntry) -> int | None:
    """The env step the trial of ``entry`` would resume from: its checkpoint's, or None
    when it has none (or it cannot be read: then it restarts from step 0)."""
    location = entry.trial_config.checkpoint_dir
    return None if location is None else saved_step(location)


def remove_checkpoint(entry: PlanEntry, progress: LaunchProgress) -> None:
    """Delete a recorded trial's checkpoint folder, and its ``<method>/<config_id>``
    folders once empty: it is never resumed again, and a study of thousands of trials
    would otherwise keep every replay buffer (and thousands of empty folders) on disk."""
    location = entry.trial_config.checkpoint_dir
    if location is None:
        return
    try:
        remove(location, parents=2)
    except Exception as e:  # the result is recorded: a checkpoint left over is no error
        progress.note(f"{entry.key}: could not remove its checkpoint {location}: {e}")
