"""Encoder diagnostics: Algorithm 1 and the analyses on envs with known answers, and the CLI."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from agent.envs import make_env
from encoders import diagnostics as dx
from encoders import make_encoder
from sweeper.cli import main

torch.set_num_threads(1)


class StripeEnv:
    """A fake env whose image shows its state exactly: row d of the red channel holds
    ``s_d * 255`` dithered along the row, so the PIXEL latent distance is ``||s - g||``
    times a constant (up to rounding). With ``arm`` it also has an arm (drawn in the
    green channel unless ``draw_arm`` is False), like fetch_push."""

    state_names = ("a", "b", "c")

    def __init__(self, arm: bool = False, draw_arm: bool = True) -> None:
        self.state = np.zeros(3)
        self.goal = np.zeros(3)
        self.arm = np.zeros(3)
        self.draw_arm = draw_arm
        self.action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.rng = np.random.default_rng(0)
        if arm:
            self.gripper_position = lambda: self.arm.copy()
            self.set_gripper_position = self._set_arm

    def _set_arm(self, xyz: np.ndarray) -> np.ndarray:
        self.arm = np.asarray(xyz, np.float64)
        return self.arm.copy()

    def reset(self, *, seed: int | None = None):
        self.rng = np.random.default_rng(seed)
        self.state, self.goal = self.rng.uniform(0, 1, 3), self.rng.uniform(0, 1, 3)
        return {}, {}

    def step(self, action):
        self.state = np.clip(self.state + 0.1 * np.asarray(action), 0, 1)
        info = {
            "is_success": float(np.linalg.norm(self.state - self.goal) < 0.1),
            "a_success": float(self.state[0] > 0.95),
            "distance": 0.0,
        }
        return {}, 0.0, False, False, info

    def state_bounds(self):
        return np.zeros(3), np.ones(3)

    def controllable_state(self) -> np.ndarray:
        return self.state.copy()

    def goal_state(self) -> np.ndarray:
        return self.goal.copy()

    def set_controllable_state(self, state) -> np.ndarray:
        self.state = np.clip(np.asarray(state, np.float64), 0, 1)
        return self.state.copy()

    def sim_state(self) -> np.ndarray:
        return np.concatenate([self.state, self.arm])

    def set_sim_state(self, state) -> None:
        self.state, self.arm = np.array(state[:3]), np.array(state[3:])

    def goal_image(self) -> np.ndarray:
        saved = self.sim_state()
        self.state = self.goal.copy()
        image = self.render_image()
        self.set_sim_state(saved)
        return image

    def render_image(self) -> np.ndarray:
        dither = (np.arange(64) + 0.5) / 64
        image = np.zeros((32, 64, 3), np.uint8)
        image[:3, :, 0] = np.floor(self.state[:, None] * 250 + dither)
        if self.draw_arm:
            image[3:6, :, 1] = np.floor(np.clip(self.arm, 0, 1)[:, None] * 250 + dither)
        return image


class FarGoalEnv(StripeEnv):
    """A StripeEnv whose reset starts in [0, 0.1]^3 and puts the goal in [0.9, 1]^3: pairs
    from its reset are always more than ``FAR`` apart, uniform pairs rarely."""

    FAR = 0.8 * np.sqrt(3)

    def reset(self, *, seed: int | None = None):
        rng = np.random.default_rng(seed)
        self.state, self.goal = rng.uniform(0, 0.1, 3), rng.uniform(0.9, 1, 3)
        return {}, {}


class NearGoalEnv(StripeEnv):
    """A StripeEnv whose reset puts the goal ``offset`` from the start along the first axis
    (0: exactly at the start)."""

    def __init__(self, offset: float) -> None:
        super().__init__()
        self.offset = offset

    def reset(self, *, seed: int | None = None):
        self.state = np.random.default_rng(seed).uniform(0.2, 0.8, 3)
        self.goal = self.state + np.array([self.offset, 0.0, 0.0])
        return {}, {}


def pixel(shape=(32, 64, 3)):
    return {"pixel": make_encoder("pixel", shape)}


# ---- Algorithm 1 ------------------------------------------------------------------------
def test_least_squares_recovers_a_known_gradient() -> None:
    def f(s: np.ndarray) -> float:
        return np.sin(s[0]) + s[1] ** 2 + 0.5 * s[0] * s[2] - np.exp(0.3 * s[3])

    s = np.array([0.3, -0.7, 1.2, 0.5])
    grad = np.array([np.cos(s[0]) + 0.5 * s[2], 2 * s[1], 0.5 * s[0], -0.3 * np.exp(0.3 * s[3])])
    steps = 1e-3 * dx.random_directions(np.random.default_rng(0), 12, 4)
    delta_r = np.array([f(s + d) - f(s) for d in steps])
    estimate = dx.least_squares_gradient(steps, delta_r)
    assert dx.cosine_distance(estimate, grad) < 0.01
    np.testing.assert_allclose(estimate, grad, rtol=0.01)


def test_hand_computed_fixtures() -> None:
    np.testing.assert_allclose(dx.true_reward_gradient([3.0, 4.0], [0.0, 0.0]), [-0.6, -0.8])
    np.testing.assert_allclose(dx.least_squares_gradient(np.eye(2), np.array([1.0, 2.0])), [1, 2])
    assert dx.cosine_distance(np.array([1.0, 0]), np.array([2.0, 0])) == pytest.approx(0)
    assert dx.cosine_distance(np.array([1.0, 0]), np.array([-1.0, 0])) == pytest.approx(2)
    assert dx.cosine_distance(np.array([1.0, 0]), np.array([0, 3.0])) == pytest.approx(1)
    assert dx.cosine_distance(np.zeros(2), np.array([0, 3.0])) == 1.0
    d = dx.random_directions(np.random.default_rng(0), 5, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)


def test_gradient_agreement_is_exact_when_the_image_shows_the_state() -> None:
    table = dx.gradient_agreement(StripeEnv(), pixel(), num_states=10, alpha=0.05, progress=False)
    assert list(table.columns) == ["encoder", "metric", "value", "sample", "distance"]
    assert len(table) == 10 and (table["metric"] == "cosine_distance").all()
    assert table["value"].max() < 0.01


def test_gradient_agreement_on_point_reach_near_the_goal() -> None:
    env = make_env("point_reach", image_size=32, obs_mode="state")
    table = dx.gradient_agreement(env, pixel((32, 32, 3)), num_states=150, progress=False)
    # the blob images overlap only near the goal: there the pixel reward points the right way
    near = table[table["distance"] < 0.5]
    assert len(near) >= 5 and near["value"].mean() < 0.1


def test_gradient_agreement_draws_start_and_goal_from_the_env_reset() -> None:
    kwargs = {"num_states": 12, "num_directions": 6, "alpha": 0.02, "progress": False}
    reset = dx.gradient_agreement(FarGoalEnv(), pixel(), **kwargs)
    assert (reset["distance"] > FarGoalEnv.FAR).all() and reset["value"].max() < 0.01
    uniform = dx.gradient_agreement(FarGoalEnv(), pixel(), start="uniform", **kwargs)
    assert (uniform["distance"] < FarGoalEnv.FAR).all()
    with pytest.raises(ValueError, match="start must be one of reset, uniform"):
        dx.gradient_agreement(FarGoalEnv(), pixel(), start="box")


def test_gradient_agreement_keeps_near_goals() -> None:
    # goals 1 cm from the start, inside the old hidden 4 * alpha filter: kept, not redrawn
    table = dx.gradient_agreement(NearGoalEnv(0.01), pixel(), num_states=8, progress=False)
    assert len(table) == 8 and "min_goal_distance" not in table
    np.testing.assert_allclose(table["distance"], 0.01, atol=0.004)
    assert table["value"].between(0, 2).all()


def test_a_goal_at_the_start_is_nan_not_redrawn() -> None:
    table = dx.gradient_agreement(NearGoalEnv(0.0), pixel(), num_states=4, progress=False)
    assert len(table) == 4 and table["value"].isna().all() and (table["distance"] == 0).all()
    summary = dx.gradient_summary(table).set_index("metric")["value"]
    assert summary["undefined_samples"] == 4 and np.isnan(summary["mean_cosine_distance"])
    assert np.isnan(dx.true_reward_gradient([1.0, 2.0], [1.0, 2.0])).all()
    assert np.isnan(dx.cosine_distance(np.array([1.0, 0]), np.array([np.nan, np.nan])))


def test_min_goal_distance_filters_and_is_reported() -> None:
    env = StripeEnv()
    table = dx.gradient_agreement(
        env, pixel(), num_states=10, min_goal_distance=0.7, progress=False
    )
    assert len(table) == 10 and (table["distance"] >= 0.7).all()
    assert (table["min_goal_distance"] == 0.7).all()
    summary = dx.gradient_summary(table).set_index("metric")["value"]
    assert summary["min_goal_distance"] == 0.7 and summary["undefined_samples"] == 0
    with pytest.raises(ValueError, match=r"only 0 of 3 \(state, goal\) pairs in 300 draws"):
        dx.gradient_agreement(env, pixel(), num_states=3, min_goal_distance=2.0, progress=False)
    with pytest.raises(ValueError, match="min_goal_distance must be finite and >= 0"):
        dx.gradient_agreement(env, pixel(), min_goal_distance=-0.1)


def test_gradient_summary_by_hand() -> None:
    table = pd.DataFrame(
        {"encoder": ["a", "a", "a", "b"], "value": [0.1, 0.5, np.nan, 1.0], "distance": 1.0}
    )
    rows = dx.gradient_summary(table)
    assert list(rows.columns) == ["encoder", "metric", "value"]
    got = {(e, m): v for e, m, v in rows.itertuples(index=False)}
    assert got == {
        ("a", "mean_cosine_distance"): pytest.approx(0.3),
        ("a", "median_cosine_distance"): pytest.approx(0.3),
        ("a", "undefined_samples"): 1.0,
        ("b", "mean_cosine_distance"): 1.0,
        ("b", "median_cosine_distance"): 1.0,
        ("b", "undefined_samples"): 0.0,
    }


# ---- the other analyses -----------------------------------------------------------------
class WideGoalStripeEnv(StripeEnv):
    """StripeEnv whose goal counts as reached within 0.4, so random episodes reach it."""

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        info["is_success"] = float(np.linalg.norm(self.state - self.goal) < 0.4)
        return obs, reward, terminated, truncated, info


def test_random_exploration_success_is_the_tasks_and_each_flag_is_reported() -> None:
    env = WideGoalStripeEnv()
    table = dx.random_exploration(env, episodes=20, steps=10, progress=False)
    rates = dict(zip(table["metric"], table["value"], strict=True))
    assert list(rates) == ["success_rate", "a_success_rate"]
    assert 0 < rates["a_success_rate"] < 1 and 0 < rates["success_rate"] < 1
    # success_rate counts is_success alone (a part of the goal, a_success, is not success)
    env.action_space.seed(0)
    reached = []
    for episode in range(20):
        env.reset(seed=episode)
        hits = [env.step(env.action_space.sample())[4]["is_success"] for _ in range(10)]
        reached.append(max(hits))
    assert rates["success_rate"] == pytest.approx(np.mean(reached))
    again = dx.random_exploration(WideGoalStripeEnv(), episodes=20, steps=10, progress=False)
    pd.testing.assert_frame_equal(table, again)


def test_reward_correlation() -> None:
    summary, pairs = dx.reward_correlation(StripeEnv(), pixel(), num_pairs=50, progress=False)
    values = summary.set_index("metric")["value"]
    assert values["pearson"] > 0.999 and values["spearman"] > 0.999
    assert list(pairs.columns) == ["encoder", "pair", "true_reward", "latent_reward"]
    assert len(pairs) == 50 and (pairs["true_reward"] <= 0).all()


def test_reward_correlation_draws_pairs_from_the_env_reset() -> None:
    _, reset = dx.reward_correlation(FarGoalEnv(), pixel(), num_pairs=20, progress=False)
    assert (reset["true_reward"] < -FarGoalEnv.FAR).all()
    _, uniform = dx.reward_correlation(
        FarGoalEnv(), pixel(), num_pairs=20, start="uniform", progress=False
    )
    assert (uniform["true_reward"] > -FarGoalEnv.FAR).all()
    # one start and one goal for every pair: the true reward is constant, no correlation
    summary, _ = dx.reward_correlation(NearGoalEnv(0.0), pixel(), num_pairs=5, progress=False)
    assert summary["value"].isna().all()


def test_precision_statistics_by_hand() -> None:
    from encoders.diagnostics.precision import ball, peak_metrics, success_auc

    points = ball(np.random.default_rng(0), np.array([1.0, 2.0]), 0.5, 2000)
    radii = np.linalg.norm(points - [1.0, 2.0], axis=1)
    assert radii.max() <= 0.5 and np.mean(radii < 0.25) == pytest.approx(0.25, abs=0.03)
    succeeded = np.array([True, True, False, False])
    assert success_auc(np.array([3.0, 1.0, 2.0, 0.0]), succeeded) == 0.75  # 3 of 4 pairs
    assert success_auc(np.array([1.0, 1.0, 1.0, 1.0]), succeeded) == 0.5  # ties: a half
    assert np.isnan(success_auc(np.zeros(4), np.zeros(4, bool)))
    # the reward peaks at the state 0.08 away, outside the 0.05 radius
    metrics = peak_metrics(np.array([0.0, 1.0, 0.5]), np.array([0.01, 0.08, 0.2]), 0.05)
    assert metrics["peak_distance"] == 0.08 and metrics["peak_success"] == 0.0
    assert metrics["success_auc"] == 0.0 and metrics["spearman"] == pytest.approx(-0.5)


def test_goal_precision_peaks_where_the_true_reward_does_when_the_image_shows_the_state():
    summary, goals = dx.goal_precision(StripeEnv(), pixel(), num_goals=4, num_states=50,
                                       radius=0.3, success_radius=0.1, progress=False)  # fmt: skip
    got = summary.pivot(index="metric", columns="encoder", values="value")
    peaks = got.loc["peak_distance"]
    assert peaks["pixel"] == pytest.approx(peaks["true_reward"])
    assert got.loc["success_auc", "pixel"] > 0.99 and got.loc["spearman", "pixel"] > 0.99
    assert list(goals.columns) == ["encoder", "metric", "value", "goal"]
    assert len(goals) == 2 * 4 * 4  # (true_reward, pixel) x 4 goals x 4 metrics
    with pytest.raises(ValueError, match="success_radius"):
        dx.goal_precision(StripeEnv(), pixel(), radius=0.1, success_radius=0.2, progress=False)


def test_greedy_descent_follows_a_reward_that_shows_the_state() -> None:
    """On StripeEnv the pixel distance is the true distance times a constant, so greedy
    descent on it picks the true reward's candidates: the same final distances, every
    episode; a random pick does worse. The candidates are the controllers' common ones."""
    summary, episodes = dx.greedy_descent(
        StripeEnv(), pixel(), episodes=6, horizon=25, candidates=8, step_size=1.0,
        progress=False,
    )  # fmt: skip
    by = {name: g.set_index("episode") for name, g in episodes.groupby("encoder")}
    assert set(by) == {"pixel", "true_reward", "random"}
    np.testing.assert_allclose(by["pixel"]["final_distance"], by["true_reward"]["final_distance"],
                               atol=0.01)  # fmt: skip
    assert by["true_reward"]["success"].mean() == 1.0
    assert by["random"]["final_distance"].median() > 3 * by["pixel"]["final_distance"].median()
    rows = summary.set_index(["encoder", "metric"])["value"]
    assert rows[("pixel", "success_rate")] == by["pixel"]["success"].mean()
    assert rows[("random", "median_final_distance")] == by["random"]["final_distance"].median()
    again, _ = dx.greedy_descent(
        StripeEnv(), pixel(), episodes=6, horizon=25, candidates=8, step_size=1.0,
        progress=False,
    )  # fmt: skip
    pd.testing.assert_frame_equal(summary, again)
    with pytest.raises(ValueError, match="two candidates"):
        dx.greedy_descent(StripeEnv(), pixel(), candidates=1, progress=False)


