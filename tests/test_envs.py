"""The goal-image env contract (agent.envs), on every env: Gymnasium's checker, exact
restore after goal rendering, goal image = image at the goal, seeding, bad arguments."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from agent.envs import ENV_ENTRY_POINTS, ENV_NAMES, check_env_name, gym_id, make_env

MUJOCO_ENVS = ("fetch_reach", "fetch_push", "sawyer_door")


@pytest.fixture(scope="module")
def envs():
    """``envs(name, obs_mode)``: one env per name and mode, shared by this module's tests
    (building one and its renderer takes ~0.5 s)."""
    cache = {}

    def get(name: str, obs_mode: str = "image"):
        if (name, obs_mode) not in cache:
            cache[name, obs_mode] = make_env(name, obs_mode=obs_mode)
        return cache[name, obs_mode]

    yield get
    for e in cache.values():
        e.close()


@pytest.fixture(params=ENV_NAMES)
def env(request, envs):
    return envs(request.param)


def snapshot(env) -> np.ndarray:
    """The full simulator state (point_reach has no simulator beyond its position)."""
    if not hasattr(env, "model"):
        return env.controllable_state()
    from agent.envs import _mujoco

    return _mujoco.snapshot(env.model, env.data)


def mean_pixel_distance(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.float64) - b).mean())


@pytest.mark.parametrize("name", ENV_NAMES)
@pytest.mark.parametrize("obs_mode", ["image", "state"])
def test_gymnasium_check_env(name, obs_mode):
    env = gym.make(gym_id(name), obs_mode=obs_mode)
    # spec-based checks re-make the env with gym.make; rendering is checked in image mode
    check_env(env.unwrapped, skip_render_check=obs_mode == "state")
    env.close()


def test_observation_spaces_and_episode_length(env):
    obs, info = env.reset(seed=0)
    size = env.image_size
    assert obs["image"].shape == obs["goal_image"].shape == (size, size, 3)
    assert obs["image"].dtype == np.uint8
    assert tuple(info) == env.metric_names
    for t in range(1, 51):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated
        assert truncated == (t == 50)
    assert tuple(info) == env.metric_names
    assert reward == pytest.approx(env.true_reward(env.controllable_state(), env.goal_state()))


def test_goal_rendering_restores_state_and_frame_exactly(env):
    rng = np.random.default_rng(1)
    env.reset(seed=1)
    for _ in range(5):
        env.step(rng.uniform(-1, 1, env.action_space.shape))
    state, frame = snapshot(env), env.render_image()
    env._render_goal_image()
    np.testing.assert_array_equal(snapshot(env), state)
    np.testing.assert_array_equal(env.render_image(), frame)


def test_goal_rendering_does_not_change_the_episode(env):
    """Same seed and actions twice; the second time the goal is re-rendered mid-episode."""
    actions = np.random.default_rng(2).uniform(-1, 1, (6, *env.action_space.shape))
    runs = []
    for rerender in (False, True):
        env.reset(seed=3)
        frames = []
        for i, a in enumerate(actions):
            if rerender and i == 3:
                env.set_goal_state(env.goal_state())
            frames.append(env.step(a)[0]["image"])
        runs.append((np.stack(frames), snapshot(env)))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_frame_shows_no_goal_marker(env):
    """The current frame does not change when only the goal does."""
    env.reset(seed=8)
    frame = env.render_image()
    low, high = env.state_bounds()
    env.set_goal_state(np.where(env.goal_state() - low > high - env.goal_state(), low, high))
    np.testing.assert_array_equal(env.render_image(), frame)


@pytest.mark.parametrize("name", MUJOCO_ENVS)
def test_the_mocap_handles_are_hidden(name, envs):
    import mujoco

    env = envs(name)
    env.reset(seed=0)
    frame = env.render_image()
    env.data.mocap_pos[0] += 0.2
    mujoco.mj_forward(env.model, env.data)  # moves the mocap's geoms, not the arm
    np.testing.assert_array_equal(env.render_image(), frame)


def test_image_at_the_goal_matches_the_goal_image(env):
    obs, info = env.reset(seed=4)
    assert info["is_success"] == 0.0
    away = mean_pixel_distance(obs["image"], obs["goal_image"])
    reached = env.set_controllable_state(env.goal_state())
    np.testing.assert_allclose(reached, env.goal_state(), atol=1e-3)
    image = env.render_image()
    info = env._info()
    at_goal = mean_pixel_distance(image, env._goal_image)
    # Fetch's far camera shows FetchPush's block as a few pixels: the start image differs
    # from the goal image by little on average, but by far more than the image at the goal
    assert at_goal < 0.5 and away > 10 * at_goal
    assert all(info[k] == 1.0 for k in env.metric_names if k.endswith("success"))
    # far from the goal (the opposite corner of the goal box): no success
    low, high = env.state_bounds()
    far = np.where(env.goal_state() - low > high - env.goal_state(), low, high)
    env.set_controllable_state(far)
    assert env._info()["is_success"] == 0.0


def test_controllable_state_round_trip(env):
    env.reset(seed=5)
    low, high = env.state_bounds()
    for s in np.random.default_rng(5).uniform(low, high, (3, low.size)):
        np.testing.assert_allclose(env.set_controllable_state(s), s, atol=1e-3)
        np.testing.assert_allclose(env.controllable_state(), s, atol=1e-3)


def test_same_seed_same_episode(env):
    """A used env and a fresh one, reset with the same seed, play the same episode."""
    name = next(n for n, ep in ENV_ENTRY_POINTS.items() if ep.endswith(type(env).__name__))
    fresh = make_env(name)
    episodes = []
    for e in (env, fresh):
        obs, info = e.reset(seed=7)
        rng = np.random.default_rng(7)
        images, infos = [obs["image"], obs["goal_image"]], [info]
        for _ in range(5):
            obs, _, _, _, info = e.step(rng.uniform(-1, 1, e.action_space.shape))
            images.append(obs["image"])
            infos.append(info)
        episodes.append((np.stack(images), infos, e.goal_state()))
    fresh.close()
    (im_a, inf_a, g_a), (im_b, inf_b, g_b) = episodes
    np.testing.assert_array_equal(im_a, im_b)
    assert inf_a == inf_b
    np.testing.assert_array_equal(g_a, g_b)


def test_reset_depends_only_on_the_generator(env):
    """What trial checkpoints rely on: restoring ``np_random`` reproduces the next episode,
    whatever the simulator went through before."""
    env.reset(seed=12)
    generator_state = env.np_random.bit_generator.state
    expected = env.reset()[0]
    env.reset(seed=13)
    for _ in range(3):
        env.step(env.action_space.sample())
    env.np_random.bit_generator.state = generator_state
    obs = env.reset()[0]
    for key in obs:
        np.testing.assert_array_equal(obs[key], expected[key])


def test_different_seeds_give_different_goals(env):
    goals = [env.reset(seed=s)[0]["goal_image"] for s in (10, 11)]
    assert not np.array_equal(*goals)


@pytest.mark.parametrize("name", MUJOCO_ENVS)
def test_state_mode_never_renders(name, envs):
    env = envs(name, "state")
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(np.zeros(3))
    assert env._renderer is None
    assert obs["state"].shape == env.observation_space["state"].shape
    np.testing.assert_array_equal(obs["goal_state"], env.goal_state().astype(np.float32))


def test_fetch_push_moves_the_arm_only(envs):
    env = envs("fetch_push", "state")
    env.reset(seed=0)
    block = env.controllable_state()
    target = env.gripper_position() + np.array([0.05, -0.05, 0.1])
    np.testing.assert_allclose(env.set_gripper_position(target), target, atol=1e-3)
    np.testing.assert_array_equal(env.controllable_state(), block)


def test_sawyer_door_metrics_separate_angle_and_hand(envs):
    env = envs("sawyer_door", "state")
    env.reset(seed=0)
    goal = env.goal_state()
    env.set_controllable_state(goal + np.array([0.0, 0.0, 0.0, 0.1]))  # hand right, angle wrong
    info = env._info()
    assert (info["hand_success"], info["angle_success"], info["is_success"]) == (1.0, 0.0, 0.0)
    assert info["angle_distance"] == pytest.approx(0.1, abs=1e-6)


# ---- workspace bounds and camera -------------------------------------------------------
def hand(env) -> np.ndarray:
    """The position the workspace bounds apply to: Fetch's gripper, the Sawyer hand."""
    return (
        env.gripper_position() if hasattr(env, "gripper_position") else env.controllable_state()[:3]
    )


