"""A study on a multi-node Ray cluster with PostgreSQL storage survives losing a worker node.

Ray's own ``ray.cluster_utils.Cluster`` runs three nodes on this machine (a head and two
workers, one CPU each); ``sweeper launch --address --storage postgresql://...`` drives a
4-trial study with 2 trials at once. Once trials run on two nodes and one of them, on a
worker node, has written a checkpoint, that node is removed. The study must still end with
exactly its budget, every key once, and the lost trial re-run from its checkpoint on
another node, its curve the one the same trial has without interruption. Needs PostgreSQL
on 127.0.0.1:5432 (database ``test``, trust auth).
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PG_URL = os.environ.get("SWEEPER_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/test")
#: a guard against a hung driver, not a bound the study must meet: the loop below ends when
#: the driver does (about a minute here, several on a loaded 2-core machine)
DEADLINE = 900.0


def write_spec(path: Path, study: str, checkpoints: Path) -> None:
    """studies/ci.yaml (tiny point_reach trials) with 2 configurations x 2 methods."""
    from sweeper.spec._models import load_yaml

    spec = load_yaml((REPO / "studies" / "ci.yaml").read_text())
    spec.update(study=study, trials_per_method=2, checkpoints=str(checkpoints))
    spec["budget"].update(env_steps=300, seed_steps=100, eval_every=100, eval_episodes=1)
    spec["execution"].update(max_concurrent=2, cpus_per_trial=1, retries=2, checkpoint_every=100)
    path.write_text(yaml.safe_dump(spec))


@pytest.fixture
def postgres():
    """Optuna's storage on PostgreSQL and a fresh study name; the study is deleted after."""
    import optuna
    import sqlalchemy

    try:
        with sqlalchemy.create_engine(PG_URL).connect() as connection:
            connection.execute(sqlalchemy.text("select 1"))
    except Exception as e:  # every dev machine and CI has it: a missing server is a failure
        pytest.fail(f"PostgreSQL not reachable at {PG_URL}: {type(e).__name__}: {e}")
    storage = optuna.storages.RDBStorage(PG_URL)
    study = f"cluster_test_{uuid.uuid4().hex[:10]}"
    yield storage, study
    with contextlib.suppress(KeyError):  # never created
        optuna.delete_study(study_name=study, storage=storage)
    storage.engine.dispose()


@pytest.fixture
def cluster():
    """A head and two worker nodes on this machine, one CPU each; always shut down."""
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        workers = [cluster.add_node(num_cpus=1) for _ in range(2)]
        cluster.wait_for_nodes()
        yield cluster, workers
    finally:
        ray.shutdown()
        cluster.shutdown()


def _raylet_pid(node) -> int:
    from ray._private import ray_constants

    return node.all_processes[ray_constants.PROCESS_TYPE_RAYLET][0].process.pid


def _parent_pid(pid: int) -> int | None:
    """The parent of ``pid`` (a Ray worker's parent is its node's raylet), None if gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    return next(int(line.split()[1]) for line in status.splitlines() if line.startswith("PPid:"))


def _trials(storage, study_name: str):
    import optuna

    try:
        return optuna.load_study(study_name=study_name, storage=storage).get_trials(deepcopy=False)
    except KeyError:  # not created yet
        return []


@pytest.mark.slow  # about a minute: three Ray nodes, four trials, one re-run
def test_study_survives_losing_a_worker_node(tmp_path, postgres, cluster):
    from optuna.trial import TrialState

    from sweeper.storage import trial_attr

    storage, study = postgres
    ray_cluster, workers = cluster
    spec_path = tmp_path / "spec.yaml"
    checkpoints = tmp_path / "checkpoints"
    write_spec(spec_path, study, checkpoints)

    nodes = {_raylet_pid(node): node for node in [ray_cluster.head_node, *workers]}
    env = {**os.environ, "MUJOCO_GL": "egl", "PYTHONPATH": str(REPO)}
    log = tmp_path / "launch.log"  # a file, not a pipe that could fill up and block the driver
    driver = subprocess.Popen(
        [sys.executable, "-m", "sweeper.cli", "launch", str(spec_path),
         "--address", ray_cluster.address, "--storage", PG_URL],
        cwd=tmp_path, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        seen_on: set[int] = set()  # raylet pids of the nodes that ran a trial
        node_of: dict[int, int] = {}  # worker pid -> raylet pid of its node, while it runs
        removed = lost_key = None
        start = time.monotonic()
        while driver.poll() is None and time.monotonic() - start < DEADLINE:
            running = [t for t in _trials(storage, study) if t.state == TrialState.RUNNING]
            for trial in running:
                worker = trial_attr(trial, "worker")
                node_pid = worker and _parent_pid(worker["pid"])
                if node_pid not in nodes:
                    continue
                node_of[worker["pid"]] = node_pid
                seen_on.add(node_pid)
                node = nodes[node_pid]
                key = trial.user_attrs["key"]
                # Mid-trial: checkpointed, with at least 100 of its 300 steps still to run.
                checkpointed = any(checkpoints.glob(f"*/{key}/checkpoint.pt"))
                early = max(trial.intermediate_values, default=0) <= 100
                ready = len(seen_on) >= 2 and node in workers and checkpointed and early
                if removed is None and ready:
                    ray_cluster.remove_node(node)
                    removed, lost_key, lost_pid = node, key, worker["pid"]
            time.sleep(0.2)
    finally:
        if driver.poll() is None:  # past the deadline, or the test failed
            driver.kill()
        driver.wait(timeout=30)
    output = log.read_text()
    print(output)

    assert removed is not None, f"no worker node was removed mid-study\n{output}"
    assert driver.returncode == 0, output
    assert len(seen_on) >= 2, "trials ran on one node only"

    trials = _trials(storage, study)
    complete = [t for t in trials if t.state == TrialState.COMPLETE]
    keys = [t.user_attrs["key"] for t in complete]
    assert len(complete) == 4 and len(set(keys)) == 4, keys  # exactly the budget, no duplicate
    per_method = {m: sum(k.startswith(f"{m}/") for k in keys) for m in ("pixel", "linear")}
    assert per_method == {"pixel": 2, "linear": 2}, keys
    assert all(t.state != TrialState.RUNNING for t in trials)

    lost = next(t for t in complete if t.user_attrs["key"] == lost_key)
    assert lost.user_attrs["attempts"] == 2 and len(trial_attr(lost, "worker_deaths")) == 1
    assert lost.user_attrs["resumed_from"] in (100, 200), "the re-run must resume its checkpoint"
    assert sorted(lost.intermediate_values) == [0, 100, 200, 300]
    rerun_pid = trial_attr(lost, "worker")["pid"]
    assert rerun_pid != lost_pid
    assert rerun_pid in node_of, "the re-run's worker was never seen running"
    gone = next(pid for pid, node in nodes.items() if node is removed)
    assert node_of[lost_pid] == gone and node_of[rerun_pid] in set(nodes) - {gone}  # another node

    # the resumed curve is the curve of the same trial run without interruption
    from conftest import assert_uninterrupted_curve

    from sweeper.run._launch import prepare

    entry = next(e for e in prepare(str(spec_path), storage=PG_URL)[1].entries if e.key == lost_key)
    assert_uninterrupted_curve(lost, entry.trial_config)
    for trial in complete:
        if trial is not lost:
            assert trial.user_attrs["attempts"] == 1