def test_candidate_actions_are_small_moves_in_the_action_box() -> None:
    rng = np.random.default_rng(0)
    low, high = np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 2.0])
    actions = dx.candidate_actions(rng, low, high, 50, 0.5)
    centre = (low + high) / 2
    assert actions.shape == (50, 3) and actions.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(actions - centre, axis=1), 0.5, rtol=1e-6)


@pytest.mark.parametrize("name", ["point_reach", "fetch_reach", "sawyer_door"])
def test_an_env_goes_on_from_a_restored_simulator_state_exactly(name) -> None:
    env = make_env(name, image_size=32 if name != "sawyer_door" else 48, obs_mode="state")
    try:
        env.reset(seed=3)
        action = np.full(env.action_space.shape, 0.5, np.float32)
        saved = env.sim_state()
        env.step(action)
        first = (env.controllable_state(), env.render_image())
        env.step(-action)  # somewhere else, then back
        env.set_sim_state(saved)
        env.step(action)
        np.testing.assert_array_equal(env.controllable_state(), first[0])
        np.testing.assert_array_equal(env.render_image(), first[1])
    finally:
        env.close()


def test_grid_topology() -> None:
    summary, emb = dx.grid_topology(
        StripeEnv(), pixel(), grid_size=7, n_neighbors=5, progress=False
    )
    values = summary.set_index("metric")["value"]
    assert values["procrustes_disparity"] < 0.01 and values["trustworthiness"] > 0.99
    assert len(emb) == 49 and {"i", "j", "state_a", "state_b", "iso_x", "iso_y"} <= set(emb)
    with pytest.raises(ValueError, match="grid dims must differ"):
        dx.grid_topology(StripeEnv(), pixel(), grid_size=7, dims=(1, 1))


