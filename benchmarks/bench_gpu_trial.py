"""The GPU path: SAC update speed, trial throughput with 1-8 trials on one GPU, a study's cost.

On CUDA, at the thesis' appendix A.1 setting (``bench_learning.FETCH_A1``: fetch_reach
84x84, batch 256, 2 updates per env step, 32 filters; the rest as ``FETCH_CPU``):

- ms per SAC update (``bench_update_speed``'s update on a random batch, copied from host
  memory each time as a trial's replay sample is), timed over ``actor_update_every``
  updates (one with the actor) with ``torch.cuda.synchronize()`` after a warm-up: fp32
  as trials run it (torch's defaults: matmul TF32 off, cuDNN TF32 on), fp32 with TF32
  on, and with the agent's ``precision: bf16`` (autocast; weights and optimiser state fp32);
- env steps per second of short real trials (``agent.train``, ``--trial-steps`` env
  steps, the first third random seed steps), in fp32 and in bf16, 1, 2, 4 and 8 at once
  on the GPU
  (``--concurrency``), each in its own spawned process as Ray runs trials with
  ``gpus_per_trial`` 1/n, started together behind a barrier once CUDA is up in each. A
  trial's reports time its phases: setup (envs, reward scale, networks), seed phase,
  learning phase, each without the evaluations, which are timed apart;
- from those, the wall time of ``studies/fetch_reach.yaml`` (``--spec``) at each
  concurrency: every trial not VGG priced as the measured one at the spec's budget (VGG
  needs its weights file: counted, not priced), and the CPU's share of it.

Without CUDA it says so and prints the CPU figures instead (ms per update at A.1 and at
``FETCH_CPU``, fp32, ``--threads``, and the CPU model), exit status 0.
``--gpu-path-on-cpu`` runs the GPU path on the CPU at ``FETCH_CPU``'s setting, to check
the script where there is no GPU: its figures mean nothing.

Run: ``./run python benchmarks/bench_gpu_trial.py [--repeats N] [--trial-steps 1500]
[--concurrency 1,2,4,8] [--threads 1]``
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import multiprocessing
import os
import queue
import statistics
import time
import traceback
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from bench_learning import FETCH_A1, FETCH_CPU
from bench_update_speed import median_seconds, random_batch

from agent import trial as trial_loop
from agent.config import Outcome, SACConfig, TrialConfig
from agent.envs.base import EPISODE_STEPS
from agent.machine import describe
from agent.metrics import evaluation_grid
from agent.sac import SAC
from sweeper.plan._entries import PlanEntry, build_plan, run_order
from sweeper.plan._estimate import format_duration, makespan
from sweeper.spec._models import load_spec
from sweeper.spec._words import plural

SPEC = Path(__file__).resolve().parent.parent / "studies" / "fetch_reach.yaml"
EVAL_EPISODES = 2  # per evaluation of a measured trial (its grid: every seed_steps)
BARRIER_SECONDS = 600  # how long a trial process waits for the others to be ready
WARMUP = {"cuda": 20, "cpu": 1}  # updates run before the timed ones
REPEATS = {"cuda": 50, "cpu": 3}  # the default --repeats: timed groups of updates


# ---- ms per update --------------------------------------------------------------------
def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@contextlib.contextmanager
def tf32(on: bool | None) -> Iterator[None]:
    """Matmul and cuDNN TF32 set to ``on`` inside (None: left as they are)."""
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    if on is not None:
        torch.backends.cuda.matmul.allow_tf32 = on
        torch.backends.cudnn.allow_tf32 = on
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def ms_per_update(
    sac: SACConfig, size: int, device: torch.device, repeats: int, bf16: bool = False
) -> float:
    """Median ms per SAC update at ``sac`` on ``size`` x ``size`` images, timed in groups
    of ``actor_update_every`` updates (each group updates the actor once, as a trial's
    average does); ``bf16``: the agent's ``precision: bf16`` (autocast)."""
    agent = SAC((size, size, 3), (size, size, 3), 4, sac, device, "bf16" if bf16 else "fp32")
    batch = random_batch(size, sac.batch_size, np.random.default_rng(0))
    group = sac.actor_update_every

    def updates(count: int) -> None:
        for _ in range(count):
            agent.update(batch)
        synchronize(device)

    updates(WARMUP[device.type])
    return 1000 * median_seconds(lambda: updates(group), repeats) / group