#: every constant action with components in {-1, 0, 1}: the corners, edges and faces
CONSTANT_ACTIONS = [np.array(a, np.float32) - 1.0 for a in np.ndindex(3, 3, 3)]


@pytest.mark.parametrize("name", MUJOCO_ENVS)
def test_the_hand_stays_inside_its_bounds_under_any_constant_action(name, envs):
    env = envs(name, "state")
    low, high = env.hand_bounds()
    worst = 0.0
    for action in CONSTANT_ACTIONS:
        env.reset(seed=0)
        for _ in range(50):
            env.step(action)
            worst = max(worst, np.max(low - hand(env)), np.max(hand(env) - high))
    assert worst < 0.01  # the commanded position is clipped; the arm lags it by < 1 cm


@pytest.mark.parametrize("name", MUJOCO_ENVS)
def test_bounds_contain_every_goal_and_the_start(name, envs):
    env = envs(name, "state")
    env.reset(seed=0)
    low, high = env.hand_bounds()
    assert np.all(low <= hand(env)) and np.all(hand(env) <= high)
    if name != "fetch_push":  # the goal is where the hand must go
        goal_low, goal_high = env.state_bounds()
        assert np.all(low <= goal_low[:3]) and np.all(goal_high[:3] <= high)


@pytest.mark.parametrize("name", ["fetch_reach", "fetch_push"])
def test_without_bounds_the_fetch_arm_leaves_the_box(name):
    env = make_env(name, obs_mode="state", workspace_margin=None)
    bounded = make_env(name, obs_mode="state")
    env.reset(seed=0)
    for _ in range(50):
        env.step(np.array([0.0, 0.0, 1.0]))
    assert hand(env)[2] > bounded.hand_bounds()[1][2] + 0.1
    env.close()
    bounded.close()