def test_arm_object_variance() -> None:
    env = StripeEnv(arm=True)
    assert dx.has_arm(env) and not dx.has_arm(StripeEnv())
    table = dx.arm_object_variance(env, pixel(), num_states=20, progress=False)
    totals = table[table["dim"] < 0].set_index("metric")["value"]
    assert 0 < totals["arm_share"] < 1
    assert (table["metric"] == "arm_variance").sum() == 32 * 64 * 3
    hidden = dx.arm_object_variance(
        StripeEnv(arm=True, draw_arm=False), pixel(), 20, progress=False
    )
    assert hidden.set_index("metric").loc["arm_share", "value"] == 0.0
    with pytest.raises(ValueError, match="gripper_position"):
        dx.arm_object_variance(StripeEnv(), pixel())


def test_random_frames() -> None:
    env = make_env("point_reach", image_size=32, obs_mode="state")
    frames = dx.random_frames(env, 60, seed=3, progress=False)
    assert frames.shape == (60, 32, 32, 3) and frames.dtype == np.uint8
    np.testing.assert_array_equal(frames, dx.random_frames(env, 60, seed=3, progress=False))
    assert not np.array_equal(frames[1], frames[2])  # the policy moves the point


# ---- the CLI ----------------------------------------------------------------------------
SMALL = ["--episodes", "3", "--gradient-states", "3", "--directions", "4", "--pairs", "5",
         "--grid-size", "5", "--variance-states", "3", "--precision-goals", "2",
         "--precision-states", "5", "--descent-episodes", "2", "--descent-horizon", "3",
         "--quiet"]  # fmt: skip