def describe_sac(sac: SACConfig, size: int) -> str:
    hidden = "x".join(str(h) for h in sac.hidden_sizes)
    return (
        f"{size}x{size}, batch {sac.batch_size}, {sac.num_filters} filters, MLP {hidden}, "
        f"{sac.updates_per_step} update(s) per env step, actor every {sac.actor_update_every}"
    )


# ---- one trial's phases ---------------------------------------------------------------
@dataclass(frozen=True)
class Phases:
    """One trial's wall seconds by phase; the evaluations are taken out of the phases
    they fell in and counted apart."""

    setup: float  # train() called -> its first evaluation (envs, reward scale, networks)
    seed_steps: int
    seed_seconds: float
    learn_steps: int
    learn_seconds: float
    eval_steps: int
    eval_seconds: float
    seconds: float  # the whole train() call
    learning: tuple[float, float]  # when the learning phase began and ended (time.time())

    @property
    def seed_rate(self) -> float:
        return self.seed_steps / self.seed_seconds

    @property
    def learn_rate(self) -> float:
        return self.learn_steps / self.learn_seconds

    @property
    def eval_rate(self) -> float:
        return self.eval_steps / self.eval_seconds

    @property
    def env_share(self) -> float:
        """The share of a learning step's time that env stepping and rendering take (a
        seed-phase step's time: stepping, rendering, storing, no action or update)."""
        return self.learn_rate / self.seed_rate

    def seconds_for(self, config: TrialConfig) -> float:
        """The wall seconds of trial ``config`` at these rates."""
        return (
            self.setup
            + config.seed_steps / self.seed_rate
            + (config.total_steps - config.seed_steps) / self.learn_rate
            + evaluation_steps(config) / self.eval_rate
        )


def evaluation_steps(config: TrialConfig) -> int:
    """The env steps of a trial's evaluations (episodes never end before EPISODE_STEPS)."""
    evaluations = len(evaluation_grid(config.total_steps, config.eval_every))
    return evaluations * config.eval_episodes * EPISODE_STEPS


def env_and_eval_steps(config: TrialConfig) -> int:
    return config.total_steps + evaluation_steps(config)


