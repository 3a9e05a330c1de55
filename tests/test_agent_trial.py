"""``agent.train``: the curve, divergence, checkpoints and resume, every env end to end."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch
from conftest import tiny

import agent
from agent import machine
from agent.config import TrialConfig
from agent.envs import ENV_NAMES
from agent.metrics import normalized_auc


class Recorder:
    """A report callback that keeps the last metrics per step, as the sweeper does."""

    def __init__(self, crash_at: int | None = None) -> None:
        self.points: dict[int, dict[str, float]] = {}
        self.calls: list[int] = []
        self.crash_at = crash_at

    def __call__(self, step: int, metrics: dict[str, float]) -> None:
        self.points[step] = metrics
        self.calls.append(step)
        if step == self.crash_at:
            raise KeyboardInterrupt("simulated crash")


def test_import_agent_is_light() -> None:
    import subprocess
    import sys

    code = "import sys, agent; print('torch' in sys.modules, 'mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_train_reports_the_whole_grid() -> None:
    report = Recorder()
    result = agent.train(tiny(), report)
    assert result.steps == (0, 100, 200) and report.calls == [0, 100, 200]
    assert set(result.metrics) == {"success_rate", "final_distance"}
    for i, step in enumerate(result.steps):
        assert report.points[step] == {k: v[i] for k, v in result.metrics.items()}
    assert result.auc == normalized_auc(result.steps, result.metrics["success_rate"])
    assert result.outcome == "completed" and result.resumed_from is None
    assert result.diverged_step is None and result.seconds > 0
    assert all(d > 0 for d in result.metrics["final_distance"])


def test_state_oracle_runs() -> None:
    result = agent.train(tiny(method="state", image_size=None))
    assert result.steps == (0, 100, 200) and result.outcome == "completed"


def stored(config: TrialConfig) -> tuple[list[float], tuple[int, ...]]:
    """The rewards a trial stores in its replay, in order, and its observations' shape."""
    from agent import trial

    rewards: list[float] = []
    shapes: set[tuple[int, ...]] = set()
    real_add = trial.ReplayBuffer.add

    def add(self, action, reward, next_obs):
        rewards.append(reward)
        shapes.add(next_obs.shape)
        return real_add(self, action, reward, next_obs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(trial.ReplayBuffer, "add", add)
        agent.train(config)
    (shape,) = shapes
    return rewards, shape


def test_true_reward_control_learns_from_images_with_the_true_reward() -> None:
    config = tiny(method="true_reward", total_steps=50, seed_steps=50, eval_every=50)
    result = agent.train(config)
    assert result.steps == (0, 50) and result.reward_scale == 1.0
    # the env's own true rewards of the same random episode as the state oracle's, on images
    rewards, shape = stored(config)
    oracle_rewards, oracle_shape = stored(dataclasses.replace(config, method="state"))
    assert rewards == oracle_rewards and all(r < 0 for r in rewards)
    assert shape == (32, 32, 3) and oracle_shape == (2,)


@pytest.mark.parametrize("method", ["pixel", "true_reward"])
def test_auto_reward_scale_makes_random_policy_rewards_about_one(method) -> None:
    config = tiny(method=method, total_steps=200, seed_steps=200, eval_every=200)
    unscaled, _ = stored(config)
    scaled, _ = stored(dataclasses.replace(config, reward_scale="auto"))
    factor = agent.train(dataclasses.replace(config, reward_scale="auto")).reward_scale
    assert scaled == pytest.approx([factor * r for r in unscaled])
    assert 0.5 < -sum(scaled) / len(scaled) < 2.0  # another random episode, same size
    if method == "pixel":  # pixel distances are far from 1 unscaled
        assert -sum(unscaled) / len(unscaled) > 3.0


def test_bad_reward_scale() -> None:
    for bad in (0, -1.0, "big", float("nan"), True):
        with pytest.raises(ValueError, match="reward_scale"):
            tiny(reward_scale=bad)


def test_divergence_stops_the_trial_and_fills_the_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    from agent import sac

    real_update = sac.SAC.update

    def update(self: sac.SAC, batch: dict) -> dict:
        losses = real_update(self, batch)
        if self.num_updates == 30:  # updates run after env steps 50, 51, ...: the 30th at 79
            losses["actor_loss"] = torch.tensor(float("nan"))
        return losses

    monkeypatch.setattr(sac.SAC, "update", update)
    report = Recorder()
    result = agent.train(tiny(total_steps=300), report)
    assert result.outcome == "diverged"
    assert (result.diverged_step, result.diverged_loss) == (79, "actor_loss")
    assert result.steps == (0, 100, 200, 300) and report.calls == [0, 100, 200, 300]
    assert result.metrics["success_rate"][1:] == (0.0, 0.0, 0.0)
    assert all(math.isnan(v) for v in result.metrics["final_distance"][1:])
    assert result.auc == normalized_auc(result.steps, result.metrics["success_rate"])


def test_resume_gives_the_same_curve(tmp_path: Path) -> None:
    config = tiny(total_steps=150, eval_every=50, checkpoint_every=50, checkpoint_dir=str(tmp_path))
    crash = Recorder(crash_at=100)  # after the checkpoint at step 50, before the one at 100
    with pytest.raises(KeyboardInterrupt):
        agent.train(config, crash)
    resumed_report = Recorder()
    resumed = agent.train(config, resumed_report)
    assert resumed.resumed_from == 50
    here = machine.describe(torch.device("cpu"))  # both runs ran here, one from the checkpoint
    assert resumed.machines == ({"from_step": 0, **here}, {"from_step": 50, **here})
    assert resumed_report.calls == [0, 50, 100, 150]  # checkpointed points re-reported
    # what the crashed run reported (step 100 too, evaluated again) is reported identically
    assert all(resumed_report.points[s] == m for s, m in crash.points.items())

    straight = agent.train(dataclasses.replace(config, checkpoint_dir=None))
    assert straight.steps == resumed.steps
    assert straight.metrics == resumed.metrics and straight.auc == resumed.auc
    assert straight.machines == ({"from_step": 0, **here},)


CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
cpu family\t: 6
model\t\t: 143
model name\t: Intel(R) Xeon(R) Platinum 8480+
flags\t\t: fpu avx512f

processor\t: 1
vendor_id\t: GenuineIntel
"""


def test_the_machine_is_described_by_what_its_kernels_depend_on() -> None:
    assert machine.cpu_fields(CPUINFO) == {
        "vendor_id": "GenuineIntel",
        "cpu family": "6",
        "model": "143",
        "model name": "Intel(R) Xeon(R) Platinum 8480+",
    }
    assert machine.cpu_fields("") == {}
    here = machine.describe(torch.device("cpu"))
    assert set(here) == {"cpu", "cpu_name", "kernels", "torch", "conv_layout", "threads"}
    assert here["threads"] == str(torch.get_num_threads())
    assert here["kernels"] == torch.backends.cpu.get_cpu_capability()
    assert here["torch"] == torch.__version__
    assert here["conv_layout"] == machine.conv_layout(torch.device("cpu"))


@pytest.mark.parametrize(
    ("vendor", "layout"),
    [
        ("GenuineIntel", "channels_last"),
        ("AuthenticAMD", "channels_last"),
        ("ARM", "nchw"),
        ("", "nchw"),
    ],
)
def test_the_conv_layout_follows_the_cpu_vendor(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, vendor: str, layout: str
) -> None:
    """Decided by the CPU's vendor (not timed), recorded with the machine; CUDA: channels-last."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(CPUINFO.replace("GenuineIntel", vendor))
    monkeypatch.setattr(machine, "CPUINFO", cpuinfo)
    assert machine.conv_layout(torch.device("cpu")) == layout
    assert machine.describe(torch.device("cpu"))["conv_layout"] == layout
    assert machine.conv_layout(torch.device("cuda")) == "channels_last"
    monkeypatch.setenv("GCRL_CONV_LAYOUT", "nchw")
    assert machine.conv_layout(torch.device("cuda")) == "nchw"
    monkeypatch.setenv("GCRL_CONV_LAYOUT", "NHWC")
    with pytest.raises(ValueError, match="GCRL_CONV_LAYOUT must be channels_last or nchw"):
        machine.conv_layout(torch.device("cpu"))


def test_a_trial_paused_at_a_rung_goes_on_to_the_uninterrupted_curve(tmp_path: Path) -> None:
    """Successive halving: stop_at pauses at a rung with a checkpoint; a later stop_at (or
    none) goes on from it, and the curve is the one of a run that never paused (CPU)."""
    config = tiny(
        total_steps=200, eval_every=50, checkpoint_every=1000, checkpoint_dir=str(tmp_path)
    )
    paused = agent.train(dataclasses.replace(config, stop_at=100))
    assert paused.outcome == "paused" and paused.steps == (0, 50, 100)
    assert paused.auc == pytest.approx(normalized_auc(paused.steps, paused.metrics["success_rate"]))
    again = agent.train(dataclasses.replace(config, stop_at=100))  # a driver relaunched
    assert again.outcome == "paused" and again.resumed_from == 100
    assert again.metrics == paused.metrics
    second = agent.train(dataclasses.replace(config, stop_at=150))
    assert second.outcome == "paused" and second.resumed_from == 100 and second.steps[-1] == 150
    finished = agent.train(config)
    assert finished.outcome == "completed" and finished.resumed_from == 150

    straight = agent.train(dataclasses.replace(config, checkpoint_dir=None))
    assert straight.steps == finished.steps
    assert straight.metrics == finished.metrics and straight.auc == finished.auc
    with pytest.raises(ValueError, match="stop_at"):
        dataclasses.replace(config, stop_at=200)


def test_corrupt_checkpoint_is_ignored(tmp_path: Path) -> None:
    # no updates (seed_steps = total_steps): this test is about the file, not the learner
    config = tiny(
        total_steps=100, seed_steps=100, checkpoint_every=50, checkpoint_dir=str(tmp_path)
    )
    first = agent.train(config)
    path = tmp_path / "checkpoint.pt"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in the middle
    path.write_bytes(bytes(data))
    notices: list[str] = []  # the driver shows them and keeps them in the trial's record
    with pytest.warns(UserWarning, match="corrupt checkpoint"):
        again = agent.train(config, notice=notices.append)
    assert again.resumed_from is None and again.metrics == first.metrics
    (notice,) = notices
    assert notice.startswith(f"discarded its corrupt checkpoint {path}: ")
    assert notice.endswith("; the trial restarts from step 0") and "\n" not in notice
    path.write_bytes(path.read_bytes()[:1000])  # truncated
    with pytest.warns(UserWarning, match="corrupt checkpoint"):
        assert agent.train(config).resumed_from is None


def test_checkpoint_of_another_config_is_refused(tmp_path: Path) -> None:
    config = tiny(
        total_steps=100, seed_steps=100, checkpoint_every=50, checkpoint_dir=str(tmp_path)
    )
    agent.train(config)
    other = dataclasses.replace(config, seed=1)
    with pytest.raises(ValueError, match="checkpoint_dir"):
        agent.train(other)


def test_checkpoint_of_another_study_is_refused(tmp_path: Path) -> None:
    """A checkpoint names the study that wrote it: another study's is never resumed."""
    config = tiny(
        total_steps=100,
        seed_steps=100,
        checkpoint_every=50,
        checkpoint_dir=str(tmp_path),
        checkpoint_owner="study-a",
    )
    agent.train(config)
    with pytest.raises(ValueError, match="another study"):
        agent.train(dataclasses.replace(config, checkpoint_owner="study-b"))
    assert agent.train(config).resumed_from == 50  # its own study resumes it


def test_bad_names_are_clear_errors() -> None:
    with pytest.raises(ValueError, match="method"):
        agent.train(tiny(method="pixle"))
    with pytest.raises(ValueError, match="unknown env"):
        agent.train(tiny(env="point_rech"))


@pytest.mark.parametrize("env", ENV_NAMES)
@pytest.mark.parametrize("method", ["pixel", "state"])
def test_every_env_end_to_end(env: str, method: str) -> None:
    config = tiny(
        env=env,
        image_size=None,
        method=method,
        total_steps=50,
        seed_steps=40,
        eval_every=50,
        eval_episodes=1,
    )
    result = agent.train(config)
    assert result.steps == (0, 50) and result.outcome == "completed"
    assert all(len(v) == 2 for v in result.metrics.values())
    assert "success_rate" in result.metrics
    if env == "sawyer_door":  # both door metrics, as docs/contracts.md names them
        door = {"angle_success_rate", "hand_success_rate", "final_angle_distance"}
        assert door | {"final_hand_distance"} <= set(result.metrics)


@pytest.mark.parametrize("method", ["conv", "vae"])
def test_encoder_methods(method: str) -> None:
    params = {"vae": {"num_images": 64, "epochs": 1, "latent_dim": 8, "batch_size": 32}}
    config = tiny(
        method=method, total_steps=50, eval_every=50, encoder_params=params.get(method, {})
    )
    result = agent.train(config)
    assert result.outcome == "completed"
    if method == "vae":  # what the fit gave, for the user attr encoder_fit
        fit = result.encoder_fit
        assert set(fit) == {"latent_dim", "loss", "recon", "kl", "active_dims", "seconds"}
        assert fit["latent_dim"] == 8 and 0 <= fit["active_dims"] <= 8 and fit["seconds"] > 0
    else:
        assert result.encoder_fit == {}


def test_checkpoint_at_an_object_store_uri() -> None:
    config = tiny(
        total_steps=100, seed_steps=100, checkpoint_every=50, checkpoint_dir="memory://gcrl/t0"
    )
    first = agent.train(config)
    again = agent.train(config)
    assert (first.resumed_from, again.resumed_from) == (None, 50)
    assert again.metrics == first.metrics
