"""Update speed against the machine's limit.

Times one full SAC-DrQ update (augmentation, critic, actor, temperature, target) at
84x84 and 48x48, batch 256, and prints the achieved GFLOP/s of the convolution and
matmul FLOPs it does (counted by ``torch.utils.flop_counter``) next to a dense fp32
matmul measured in the same run with the same threads. Target: >= 50% of the matmul.

Run: ``.venv/bin/python benchmarks/bench_update_speed.py [--threads 2] [--repeats 10]``
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from agent.config import SACConfig
from agent.sac import SAC


def matmul_gflops(n: int = 2048, repeats: int = 10) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
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


def time_update(size: int, batch_size: int, repeats: int) -> tuple[float, float]:
    """(seconds per update, counted GFLOP per update)."""
    cfg = SACConfig(batch_size=batch_size)
    agent = SAC((size, size, 3), (size, size, 3), 4, cfg, torch.device("cpu"))
    batch = random_batch(size, batch_size, np.random.default_rng(0))
    with FlopCounterMode(display=False) as counter:
        agent.update(batch)  # also the warm-up
    return median_seconds(lambda: agent.update(batch), repeats), counter.get_total_flops() / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=256)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), batch {args.batch_size}")
    peak_before = matmul_gflops()
    rows = [(size, *time_update(size, args.batch_size, args.repeats)) for size in (84, 48)]
    peak = max(peak_before, matmul_gflops())
    print(f"dense fp32 matmul 2048^3: {peak:.1f} GFLOP/s")
    for size, seconds, gflop in rows:
        rate = gflop / seconds
        print(
            f"{size}x{size}: {seconds * 1000:.0f} ms/update, {gflop:.1f} GFLOP counted, "
            f"{rate:.1f} GFLOP/s = {100 * rate / peak:.0f}% of matmul "
            f"({'PASS' if rate >= 0.5 * peak else 'FAIL'} at the 50% target)"
        )


if __name__ == "__main__":
    main()