def measured_config(base: TrialConfig, steps: int, device: str, threads: int) -> TrialConfig:
    """``base`` cut to ``steps`` env steps, the first third random; evaluated at the end of
    the seed phase and every as many steps after it (so reports bound the phases)."""
    seed_steps = max(1, steps // 3)
    return dataclasses.replace(
        base,
        total_steps=steps,
        seed_steps=seed_steps,
        eval_every=seed_steps,
        eval_episodes=EVAL_EPISODES,
        device=device,
        threads=threads,
    )


def phases(
    config: TrialConfig,
    start: float,
    reports: dict[int, tuple[float, float]],
    end: float,
    epoch: float,
) -> Phases:
    """``reports[step]``: (``time.perf_counter()`` at the report, seconds of the evaluation
    just before it); ``start``, ``end``: ``train`` called and returned; ``epoch``:
    ``time.time()`` at ``start``."""
    s, t = config.seed_steps, config.total_steps
    at = {step: when for step, (when, _) in reports.items()}
    evals = {step: seconds for step, (_, seconds) in reports.items()}
    return Phases(
        setup=at[0] - evals[0] - start,
        seed_steps=s,
        seed_seconds=at[s] - at[0] - evals[s],
        learn_steps=t - s,
        learn_seconds=at[t] - at[s] - sum(v for step, v in evals.items() if step > s),
        eval_steps=len(reports) * config.eval_episodes * EPISODE_STEPS,
        eval_seconds=sum(evals.values()),
        seconds=end - start,
        learning=(epoch + at[s] - start, epoch + at[t] - start),
    )


def trial_process(config: TrialConfig, barrier: Any, results: Any) -> None:
    """One spawned process: wait for the others, run the trial, put its ``Phases`` (or
    the traceback of what went wrong) on ``results``."""
    try:
        evaluations: list[float] = []
        evaluate = trial_loop.evaluate

        def timed_evaluate(*args: Any, **kwargs: Any) -> dict[str, float]:
            start = time.perf_counter()
            try:
                return evaluate(*args, **kwargs)
            finally:
                evaluations.append(time.perf_counter() - start)

        trial_loop.evaluate = timed_evaluate  # the trial looks it up at each evaluation
        reports: dict[int, tuple[float, float]] = {}

        def report(step: int, metrics: dict[str, float]) -> None:
            reports[step] = (time.perf_counter(), evaluations[-1])

        torch.zeros(1, device=config.device)  # CUDA's start-up before the barrier
        barrier.wait(BARRIER_SECONDS)
        start, epoch = time.perf_counter(), time.time()
        result = trial_loop.train(config, report)
        end = time.perf_counter()
        if result.outcome != Outcome.COMPLETED:
            raise RuntimeError(f"the trial ended {result.outcome}, not completed")
        results.put(phases(config, start, reports, end, epoch))
    except BaseException:
        results.put(traceback.format_exc())


def run_together(config: TrialConfig, count: int) -> list[Phases]:
    """``count`` trials (seeds 0..count-1) at once, each in its own spawned process."""
    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(count), ctx.Queue()
    processes = [
        ctx.Process(
            target=trial_process, args=(dataclasses.replace(config, seed=i), barrier, results)
        )
        for i in range(count)
    ]
    for process in processes:
        process.start()
    done: list[Phases | str] = []
    try:
        while len(done) < count:
            try:
                done.append(results.get(timeout=5))
            except queue.Empty:
                if not any(p.is_alive() for p in processes):
                    codes = [p.exitcode for p in processes]
                    raise RuntimeError(
                        f"{count - len(done)} trial process(es) ended without a result "
                        f"(exit codes {codes})"
                    ) from None
    finally:
        for process in processes:
            process.join(timeout=10)
            if process.is_alive():  # ours, stuck after a failure elsewhere
                process.terminate()
                process.join()
    failures = [d for d in done if isinstance(d, str)]
    if failures:
        raise RuntimeError(f"a trial process failed:\n{failures[0]}")
    return [d for d in done if isinstance(d, Phases)]


# ---- the study ------------------------------------------------------------------------
def study_entries(spec_path: Path) -> tuple[list[PlanEntry], list[PlanEntry]]:
    """The plan's entries in run order: (priced, VGG's)."""
    entries = sorted(build_plan(load_spec(spec_path)).entries, key=run_order)
    vgg = [e for e in entries if e.trial_config.method == "vgg"]
    return [e for e in entries if e.trial_config.method != "vgg"], vgg


def overlap(measured: list[Phases]) -> float:
    """The time all the trials were in their learning phase at once, over the mean
    learning phase's (1: the aggregate rate was measured with all running together)."""
    together = min(m.learning[1] for m in measured) - max(m.learning[0] for m in measured)
    return max(0.0, together) / statistics.mean(m.learning[1] - m.learning[0] for m in measured)


def study_seconds(entries: list[PlanEntry], measured: list[Phases], workers: int) -> float:
    """Wall seconds of ``entries`` on ``workers`` slots, each trial priced at the mean of
    the ``measured`` trials' phases."""
    durations = [statistics.mean(m.seconds_for(e.trial_config) for m in measured) for e in entries]
    return makespan(durations, workers)


def print_study(
    spec_path: Path, priced: list[PlanEntry], vgg: list[PlanEntry], rows: dict[int, list[Phases]]
) -> None:
    configs = [e.trial_config for e in priced + vgg]
    env_steps = sum(c.total_steps for c in configs)
    eval_steps = sum(evaluation_steps(c) for c in configs)
    methods = sorted({e.method for e in priced})
    layers = Counter(str(e.params.get("hidden_sizes", "?")) for e in priced + vgg)
    print(
        f"\n{spec_path.name}: {len(configs)} trials, {env_steps:,} env steps and {eval_steps:,} "
        f"evaluation steps; priced: {len(priced)} trials ({', '.join(methods)}) each as the "
        f"measured pixel trial at the spec's budget; vgg: {len(vgg)} trials, cost not measured "
        f"(needs its ImageNet weights file)"
    )
    print(
        "not measured either: learned encoders' fits (vae, cvae), encoders' per-step encoding, "
        "checkpoints, videos; the plan's MLPs ("
        + ", ".join(f"{n} {k}" for k, n in sorted(layers.items()))
        + ") priced at the measured 256x256"
    )
    walls = {c: study_seconds(priced, measured, c) for c, measured in rows.items()}
    best = min(walls, key=lambda c: walls[c])
    measured = rows[best]
    env_side = statistics.mean(m.env_share for m in measured)
    seed_rate = statistics.mean(m.seed_rate for m in measured)
    cores = os.cpu_count() or 1
    trial_seconds = sum(
        statistics.mean(m.seconds_for(e.trial_config) for m in measured) for e in priced
    )
    priced_steps = sum(env_and_eval_steps(e.trial_config) for e in priced)
    print(
        f"best measured: {plural(best, 'trial')} on the GPU at once (gpus_per_trial "
        f"{1 / best:g}): the priced trials in about {format_duration(walls[best])} wall, "
        f"{format_duration(trial_seconds)} of trial time"
    )
    print(
        f"CPU's share: env stepping and rendering (a seed-phase step's time) are "
        f"{100 * env_side:.0f}% of a learning step's time there, about "
        f"{format_duration(priced_steps / seed_rate)} of one core's time over the priced "
        f"trials' env and evaluation steps; this machine has {plural(cores, 'CPU core')} and "
        f"the wall time assumes one core per trial ({plural(best, 'core')}"
        + (")" if best <= cores else ": more than it has, so the figure is optimistic)")
    )


# ---- output ---------------------------------------------------------------------------
def header(gpu: str, bf16: bool | None, threads: int) -> str:
    """torch, the GPU (``torch.cuda.get_device_name``), CUDA, bf16, the CPU, the load."""
    cpu = describe(torch.device("cpu"))["cpu_name"]
    load = os.getloadavg()[0]
    return (
        f"torch {torch.__version__}; GPU: {gpu}; CUDA {torch.version.cuda}; bf16 supported: "
        f"{bf16}; CPU: {cpu}, {os.cpu_count()} cores, load average {load:.1f}; "
        f"{threads} torch thread(s); MUJOCO_GL={os.environ.get('MUJOCO_GL')}"
    )


def gpu_path(args: argparse.Namespace, device: torch.device) -> None:
    on_gpu = device.type == "cuda"
    base = FETCH_A1 if on_gpu else FETCH_CPU
    size = base.image_size
    repeats = args.repeats or REPEATS[device.type]
    if on_gpu:
        bf16 = torch.cuda.is_bf16_supported()
        print(header(torch.cuda.get_device_name(device), bf16, args.threads))
    else:
        bf16 = True  # CPU autocast takes bf16
        print(header("none", None, args.threads))
        print("--gpu-path-on-cpu: the GPU path on the CPU at FETCH_CPU: its figures mean nothing")
    print(f"setting: fetch_reach {describe_sac(base.sac, size)}; median of {repeats}\n")
    matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    rows = [(f"fp32, torch's defaults (matmul TF32 {matmul}, cuDNN TF32 {cudnn}): trials", None)]
    rows += [("fp32, TF32 on", True)]
    print("| SAC update | ms | vs trials' |\n|---|---:|---:|")
    first = None
    for label, flag in rows:
        with tf32(flag):
            ms = ms_per_update(base.sac, size, device, repeats)
        first = first or ms
        print(f"| {label} | {ms:.2f} | {first / ms:.2f}x |", flush=True)
    if bf16:
        with tf32(True):
            ms = ms_per_update(base.sac, size, device, repeats, bf16=True)
        print(f"| bf16 autocast, TF32 on | {ms:.2f} | {first / ms:.2f}x |", flush=True)
    else:
        print("| bf16 autocast | not supported here | |")

    if on_gpu:
        torch.cuda.empty_cache()  # the timed updates' memory, before the trials start
    priced, vgg = study_entries(args.spec)
    for precision in ("fp32", "bf16") if bf16 else ("fp32",):
        config = measured_config(base, args.trial_steps, str(device), args.threads)
        config = dataclasses.replace(config, precision=precision)
        print(
            f"\ntrials in {precision}: {config.total_steps} env steps ({config.seed_steps} seed "
            f"steps), {config.eval_episodes} evaluation episodes every {config.eval_every}, "
            "torch's TF32 defaults; env steps/s per trial and all together, mean over the "
            "trials\n"
        )
        print(
            "| trials at once | gpus_per_trial | learning steps/s per trial | all together | "
            "overlap | seed steps/s | eval steps/s | env side | setup s | study (priced) |"
        )
        print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        results: dict[int, list[Phases]] = {}
        for count in args.concurrency:
            measured = run_together(config, count)
            results[count] = measured
            learn = [m.learn_rate for m in measured]
            env_side = statistics.mean(m.env_share for m in measured)
            print(
                f"| {count} | {1 / count:g} | {statistics.mean(learn):.1f} | {sum(learn):.1f} | "
                f"{100 * overlap(measured):.0f}% | "
                f"{statistics.mean(m.seed_rate for m in measured):.0f} | "
                f"{statistics.mean(m.eval_rate for m in measured):.0f} | {100 * env_side:.0f}% | "
                f"{statistics.mean(m.setup for m in measured):.1f} | "
                f"{format_duration(study_seconds(priced, measured, count))} |",
                flush=True,
            )
        print_study(args.spec, priced, vgg, results)


def cpu_figures(args: argparse.Namespace) -> None:
    device = torch.device("cpu")
    repeats = args.repeats or REPEATS["cpu"]
    print("no GPU found (torch.cuda.is_available() is False): the CPU figures instead")
    print(header("none", None, args.threads))
    print(f"(--trial-steps and --concurrency apply on a GPU); median of {repeats}\n")
    print("| SAC update, fp32, CPU | setting | ms |\n|---|---|---:|")
    for name, base in (("A.1", FETCH_A1), ("FETCH_CPU", FETCH_CPU)):
        ms = ms_per_update(base.sac, base.image_size, device, repeats)
        print(f"| {name} | {describe_sac(base.sac, base.image_size)} | {ms:.0f} |", flush=True)


def positive_ints(text: str) -> list[int]:
    values = [int(v) for v in text.split(",") if v.strip()]
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers like 1,2,4,8, got {text!r}")
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=None, help="timed groups of updates")
    parser.add_argument("--trial-steps", type=int, default=1500, help="env steps per trial")
    parser.add_argument("--concurrency", type=positive_ints, default=[1, 2, 4, 8])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (per trial)")
    parser.add_argument("--spec", type=Path, default=SPEC, help="the study to price")
    parser.add_argument("--gpu-path-on-cpu", action="store_true", help="check the script")
    args = parser.parse_args()
    if args.trial_steps < 3:
        parser.error("--trial-steps must be at least 3")
    torch.set_num_threads(args.threads)
    if torch.cuda.is_available():
        gpu_path(args, torch.device("cuda"))
    elif args.gpu_path_on_cpu:
        gpu_path(args, torch.device("cpu"))
    else:
        cpu_figures(args)


if __name__ == "__main__":
    main()
