"""Whether a study's trials fit the Ray cluster, and what a launch says when they do not.

``pool_size`` checks the spec's per-trial resources against the connected cluster before
any worker starts: a trial larger than the cluster is refused, a cluster that holds fewer
trials than ``execution.max_concurrent`` is a note, and torch threads beyond the CPUs are
refused beyond Ray's CPUs and a note beyond this machine's cores (``oversubscription``).
``cannot_reach_message`` is the one line for a Ray that cannot be started or joined.
"""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING, TextIO

import ray

from sweeper.run._execution import Unreachable, one_line, resources_fit
from sweeper.spec import plural

if TYPE_CHECKING:
    from sweeper.spec import Execution


def local_cpus(execution: Execution) -> int:
    """The CPUs a local Ray is started with: what the trials at once reserve."""
    return math.ceil(execution.max_concurrent * execution.cpus_per_trial)


def pool_size(execution: Execution, planned: int, stream: TextIO) -> int | None:
    """How many workers to start for ``planned`` keys on the connected Ray cluster; None
    (after printing why) when the spec's trials do not fit it. Notes go to ``stream``."""
    cpus, gpus = execution.cpus_per_trial, execution.gpus_per_trial
    fit = resources_fit(cpus, gpus)
    if fit < 1:
        print(
            f"sweeper launch: execution: a trial needs {cpus:g} CPUs and {gpus:g} GPUs, "
            f"more than the Ray cluster has ({ray.cluster_resources()})",
            file=stream,
        )
        return None
    if fit < execution.max_concurrent:
        print(
            f"sweeper launch: note: the Ray cluster holds {plural(fit, 'trial')} at once, "
            f"not execution.max_concurrent={execution.max_concurrent}",
            file=stream,
        )
    size = min(fit, execution.max_concurrent, planned)
    threads = execution.threads_per_trial
    ray_cpus = ray.cluster_resources().get("CPU", 0)
    refusal = oversubscription(threads, size, ray_cpus, local=execution.address is None)
    if refusal is not None:
        print(f"sweeper launch: execution: {refusal}", file=stream)
        return None
    cores = len(os.sched_getaffinity(0))
    if execution.address is None and threads * size > cores:
        print(
            f"sweeper launch: note: {oversubscription(threads, size, cores, 'here')}",
            file=stream,
        )
    return size


def oversubscription(
    threads: int, trials: int, cpus: float, where: str = "Ray reports", local: bool = False
) -> str | None:
    """Why ``trials`` at once with ``threads`` torch threads each do not fit ``cpus``, and
    the fix; None when they fit. Torch threads beyond the cores make every trial several
    times slower (9x measured), not just the extra ones. ``local``: ``cpus`` are a local
    Ray's, started with max_concurrent x cpus_per_trial CPUs, so running fewer at once
    shrinks them too: only more CPUs a trial (or fewer threads) help."""
    if threads * trials <= cpus:
        return None
    if local:
        fix = (
            f"reserve them (cpus_per_trial: {threads}, or --threads-per-trial {threads}, "
            "which reserves as many) or lower threads_per_trial"
        )
    elif threads > cpus:
        fix = f"lower threads_per_trial to at most {cpus:g}"
    else:
        fix = (
            f"run fewer at once (max_concurrent, --max-concurrent {int(cpus // threads)}), "
            f"lower threads_per_trial, or reserve them (cpus_per_trial: {threads})"
        )
    return (
        f"threads_per_trial {threads} x {plural(trials, 'trial')} at once = "
        f"{plural(threads * trials, 'torch thread')}, more than the {cpus:g} CPUs {where}: every "
        f"trial would run several times slower; {fix}"
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
