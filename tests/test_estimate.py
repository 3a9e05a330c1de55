"""The cost of a plan before it runs: durations, scheduling, calibration, ``sweeper plan``."""

from __future__ import annotations

import time
import types

import pytest
from conftest import CI_SPEC

from agent.calibrate import Calibration, TrialCosts, per_call
from agent.config import SACConfig, TrialConfig
from sweeper.plan._estimate import format_duration, local_workers, makespan
from sweeper.storage import finished, measured_seconds


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0, "0 s"),
        (42.4, "42 s"),
        (60, "1 min"),
        (725, "12 min"),
        (3600, "1 h"),
        (42_060, "11 h 41 min"),
        (86_400, "1 d"),
        (183_600, "2 d 3 h"),
        (-5, "0 s"),
    ],
)
def test_format_duration_reads_as_a_duration(seconds, text):
    assert format_duration(seconds) == text


def test_makespan_hands_each_trial_to_the_first_free_slot():
    assert makespan([], 2) == 0
    assert makespan([10, 10, 10], 1) == 30
    assert makespan([10, 10, 10], 2) == 20  # 10 + 10 on one slot, 10 on the other
    assert makespan([30, 10, 10, 10], 2) == 30  # the three short ones share the other slot
    assert makespan([10], 2, busy=[25, 5]) == 25  # the new one waits for the 5 s slot
    with pytest.raises(ValueError, match="workers"):
        makespan([1], 0)


def test_local_workers_are_bounded_by_the_cores():
    assert local_workers(2, 1, cores=2) == 2
    assert local_workers(8, 1, cores=2) == 2
    assert local_workers(4, 2, cores=4) == 2
    assert local_workers(2, 4, cores=2) == 1


def test_measured_seconds_are_the_mean_per_method():
    assert measured_seconds([("a", 10.0), ("a", 20.0), ("b", 5.0)]) == {"a": 15.0, "b": 5.0}


def test_only_trials_measured_on_this_cpu_at_these_threads_are_taken():
    """A trial's seconds say little of another CPU kind or thread count: ``finished`` with
    ``here`` keeps those recorded with both in every run (one before threads were: not)."""
    import optuna
    from optuna.trial import TrialState

    zen4 = {"cpu": "AuthenticAMD 25 17", "cpu_name": "AMD EPYC", "threads": "1"}

    def trial(key: str, seconds: float, *machines: dict) -> optuna.trial.FrozenTrial:
        return optuna.trial.create_trial(
            state=TrialState.COMPLETE, value=0.5,
            user_attrs={"key": key, "seconds": seconds},
            system_attrs={"machines": [{"from_step": 0, **m} for m in machines]},
        )  # fmt: skip

    trials = [
        trial("pixel/0/0", 100.0, zen4),
        trial("pixel/0/1", 300.0, zen4, {**zen4, "threads": "2"}),  # resumed at 2 threads
        trial("conv/0/0", 50.0, {**zen4, "cpu": "GenuineIntel 6 167"}),
        trial("conv/0/1", 70.0, {k: v for k, v in zen4.items() if k != "threads"}),
        trial("conv/1/0", 90.0, zen4),
    ]
    for index, t in enumerate(trials):
        t.number = index
    keys = [t.user_attrs["key"] for t in trials]
    here = {"cpu": "AuthenticAMD 25 17", "threads": "1"}
    done, measured = finished(trials, keys, here)
    assert done == set(keys)
    assert measured == {"pixel": 100.0, "conv": 90.0}
    assert finished(trials, keys)[1] == {"pixel": 200.0, "conv": 70.0}  # every machine


def test_trial_costs_add_up_by_hand():
    costs = TrialCosts(setup=100.0, seed_step=0.01, train_step=0.1, eval_step=0.02)
    config = TrialConfig(total_steps=3000, seed_steps=1000, eval_every=1000, eval_episodes=2)
    # 4 evaluations (0, 1000, 2000, 3000) of 2 episodes of 50 steps
    assert costs.seconds(config) == pytest.approx(100 + 10 + 200 + 4 * 2 * 50 * 0.02)
    # until 1500: 2 evaluations, 1000 seed steps, 500 training steps
    assert costs.seconds(config, until=1500) == pytest.approx(100 + 10 + 50 + 2 * 100 * 0.02)


def test_per_call_times_a_call():
    assert per_call(lambda: time.sleep(0.01), min_calls=3, seconds=0) == pytest.approx(
        0.01, rel=0.5, abs=0.01
    )
    calls = []
    # a warm-up slower than the budget: one more call, timed
    assert per_call(lambda: calls.append(time.sleep(0.05)), seconds=0.01) >= 0.05
    assert len(calls) == 2