@pytest.mark.parametrize("name", MUJOCO_ENVS)
@pytest.mark.parametrize("margin", [-0.1, 0.6, "5cm", True])
def test_bad_workspace_margin(name, margin):
    with pytest.raises(ValueError, match="workspace_margin"):
        make_env(name, obs_mode="state", workspace_margin=margin)


def test_fetch_uses_fetchs_own_viewer_camera():
    from gymnasium_robotics.envs.fetch.fetch_env import DEFAULT_CAMERA_CONFIG

    from agent.envs.fetch import DEFAULT_CAMERA

    assert set(DEFAULT_CAMERA) == set(DEFAULT_CAMERA_CONFIG)
    for key, value in DEFAULT_CAMERA_CONFIG.items():
        np.testing.assert_allclose(DEFAULT_CAMERA[key], value)


# ---- bad arguments: a ValueError that names the argument -------------------------------
def test_unknown_env_name():
    with pytest.raises(ValueError, match=r"unknown env 'fetch_rech'.*did you mean 'fetch_reach'"):
        make_env("fetch_rech")
    with pytest.raises(ValueError, match="unknown env"):
        check_env_name("door")


@pytest.mark.parametrize("name", ENV_NAMES)
@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"image_size": 16}, "image_size must be in"),
        ({"image_size": 48.0}, "image_size must be an integer"),
        ({"obs_mode": "pixels"}, "obs_mode must be one of"),
        ({"render_mode": "human"}, "render_mode must be"),
    ],
)
def test_bad_constructor_arguments(name, kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_env(name, **kwargs)


@pytest.mark.parametrize("name", MUJOCO_ENVS)
def test_unknown_camera_name(name):
    with pytest.raises(ValueError, match="camera must be one of"):
        make_env(name, camera="no_such_camera")


def test_bad_free_camera():
    import mujoco

    from agent.envs._mujoco import make_camera

    model = mujoco.MjModel.from_xml_string("<mujoco/>")
    with pytest.raises(ValueError, match="camera must be a camera name or a dict"):
        make_camera(model, {"lookat": [0, 0, 0], "distance": 1.0})
    bad = {"lookat": [0, 0], "distance": 1.0, "azimuth": 0.0, "elevation": 0.0}
    with pytest.raises(ValueError, match=r"camera\['lookat'\] must be 3 finite numbers"):
        make_camera(model, bad)
    with pytest.raises(ValueError, match=r"camera\['distance'\] must be > 0"):
        make_camera(model, {**bad, "lookat": [0, 0, 0], "distance": 0})
    camera = make_camera(model, {**bad, "lookat": [1, 2, 3], "azimuth": 90})
    assert camera.type == mujoco.mjtCamera.mjCAMERA_FREE and camera.azimuth == 90


def test_sawyer_door_bad_options():
    with pytest.raises(ValueError, match="action_scale"):
        make_env("sawyer_door", action_scale=0.0)
    with pytest.raises(ValueError, match="frame_skip"):
        make_env("sawyer_door", frame_skip=0)


def test_bad_actions(env):
    env.reset(seed=0)
    n = env.action_space.shape[0]
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(np.full(n, np.nan))
    with pytest.raises(ValueError, match="action must lie in"):
        env.step(np.full(n, 1.5))
    with pytest.raises(ValueError, match="action must have shape"):
        env.step(np.zeros(n + 1))


@pytest.mark.parametrize("name", MUJOCO_ENVS)
def test_bad_states(name, envs):
    env = envs(name, "state")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="state must be"):
        env.set_controllable_state([np.nan] * len(env.state_names))
    with pytest.raises(ValueError, match="goal must be"):
        env.set_goal_state([0.0])


def test_step_before_reset():
    env = make_env("point_reach")
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2))


def test_close_twice_is_fine():
    env = make_env("fetch_reach")
    env.reset(seed=0)
    env.close()
    env.close()


def test_a_subclass_missing_a_hook_cannot_be_built():
    """The base classes' hooks are abstract: a forgotten one fails at construction, not
    at the first reset or frame."""
    from agent.envs._mujoco import MujocoGoalImageEnv
    from agent.envs.base import GoalImageEnv
    from agent.envs.point_reach import PointReachEnv

    with pytest.raises(TypeError, match="abstract"):
        GoalImageEnv()

    class NoMetrics(PointReachEnv):
        _metrics = GoalImageEnv._metrics

    with pytest.raises(TypeError, match="_metrics"):
        NoMetrics()

    class NoSim(MujocoGoalImageEnv):
        pass

    with pytest.raises(TypeError, match="_make_sim"):
        NoSim()
