"""Where one SAC-DrQ update's time goes, and whether ``torch.compile`` makes it faster.

Profiles ``--updates`` full updates (``torch.profiler``, CPU) at one setting (default
``bench_learning.FETCH_CPU``: 84x84, 16 filters, batch 32; the agent's conv layout on this
CPU, ``agent.machine.conv_layout``) in each precision, and prints the share of the wall
time of each kind of work: convolutions (forward and backward), ReLU, matrix products,
the augmentation's gather, the optimiser steps, casts and copies, the other ATen ops, and
what no ATen op accounts for (Python, autograd and dispatch overhead). Then
the ops that took most time. With ``--compile``: the same updates through
``torch.compile(agent.update)`` from the same weights and batches, their ms per update
against eager's, and the largest relative difference of their losses.

Run: ``./run python benchmarks/profile_update.py [--size 84] [--batch 32] [--filters 16]
[--updates 20] [--compile]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_update_speed import cpu_line, random_batch

from agent import machine
from agent.config import PRECISIONS, SACConfig
from agent.sac import SAC

#: kinds of work, by the ATen op names that do it (the first match wins)
KINDS = (
    ("convolutions", ("convolution", "conv2d", "mkldnn_conv")),
    ("ReLU, forward and backward", ("clamp_min", "threshold_backward", "relu")),
    ("matrix products", ("addmm", "aten::mm", "aten::bmm", "matmul", "linear")),
    ("augmentation gather", ("gather",)),
    ("optimiser steps and target update", ("adam", "lerp_")),
    ("dtype casts and copies (autocast's weight casts)", ("copy_", "_to_copy")),
)


def kind_of(op: str) -> str:
    """The kind of work of ATen op ``op`` (``KINDS``), else "other ATen ops"."""
    name = op.lower()
    for kind, parts in KINDS:
        if any(part in name for part in parts):
            return kind
    return "other ATen ops"


def make_agent(args: argparse.Namespace, precision: str) -> SAC:
    torch.manual_seed(0)
    cfg = SACConfig(batch_size=args.batch, num_filters=args.filters, actor_update_every=1)
    size, device = args.size, torch.device("cpu")
    channels_last = machine.conv_layout(device) == "channels_last"
    return SAC((size, size, 3), (size, size, 3), 4, cfg, device, precision, channels_last)


def timed(update: Callable[[dict], dict], batches: list[dict]) -> tuple[float, list[dict]]:
    """(seconds per update, the losses of each) of ``update`` over ``batches``."""
    torch.manual_seed(1)
    start = time.perf_counter()
    losses = [{k: float(v) for k, v in update(b).items()} for b in batches]
    return (time.perf_counter() - start) / len(batches), losses


def profile_shares(args: argparse.Namespace, precision: str) -> None:
    agent = make_agent(args, precision)
    rng = np.random.default_rng(0)
    batches = [random_batch(args.size, args.batch, rng) for _ in range(args.updates)]
    agent.update(batches[0])  # warm-up
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        for batch in batches:
            agent.update(batch)
        wall_us = (time.perf_counter() - start) * 1e6
    events = prof.key_averages()
    shares: dict[str, float] = {}
    for event in events:
        kind = kind_of(event.key)
        shares[kind] = shares.get(kind, 0.0) + event.self_cpu_time_total
    shares["Python, autograd, dispatch (no ATen op)"] = wall_us - sum(shares.values())
    print(f"\n{precision}: {wall_us / 1000 / len(batches):.1f} ms per update under the "
          f"profiler ({args.updates} updates)")  # fmt: skip
    print("| work | % of wall time |\n|---|---:|")
    for kind, us in sorted(shares.items(), key=lambda item: -item[1]):
        print(f"| {kind} | {100 * us / wall_us:.0f}% |")
    top = sorted(events, key=lambda e: -e.self_cpu_time_total)[: args.top]
    print(f"top {args.top} ops by own time:")
    for event in top:
        print(f"  {event.key:<45} {100 * event.self_cpu_time_total / wall_us:5.1f}%  "
              f"{event.count // len(batches):>4} calls/update")  # fmt: skip


def compare_compile(args: argparse.Namespace, precision: str) -> None:
    rng = np.random.default_rng(0)
    batches = [random_batch(args.size, args.batch, rng) for _ in range(args.updates)]
    eager = make_agent(args, precision)
    eager.update(batches[0])
    eager_s, eager_losses = timed(eager.update, batches[1:])
    agent = make_agent(args, precision)
    # inductor draws its own random numbers unless told to use eager's: without this the
    # compiled update's noise (actions, shifts) differs and so do its losses
    torch._inductor.config.fallback_random = True
    compiled = torch.compile(agent.update)
    start = time.perf_counter()
    try:
        compiled(batches[0])
    except Exception as e:  # a compiler missing or failing here: say so, nothing is kept
        print(f"{precision}: torch.compile failed: {type(e).__name__}: {str(e)[:300]}")
        return
    compile_s = time.perf_counter() - start
    compiled_s, compiled_losses = timed(compiled, batches[1:])
    worst = max(
        abs(c[k] - e[k]) / max(abs(e[k]), 1e-6)
        for c, e in zip(compiled_losses, eager_losses, strict=True)
        for k in e
    )
    print(f"{precision}: eager {eager_s * 1000:.1f} ms/update, compiled {compiled_s * 1000:.1f} "
          f"ms/update ({eager_s / compiled_s:.2f}x; first call {compile_s:.0f} s), largest "
          f"relative loss difference over {len(batches) - 1} updates {worst:.1e}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=84)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--filters", type=int, default=16)
    parser.add_argument("--updates", type=int, default=20)
    parser.add_argument("--top", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--compile", action="store_true", help="also try torch.compile")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(cpu_line())
    print(f"torch {torch.__version__}, {args.threads} thread(s); {args.size}x{args.size}, "
          f"batch {args.batch}, {args.filters} filters, conv layout "
          f"{machine.conv_layout(torch.device('cpu'))}; load average "
          f"{os.getloadavg()[0]:.1f}")  # fmt: skip
    for precision in PRECISIONS:
        profile_shares(args, precision)
    if args.compile:
        print()
        for precision in PRECISIONS:
            compare_compile(args, precision)


if __name__ == "__main__":
    main()