def test_per_call_leaves_the_warm_up_out():
    """A first call that costs more (allocations, kernels built once) is not the answer,
    however slow it is."""
    durations = iter([0.3, 0.02, 0.02, 0.02, 0.02, 0.02, 0.02])
    answer = per_call(lambda: time.sleep(next(durations)), min_calls=3, seconds=0.05)
    assert answer == pytest.approx(0.02, abs=0.015)


def _point_config(method: str, **kw) -> TrialConfig:
    sac = SACConfig(batch_size=32, updates_per_step=1, num_filters=8, hidden_sizes=(64, 64))
    base = dict(env="point_reach", image_size=32, method=method, sac=sac, device="cpu",
                total_steps=600, seed_steps=200, eval_every=300, eval_episodes=2)  # fmt: skip
    return TrialConfig(**(base | kw))


def test_calibration_times_each_part_once_and_predicts_a_trial():
    from agent.trial import train

    pixel, vae = (
        _point_config("pixel"),
        _point_config("vae", encoder_params={"epochs": 2, "num_images": 300, "latent_dim": 8}),
    )
    with Calibration(min_calls=2, seconds=0.05) as calibration:
        costs = calibration.costs(pixel)
        parts = dict(calibration._parts)
        assert calibration.costs(pixel) == costs and calibration._parts == parts  # cached
        vae_costs = calibration.costs(vae)
    assert 0 < costs.seed_step < costs.train_step
    assert vae_costs.setup > costs.setup > 0  # the envs built; then the fit, scaled
    # the prediction is within a factor of 3 of the trial's measured wall time
    result = train(pixel)
    assert costs.seconds(pixel) / 3 < result.seconds < 3 * costs.seconds(pixel)


def test_calibration_times_vgg_without_its_weights_file(monkeypatch, tmp_path):
    monkeypatch.delenv("GCRL_VGG16_WEIGHTS", raising=False)
    config = _point_config(
        "vgg", encoder_params={"input_size": 32, "weights_path": str(tmp_path / "none.pth")}
    )
    with Calibration(min_calls=1, seconds=0.01) as calibration:
        assert calibration.costs(config).seed_step > 0


def plan_output(capsys) -> tuple[str, dict[str, list[str]]]:
    """What ``sweeper plan`` printed, and its per-method table (above the gradient samples)
    as each method's words: method, trials, env steps, done, the estimate and its source."""
    out = capsys.readouterr().out
    table = out.split("gradient samples per env step")[0]
    return out, {line.split()[0]: line.split() for line in table.splitlines() if line}


def test_sweeper_plan_calibrates_a_new_study_and_measures_a_launched_one(
    ci_study, capsys, tmp_path
):
    from sweeper import cli

    fresh = f"sqlite:///{tmp_path / 'none.db'}"
    assert cli.main(["plan", str(ci_study.spec), "--storage", fresh]) == 0
    out, rows = plan_output(capsys)
    assert rows["linear"][1:4] == ["1", "300", "0"] and rows["linear"][-1] == "calibrated"
    assert "left: 2 of 2 trials" in out and "calibrated in" in out
    assert not (tmp_path / "none.db").exists()  # read-only: no database made

    argv = ["plan", str(ci_study.spec), "--storage", ci_study.storage_url]
    assert cli.main(argv) == 0
    out, rows = plan_output(capsys)
    assert rows["pixel"][3] == "1" and rows["pixel"][-2:] == ["(1", "finished)"]
    assert "left: 0 of 2 trials" in out and "calibrated in" not in out

    # at launch's overrides: the trials measured at 1 thread say nothing of 2 threads
    assert cli.main([*argv, "--threads-per-trial", "2", "--max-concurrent", "1"]) == 0
    out, rows = plan_output(capsys)
    assert rows["pixel"][3] == "1" and rows["pixel"][-1] == "calibrated"
    assert "1 trial at once" in out and "2 threads a trial" in out


@pytest.mark.parametrize("threads", [1, 2])
def test_at_more_than_one_thread_a_trial_the_launch_calibrates_before_ray_starts(
    tmp_path, monkeypatch, capsys, threads
):
    """At one thread a trial the calibration overlaps Ray's start; at more it is done first:
    two torch threads on two cores beside Ray starting timed a trial nearly twice as long."""
    import threading

    from sweeper import cli
    from sweeper.plan._estimate import InBackground
    from sweeper.run import _launch as launcher

    calibrating = []

    def unreachable_ray(*args, **kwargs):
        names = [t.name for t in threading.enumerate()]
        calibrating.append(InBackground.THREAD_NAME in names)
        raise ConnectionError("no Ray here")

    monkeypatch.setattr(launcher, "start_ray", unreachable_ray)
    url = f"sqlite:///{tmp_path / 'study.db'}"
    argv = ["launch", str(CI_SPEC), "--storage", url, "--threads-per-trial", str(threads)]
    assert cli.main(argv) == 2
    assert "cannot reach local Ray: no Ray here" in capsys.readouterr().err
    assert calibrating == [threads == 1]


