"""Update speed against the machine's limit, in every layout and precision.

Prints the CPU (model, and whether it has native bf16: AMX or AVX512-BF16), a dense 2048^3
matmul's GFLOP/s in fp32 and in bf16 measured in the same run with the same threads (the
peaks), then one full SAC-DrQ update (augmentation, critic, actor, temperature, target;
``actor_update_every=1``) per row: 84x84 and 48x48, batch 32, 128 and 256, 32 filters
(A.1's; ``--filters 16``: the CPU studies'), the agent's precisions (fp32, bf16 autocast),
the convolutions channels-last and NCHW. Each row: ms per update (median), the convolution
and matmul GFLOP it does (``torch.utils.flop_counter``), GFLOP/s, and that as a % of the
matching peak. Targets (issue 34): fp32 at batch 256 >= 80% of the fp32 peak, bf16 >= 35%
of the bf16 peak. Last, with ``--trial-steps N``, a real trial at
``bench_learning.FETCH_CPU`` cut to N env steps (``bench_gpu_trial``'s measurement), in
fp32 in either conv layout and in bf16: its env steps per second while learning.

Run: ``./run python benchmarks/bench_update_speed.py [--threads 1] [--repeats 5]
[--sizes 84,48] [--batches 32,128,256] [--filters 32] [--precisions fp32,bf16]
[--trial-steps 1500]``
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from agent.config import SACConfig
from agent.machine import CPUINFO, LAYOUT_VARIABLE, conv_layout, cpu_fields, native_bf16
from agent.sac import PRECISIONS, SAC

#: the targets of issue 34, as a fraction of the matching matmul peak
TARGETS = {"fp32": 0.80, "bf16": 0.35}


def cpu_line() -> str:
    """The CPU model and its native bf16 instructions (the flags /proc/cpuinfo lists)."""
    try:
        fields = cpu_fields(CPUINFO.read_text())
    except OSError:
        return "CPU: unknown (no /proc/cpuinfo)"
    native = native_bf16()
    bf16 = (
        f"native bf16: {', '.join(native)}" if native else "no native bf16 (no AMX, no AVX512-BF16)"
    )
    return (f"CPU: {fields.get('model name', '?')} ({fields.get('vendor_id', '?')} family "
            f"{fields.get('cpu family', '?')} model {fields.get('model', '?')}); {bf16}; "
            f"torch kernels {torch.backends.cpu.get_cpu_capability()}")  # fmt: skip


def matmul_gflops(dtype: torch.dtype, n: int = 2048, repeats: int = 10) -> float:
    a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)
    a @ b  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        a @ b
    return 2 * n**3 * repeats / (time.perf_counter() - start) / 1e9


def random_batch(size: int, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    def images() -> np.ndarray:
        return rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8)

    return {
        "obs": images(),
        "next_obs": images(),
        "goal": images(),
        "action": rng.uniform(-1, 1, (n, 4)).astype(np.float32),
        "reward": rng.uniform(-1, 0, (n, 1)).astype(np.float32),
    }


def median_seconds(call: Callable[[], object], repeats: int) -> float:
    """The median wall seconds of ``repeats`` calls of ``call``."""
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        seconds.append(time.perf_counter() - start)
    return float(np.median(seconds))


def time_update(
    size: int, batch_size: int, filters: int, repeats: int, precision: str, channels_last: bool
) -> tuple[float, float]:
    """(seconds per update, counted GFLOP per update) of one full update."""
    cfg = SACConfig(batch_size=batch_size, num_filters=filters, actor_update_every=1)
    agent = SAC((size, size, 3), (size, size, 3), 4, cfg, torch.device("cpu"), precision,
                channels_last)  # fmt: skip
    batch = random_batch(size, batch_size, np.random.default_rng(0))

    def update() -> None:
        agent.update(batch)

    with FlopCounterMode(display=False) as counter:
        update()  # also the warm-up
    update()
    return median_seconds(update, repeats), counter.get_total_flops() / 1e9


def trial_rates(steps: int, threads: int) -> list[str]:
    """A real trial at FETCH_CPU cut to ``steps`` env steps, in fp32 in both conv layouts
    and in bf16 in this CPU's (``GCRL_CONV_LAYOUT``): env steps per second while it learns
    (``bench_gpu_trial.run_together``, one trial)."""
    from bench_gpu_trial import measured_config, run_together
    from bench_learning import FETCH_CPU

    here = conv_layout(torch.device("cpu"))
    lines = []
    for precision, layout in (("fp32", "channels_last"), ("fp32", "nchw"), ("bf16", here)):
        config = dataclasses.replace(FETCH_CPU, precision=precision)
        os.environ[LAYOUT_VARIABLE] = layout  # the spawned trial process reads it
        try:
            (phases,) = run_together(measured_config(config, steps, "cpu", threads), 1)
        finally:
            del os.environ[LAYOUT_VARIABLE]
        lines.append(f"trial at FETCH_CPU (84x84, 16 filters, batch 32, 1 update per step), "
                     f"{precision}, {layout}, {steps} env steps: {phases.learn_rate:.2f} env "
                     f"steps/s while learning")  # fmt: skip
    return lines


def ints(text: str) -> list[int]:
    return [int(part) for part in text.split(",")]


def precisions(text: str) -> list[str]:
    names = text.split(",")
    unknown = sorted(set(names) - set(PRECISIONS))
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown {unknown}; one of {list(PRECISIONS)}")
    return names


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", type=ints, default=[84, 48])
    parser.add_argument("--batches", type=ints, default=[32, 128, 256])
    parser.add_argument("--filters", type=int, default=32)
    parser.add_argument("--precisions", type=precisions, default=list(PRECISIONS))
    parser.add_argument("--trial-steps", type=int, default=0, help="0: no trial")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(cpu_line())
    print(f"torch {torch.__version__}, {args.threads} thread(s), {args.filters} filters, median of "
          f"{args.repeats} updates")  # fmt: skip
    dtypes = {"fp32": torch.float32, "bf16": torch.bfloat16}
    # only the peaks of the rows asked for: bf16 matmul without native bf16 takes minutes
    peaks = {name: matmul_gflops(dtypes[name]) for name in args.precisions}
    rows = []
    for size in args.sizes:
        for batch_size in args.batches:
            for precision in args.precisions:
                for channels_last in (True, False):
                    seconds, gflop = time_update(
                        size, batch_size, args.filters, args.repeats, precision, channels_last
                    )
                    rows.append((size, batch_size, precision, channels_last, seconds, gflop))
    # the peaks again after the rows: the higher of the two, as the machine allowed
    peaks = {name: max(peak, matmul_gflops(dtypes[name])) for name, peak in peaks.items()}
    print("dense matmul 2048^3: " + ", ".join(f"{name} {peak:.0f} GFLOP/s"
                                               for name, peak in peaks.items()))  # fmt: skip
    print("| image | batch | precision | layout | ms/update | GFLOP | GFLOP/s | % of peak |")
    print("|---|---|---|---|---|---|---|---|")
    for size, batch_size, precision, channels_last, seconds, gflop in rows:
        rate = gflop / seconds
        share = rate / peaks[precision]
        target = ""
        if batch_size == 256:
            met = "met" if share >= TARGETS[precision] else "not met"
            target = f" (target {TARGETS[precision]:.0%}: {met})"
        layout = "channels-last" if channels_last else "NCHW"
        print(f"| {size}x{size} | {batch_size} | {precision} | {layout} | {seconds * 1000:.0f} | "
              f"{gflop:.1f} | {rate:.1f} | {share:.0%}{target} |")  # fmt: skip
    if args.trial_steps:
        print(f"conv layout of this CPU's trials: {conv_layout(torch.device('cpu'))}")
        for line in trial_rates(args.trial_steps, args.threads):
            print(line, flush=True)


if __name__ == "__main__":
    main()