def test_cli_writes_its_files(tmp_path, capsys) -> None:
    code = main(["diagnose", "--env", "point_reach", "--encoders", "pixel,cvae",
                 "--option", "cvae.epochs=1", "--option", "cvae.num_images=20",
                 "--image-size", "32", "--out", str(tmp_path / "{env}"), *SMALL])  # fmt: skip
    assert code == 0
    out = tmp_path / "point_reach"
    for stem in ("exploration", "gradient", "correlation", "precision", "topology", "descent"):
        assert (out / f"{stem}.png").stat().st_size > 1000
        table = pd.read_csv(out / f"{stem}.csv")
        assert list(table.columns[:4]) == ["env", "encoder", "metric", "value"]
    summary = pd.read_csv(out / "summary.csv")
    # true_reward: precision's and descent's; random: descent's
    assert set(summary["encoder"]) == {"none", "pixel", "cvae", "true_reward", "random"}
    assert "mean_cosine_distance" in set(summary["metric"])
    assert "point_reach: wrote" in capsys.readouterr().out
    # Algorithm 1's defaults, recorded: pairs from the env's reset, no near-goal filter
    gradient = pd.read_csv(out / "gradient.csv")
    assert (gradient["start"] == "reset").all() and "min_goal_distance" not in gradient
    drawn = summary["analysis"].isin(["gradient", "correlation"])
    assert (summary.loc[drawn, "start"] == "reset").all()
    assert summary.loc[~drawn, "start"].isna().all()  # the other analyses draw no pairs
    assert "min_goal_distance" not in set(summary["metric"])
    # what the encoders see: 4 resets in a 2 x 2 grid, each the 32-pixel view and goal
    # scaled to 128, labelled
    views = np.asarray(Image.open(out / "views.png").convert("RGB"))
    assert views.shape == (2 * (16 + 128) + 6, 2 * (2 * 128 + 6) + 6, 3)


