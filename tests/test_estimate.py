"""The cost of a plan before it runs: durations, scheduling, calibration, ``sweeper plan``."""

from __future__ import annotations

import time

import pytest

from agent.calibrate import Calibration, TrialCosts, per_call
from agent.config import SACConfig, TrialConfig
from sweeper.estimate import format_duration, local_workers, makespan, measured_seconds


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
    # a warm-up slower than the budget is the answer: one call
    assert per_call(lambda: calls.append(time.sleep(0.05)), seconds=0.01) >= 0.05
    assert len(calls) == 1


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
    assert costs.setup == 0 and 0 < costs.seed_step < costs.train_step
    assert vae_costs.setup > 0  # the fit, scaled to 300 images and 2 epochs
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


def test_sweeper_plan_calibrates_a_new_study_and_measures_a_launched_one(
    ci_study, capsys, tmp_path
):
    from sweeper import cli

    fresh = f"sqlite:///{tmp_path / 'none.db'}"
    assert cli.main(["plan", str(ci_study.spec), "--storage", fresh]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line}
    # method, trials, env steps, done, then the estimate and its source
    assert rows["linear"][1:4] == ["1", "300", "0"] and rows["linear"][-1] == "calibrated"
    assert "left: 2 of 2 trials" in out and "calibrated in" in out
    assert not (tmp_path / "none.db").exists()  # read-only: no database made

    assert cli.main(["plan", str(ci_study.spec), "--storage", ci_study.storage_url]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line}
    assert rows["pixel"][3] == "1" and rows["pixel"][-2:] == ["(1", "finished)"]
    assert "left: 0 of 2 trials" in out and "calibrated in" not in out


def test_a_plan_of_more_than_a_day_of_cpu_warns_naming_the_gpu_option():
    from sweeper.show_plan import cpu_warning

    text = cpu_warning(2 * 86_400)
    assert "2 d" in text and "execution.gpus_per_trial" in text and "docs/cluster.md" in text