def test_the_summary_counts_what_is_left_and_warns_past_a_day_of_cpu():
    from sweeper.plan._entries import build_plan
    from sweeper.plan._estimate import TrialEstimate, summary_lines
    from sweeper.spec._models import load_spec

    spec = load_spec(CI_SPEC)
    entries = build_plan(spec).entries
    hours = {e.key: TrialEstimate(15 * 3600.0, "measured", e.trial_config) for e in entries}
    cpu = spec.execution.model_copy(update={"max_concurrent": 2, "gpus_per_trial": 0})
    gpu = cpu.model_copy(update={"gpus_per_trial": 0.5})
    lines = summary_lines(entries, set(), hours, cpu)
    assert lines[0].startswith("left: 2 of 2 trials, 1 d 6 h of trial time; about 15 h at ")
    assert "execution.gpus_per_trial" in lines[-1] and "docs/cluster.md" in lines[-1]
    assert len(summary_lines(entries, set(), hours, gpu)) == 1  # GPUs: no warning
    assert summary_lines(entries, {entries[0].key}, hours, cpu)[0].startswith(
        "left: 1 of 2 trials, 15 h of trial time"
    )


def test_the_launch_eta_knows_the_seed_phase_and_follows_the_pace():
    from agent.calibrate import TrialCosts
    from sweeper.plan._estimate import TrialEstimate
    from sweeper.run._progress import LaunchProgress

    config = TrialConfig(total_steps=1000, seed_steps=500, eval_every=1000, eval_episodes=1)
    # seed steps are free, training steps 1 s: a trial is 500 s, all in its second half
    costs = TrialCosts(setup=0.0, seed_step=0.0, train_step=1.0, eval_step=0.0)
    keys = ["a/0/0", "a/1/0", "a/2/0"]
    estimates = {k: TrialEstimate(costs.seconds(config), "calibrated", config, costs) for k in keys}
    progress = LaunchProgress("s", keys, 1000, estimates=estimates, workers=2)
    for key in keys:
        progress.set_state(key, "left")
    progress.set_state("a/0/0", "running")
    progress.set_state("a/1/0", "running")
    assert progress.eta(now=0.0)[1] == pytest.approx(1000)  # two 500 s trials, then one
    progress.set_step("a/0/0", 400)
    progress.set_step("a/1/0", 400)
    # 800 seed steps done in 10 s: a rate would say 2 s left; the costs know better
    assert progress.eta(now=10.0)[1] == pytest.approx(1000)
    progress.set_step("a/0/0", 600)
    progress.set_step("a/1/0", 600)
    # 200 predicted seconds done in 2 trials x 110 s (the "free" seed steps took 10 s)
    assert progress.eta(now=110.0)[1] == pytest.approx((400 + 500) * 220 / 200)
    progress.set_step("a/0/0", 700)
    progress.set_step("a/1/0", 700)
    # 400 predicted seconds in 2 trials x 210 s: 1.05 x slower than predicted
    assert progress.eta(now=210.0)[1] == pytest.approx((300 + 500) * 420 / 400)
    assert progress.lines(now=210.0)[0].endswith("ETA 14 min")


def test_the_launch_eta_counts_the_start_up_and_runs_down_between_reports():
    """A trial reports only at its evaluations, minutes apart at 1/2 of A.1: the pace is
    taken at its reports, with its start-up, and between them the ETA runs down with the
    clock (it used to grow: a 2.5 h trial showed "ETA 1 d 6 h" eight minutes in)."""
    from agent.calibrate import TrialCosts
    from sweeper.plan._estimate import TrialEstimate
    from sweeper.run._progress import LaunchProgress

    config = TrialConfig(total_steps=15000, seed_steps=1000, eval_every=1000, eval_episodes=1)
    costs = TrialCosts(setup=100.0, seed_step=0.1, train_step=0.5, eval_step=0.0)  # 7,200 s
    estimates = {"a/0/0": TrialEstimate(costs.seconds(config), "calibrated", config, costs)}
    progress = LaunchProgress("s", ["a/0/0"], 15000, estimates=estimates)
    progress.set_state("a/0/0", "running")
    assert progress.eta(now=0.0)[1] == pytest.approx(7200)
    assert progress.eta(now=150.0)[1] == pytest.approx(7050)
    progress.set_step("a/0/0", 1000)  # start-up and seed steps took what was predicted
    assert progress.eta(now=200.0)[1] == pytest.approx(7000)
    assert progress.eta(now=700.0)[1] == pytest.approx(6500)
    progress.set_step("a/0/0", 2000)  # 1,000 steps took 1,000 s: twice the prediction
    assert progress.eta(now=1200.0)[1] == pytest.approx(6500 * 1200 / 700)
    assert progress.eta(now=1300.0)[1] == pytest.approx(6500 * 1200 / 700 - 100)