def test_cli_start_and_min_goal_distance_are_recorded(tmp_path) -> None:
    code = main(["diagnose", "--env", "point_reach", "--encoders", "pixel", "--image-size", "32",
                 "--analyses", "gradient,correlation", "--start", "uniform",
                 "--min-goal-distance", "0.5", "--out", str(tmp_path), *SMALL])  # fmt: skip
    assert code == 0
    gradient = pd.read_csv(tmp_path / "gradient.csv")
    assert (gradient["start"] == "uniform").all() and (gradient["min_goal_distance"] == 0.5).all()
    assert (gradient["distance"] >= 0.5).all()
    assert (pd.read_csv(tmp_path / "correlation_pairs.csv")["start"] == "uniform").all()
    summary = pd.read_csv(tmp_path / "summary.csv")
    assert list(summary.columns) == ["env", "analysis", "encoder", "metric", "value", "start"]
    assert (summary["start"] == "uniform").all()
    rows = summary.set_index("metric")["value"]
    assert rows["min_goal_distance"] == 0.5 and rows["undefined_samples"] == 0


def test_cli_start_choices(capsys) -> None:
    from sweeper.diagnose import cli_diagnose as diagnose

    assert diagnose.START_MODES == dx.START_MODES  # spelled out there to keep --help light
    with pytest.raises(SystemExit) as exit_info:
        main(["diagnose", "--env", "point_reach", "--start", "box"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'box'" in capsys.readouterr().err


def test_diagnose_help_shows_real_defaults_and_the_env_names(capsys) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["diagnose", "--help"])
    assert exit_info.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "(default: None)" not in out and "(default: [])" not in out
    assert "(default: first two)" in out and "(default: first two) (default" not in out
    assert "comma-separated: point_reach, fetch_reach, fetch_push, sawyer_door" in out
    assert "--seed SEED seeds the encoders' random weights" in out and "(default: 0)" in out


@pytest.mark.parametrize("command", ["diagnose", "launch", "aggregate"])
def test_help_wraps_between_words_only(command, capsys, monkeypatch) -> None:
    """argparse broke a word longer than the room left on a line ("gr adient" in
    ``--analyses``' default): at any width the help holds the same words as on one line."""

    def words(columns: int) -> list[str]:
        monkeypatch.setenv("COLUMNS", str(columns))
        with pytest.raises(SystemExit):
            main([command, "--help"])
        return capsys.readouterr().out.split()

    wide = words(1000)
    for columns in (40, 60, 80, 100):
        assert words(columns) == wide, columns


def test_cli_on_fetch_push(tmp_path) -> None:
    code = main(["diagnose", "--env", "fetch_push", "--encoders", "pixel", "--image-size", "32",
                 "--out", str(tmp_path), *SMALL])  # fmt: skip
    assert code == 0
    assert (tmp_path / "variance.png").exists()
    summary = pd.read_csv(tmp_path / "summary.csv")
    assert "arm_share" in set(summary["metric"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--encoders", "pixel,cnv"], "unknown encoder 'cnv'.*known encoders: pixel, linear"),
        (["--env", "fetch_rech"], "unknown env 'fetch_rech'.*known envs: point_reach"),
        (["--encoders", "vae", "--option", "vae.latnt_dim=8"], "valid options: latent_dim"),
        (["--encoders", "vae", "--option", "vae.latent_dim=12"], "latent_dim must be one of"),
        (["--option", "beta=3"], "ENCODER.KEY=VALUE"),
        (["--option", "vae.beta=3"], "not in --encoders"),
        (["--analyses", "gradient,isomap"], "unknown analysis 'isomap'"),
        (["--grid-dims", "x,q"], "unknown state 'q'; states: x, y"),
        (["--pairs", "0"], r"--pairs must be in \[3, 10000\], got 0"),
        (["--precision-states", "1"], r"--precision-states must be in \[2, 10000\], got 1"),
        # issue 35: a traceback, or hours and GBs without a word
        (["--seed", "-1"], r"--seed must be in \[0, 4294967295\], got -1"),
        (["--pairs", "1000000000000"], r"--pairs must be in \[3, 10000\], got 1000000000000"),
        (["--gradient-states", "1000000000000"], r"--gradient-states must be in \[1, 10000\]"),
        (["--directions", "1000000"], r"--directions must be in \[1, 1000\]"),
        (["--grid-size", "100000"], r"--grid-size must be in \[5, 64\]"),
        (["--episodes", "0"], r"--episodes must be in \[1, 100000\]"),
        (["--descent-episodes", "1000000000"], r"--descent-episodes must be in \[1, 10000\]"),
        (["--descent-horizon", "1000000"], r"--descent-horizon must be in \[1, 1000\]"),
        (["--descent-candidates", "1000000"], r"--descent-candidates must be in \[2, 100\]"),
        (["--descent-step", "inf"], r"--descent-step must be in \(0, 1\]"),
        (["--alpha", "inf"], "--alpha must be positive and finite, got inf"),
        (["--threads", "100000"], r"--threads must be in \[1, 256\]"),
        (["--success-radius", "0.2"], "need 0 < --success-radius < --precision-radius"),
        (["--min-goal-distance", "-1"], "--min-goal-distance must be finite and at least 0"),
        (["--min-goal-distance", "nan"], "--min-goal-distance must be finite and at least 0"),
    ],
)
def test_cli_bad_input_exits_2_with_a_message(args, message, capsys, tmp_path) -> None:
    argv = ["diagnose", "--env", "point_reach", "--out", str(tmp_path), *args]
    if "--env" in args:
        argv = ["diagnose", "--out", str(tmp_path), *args]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("sweeper diagnose: error:") and len(err.strip().splitlines()) == 1
    assert re.search(message, err)
    assert not any(tmp_path.iterdir())


def test_an_out_folder_that_cannot_be_created_is_one_line(capsys, tmp_path) -> None:
    (tmp_path / "a_file").write_text("")
    out = tmp_path / "a_file" / "diagnostics"
    assert main(["diagnose", "--env", "point_reach", "--out", str(out), *SMALL]) == 2
    err = capsys.readouterr().err
    assert err == f"sweeper diagnose: error: --out: cannot create {out}: Not a directory\n"


def test_every_analysis_shows_its_progress(capsys, tmp_path) -> None:
    """A long analysis says how far it is: each prints ``[diagnose] <what> i/n``."""
    small = [arg for arg in SMALL if arg != "--quiet"]
    assert main(["diagnose", "--env", "point_reach", "--encoders", "pixel", "--image-size", "32",
                 "--out", str(tmp_path), *small]) == 0  # fmt: skip
    err = capsys.readouterr().err
    for label in ("random agent episodes 3/3", "gradient agreement states 3/3",
                  "correlation pairs 5/5", "precision states 12/12", "topology grid states 25/25",
                  "descent steps 18/18"):  # fmt: skip
        assert f"[diagnose] {label}" in err, err
    assert "[diagnose] point_reach: the variance analysis is for fetch_push; skipped" in err


# ---- every analysis starts from a freshly reset env (issue 12) --------------------------
@pytest.fixture
def fetch_push_envs():
    """``make()`` builds a 32-pixel fetch_push in state mode; all are closed afterwards."""
    made = []

    def make():
        made.append(make_env("fetch_push", image_size=32, obs_mode="state"))
        return made[-1]

    yield make
    for env in made:
        env.close()


def move_the_arm(env) -> None:
    """The exploration analysis: random actions leave the arm somewhere else."""
    before = env.gripper_position()
    dx.random_exploration(env, episodes=2, steps=10, progress=False)
    assert np.linalg.norm(env.gripper_position() - before) > 0.02  # or the test proves nothing


def test_gradient_rows_do_not_depend_on_an_earlier_exploration(fetch_push_envs) -> None:
    encoders = pixel((32, 32, 3))
    kwargs = {"num_states": 3, "num_directions": 4, "progress": False}
    alone = dx.gradient_agreement(fetch_push_envs(), encoders, **kwargs)
    env = fetch_push_envs()
    move_the_arm(env)
    after = dx.gradient_agreement(env, encoders, **kwargs)
    pd.testing.assert_frame_equal(after, alone, check_exact=True)


@pytest.mark.parametrize(
    "analysis",
    [
        lambda env, enc: dx.reward_correlation(env, enc, num_pairs=4, progress=False)[1],
        lambda env, enc: dx.grid_topology(env, enc, grid_size=5, n_neighbors=4, progress=False)[1],
        lambda env, enc: dx.arm_object_variance(env, enc, num_states=3, progress=False),
    ],
    ids=["correlation", "topology", "variance"],
)
def test_other_analyses_do_not_depend_on_an_earlier_exploration(fetch_push_envs, analysis) -> None:
    # CONV, not PIXEL: a linear encoder cancels an arm that is the same in both images
    encoders = {"conv": make_encoder("conv", (32, 32, 3), seed=0)}
    alone = analysis(fetch_push_envs(), encoders)
    env = fetch_push_envs()
    move_the_arm(env)
    pd.testing.assert_frame_equal(analysis(env, encoders), alone, check_exact=True)


def test_every_analysis_the_command_offers_has_a_runner_in_order() -> None:
    from sweeper.diagnose import _analyses as analyses
    from sweeper.diagnose import cli_diagnose as diagnose

    assert tuple(analyses.RUNNERS) == diagnose.ANALYSES