def test_a_measured_trial_s_seconds_lie_in_its_policy_steps_not_its_seed_phase():
    """A method's measured trial time carries no part costs: spread over all its steps, a
    1/2 trial's seed phase (1,000 random steps in 50 s) made the ETA say 5 min where 1 h
    35 min were left, then 51 min at its next report."""
    from sweeper.plan._estimate import TrialEstimate
    from sweeper.run._progress import LaunchProgress

    config = TrialConfig(total_steps=15000, seed_steps=1000, eval_every=1000, eval_episodes=1)
    estimate = TrialEstimate(7000.0, "measured", config)  # 500 s per 1,000 policy steps
    assert [estimate.until(s) for s in (0, 1000, 2000, 15000, 16000)] == [0, 0, 500, 7000, 7000]
    progress = LaunchProgress("s", ["a/0/0"], 15000, estimates={"a/0/0": estimate})
    progress.set_state("a/0/0", "running")
    assert progress.eta(now=0.0)[1] == pytest.approx(7000)
    progress.set_step("a/0/0", 1000)  # the seed phase: no pace yet, the trial still ahead
    assert progress.eta(now=50.0)[1] == pytest.approx(7000)
    progress.set_step("a/0/0", 2000)  # 1,000 policy steps in 450 s (and 50 s before them)
    assert progress.eta(now=500.0)[1] == pytest.approx(6500 * 500 / 500)
    progress.set_step("a/0/0", 3000)  # then twice as slow
    assert progress.eta(now=1500.0)[1] == pytest.approx(6000 * 1500 / 1000)


def test_a_resumed_trial_s_steps_before_its_checkpoint_are_not_the_launch_s_pace():
    """A trial resumed from its checkpoint at step 12,000 first reports its curve up to
    there again: neither the rate nor the pace counts those steps (they made a relaunched
    study say "391 env steps/s | ETA 18 min" where 13 h were left)."""
    from agent.calibrate import TrialCosts
    from sweeper.plan._estimate import TrialEstimate
    from sweeper.run._progress import LaunchProgress

    config = TrialConfig(total_steps=15000, seed_steps=1000, eval_every=1000, eval_episodes=1)
    costs = TrialCosts(setup=0.0, seed_step=0.0, train_step=0.1, eval_step=0.0)  # 1,400 s
    keys = ["a/0/0", "a/1/0"]
    estimates = {k: TrialEstimate(costs.seconds(config), "calibrated", config, costs) for k in keys}
    progress = LaunchProgress("s", keys, 15000, estimates=estimates, workers=1)
    for key in keys:
        progress.set_state(key, "left")
    progress.set_state("a/0/0", "running", from_step=12000)
    assert progress.eta(now=0.0)[1] == pytest.approx(300 + 1400)
    for step in range(0, 13001, 1000):  # the checkpoint's curve again, then one new step
        progress.set_step("a/0/0", step)
    rate, seconds = progress.eta(now=200.0)
    assert rate == pytest.approx(1000 / 200)
    # 100 predicted seconds took 200 s: 2x slower than predicted
    assert seconds == pytest.approx((200 + 1400) * 2)
    progress.set_state("a/0/0", "completed")
    assert progress.eta(now=600.0)[0] == pytest.approx(3000 / 600)


def test_halving_seconds_count_each_rung_s_trials():
    from sweeper.plan._estimate import TrialEstimate, halving_seconds
    from sweeper.plan._halving import Schedule

    config = TrialConfig(total_steps=400, seed_steps=100, eval_every=100)
    entries = [
        types.SimpleNamespace(key=f"{m}/{c}/0", method=m, seed=0) for m in "ab" for c in range(3)
    ]
    # measured: 300 s a trial, spread over its 300 policy steps, so 1 s per step after 100
    estimates = {e.key: TrialEstimate(300.0, "measured", config) for e in entries}
    schedule = Schedule(stops=(200, 300, 400), sizes=(3, 2, 1), keep=0.5, rule="per_method")
    # per method: 3 x 100 + 2 x 100 + 1 x 100 = 600 s, of 900 without halving
    assert halving_seconds(entries, estimates, schedule) == pytest.approx(2 * 600)
