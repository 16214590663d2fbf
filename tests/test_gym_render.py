"""The Gymnasium wrapper and the top-down renderer."""

import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from offline_rl_core.task.pusher_reach import MAX_STEPS, PusherReachEnv
from offline_rl_core.task.gym_env import ENV_ID, PusherReachGymEnv, register_gym_envs
from offline_rl_core.task.render import TopDownRenderer, camera_pixels, render_top_down, save_png


@pytest.fixture
def quiet_unbounded_box():
    # The observation space is unbounded by design (joint velocities have no limit);
    # check_env warns about that and nothing else.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is.*infinity")
        yield


def test_check_env_passes(quiet_unbounded_box):
    register_gym_envs()
    register_gym_envs()  # idempotent
    env = gymnasium.make(ENV_ID, render_mode="rgb_array")
    check_env(env.unwrapped)
    env.close()


def test_make_with_module_prefix_needs_no_prior_import():
    env = gymnasium.make("offline_rl_core.task.gym_env:" + ENV_ID)
    assert isinstance(env.unwrapped, PusherReachGymEnv)
    assert env.spec.max_episode_steps is None  # no TimeLimit: the env truncates itself


def test_episode_is_the_classic_env_in_five_tuples():
    env = gymnasium.make(ENV_ID)
    classic = PusherReachEnv()
    obs, info = env.reset(seed=17)
    assert obs.tobytes() == classic.reset(17).tobytes() and info["episode_seed"] == 17
    rng = np.random.default_rng(0)
    for t in range(1, MAX_STEPS + 1):
        action = rng.uniform(-1, 1, 2).astype(np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        c_obs, c_reward, c_done, c_info = classic.step(action)
        assert obs.tobytes() == c_obs.tobytes() and reward == c_reward and info["dist"] == c_info["dist"]
        assert terminated is False and truncated == (t == MAX_STEPS) and (terminated or truncated) == c_done
    env.close()


def test_reset_seeding():
    env = PusherReachGymEnv()
    classic = PusherReachEnv()
    for seed in (0, 5, 2**40):
        assert env.reset(seed=seed)[0].tobytes() == classic.reset(seed).tobytes()
    env.reset(seed=3)
    _, a = env.reset()
    _, b = env.reset()
    assert a["episode_seed"] != b["episode_seed"]  # fresh seeds from np_random
    env.reset(seed=3)
    assert env.reset()[1]["episode_seed"] == a["episode_seed"]  # ... reproducibly
    assert env.reset()[0].tobytes() == classic.reset(b["episode_seed"]).tobytes()


def test_terminate_on_success_is_terminated_not_truncated():
    from offline_rl_core.task.expert import reach_action

    env = PusherReachGymEnv(terminate_on_success=True)
    env.reset(seed=0)
    for _ in range(MAX_STEPS):
        _, _, terminated, truncated, info = env.step(reach_action(env.env))
        if terminated or truncated:
            break
    assert terminated and not truncated and info["success"]


@pytest.mark.parametrize("backend", ["auto", "numpy"])
def test_render_shows_arm_and_target(backend, tmp_path):
    env = PusherReachEnv()
    env.reset(3)
    image = render_top_down(env, width=160, height=120, backend=backend)
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8
    background = image[2, 2].astype(int)  # a corner: floor only
    points = camera_pixels(env.model, env.data, [env.target, env.data.xpos[env.model.body("link2").id]], 160, 120)
    for col, row in np.rint(points).astype(int):
        assert 0 <= col < 160 and 0 <= row < 120
        patch = image[row - 1 : row + 2, col - 1 : col + 2].astype(int)
        assert np.abs(patch - background).sum(axis=2).min() > 30, (backend, col, row)
    path = save_png(image, tmp_path / "frame.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_gym_render_rgb_array():
    env = PusherReachGymEnv(render_mode="rgb_array", width=64, height=48)
    assert PusherReachGymEnv().render() is None  # no render_mode, no picture
    env.reset(seed=1)
    first = env.render()
    assert first.shape == (48, 64, 3) and first.dtype == np.uint8 and first.std() > 0
    env.step([1.0, 1.0])
    for _ in range(5):
        env.step([1.0, 1.0])
    assert not np.array_equal(env.render(), first)  # the arm moved
    env.close()
    env.close()


def test_auto_falls_back_to_numpy_when_no_gl_context_renders(monkeypatch):
    import offline_rl_core.task.render as render

    class BrokenContext:
        def __init__(self, width, height):
            raise RuntimeError("no display")

    monkeypatch.setattr(render, "_gl_context_classes", lambda: iter([("egl", BrokenContext)]))
    env = PusherReachEnv()
    env.reset(0)
    renderer = TopDownRenderer(env.model, 40, 30)
    assert renderer.backend == "numpy" and renderer.render(env.data).shape == (30, 40, 3)
    with pytest.raises(RuntimeError, match="no OpenGL backend could render: egl: no display"):
        TopDownRenderer(env.model, 40, 30, backend="gl")


def test_the_backend_reported_is_the_one_that_renders(monkeypatch):
    """``backend`` names the first GL backend that can render here (numpy when none can),
    and ``MUJOCO_GL=disable`` means numpy."""
    from offline_rl_core.task.render import _gl_context_classes, _GLRenderer

    model = PusherReachEnv().model
    works = None
    for name, context_cls in _gl_context_classes():
        try:
            _GLRenderer(model, 32, 32, context_cls).close()
        except Exception:  # noqa: BLE001 - this backend cannot render here
            continue
        works = name
        break
    renderer = TopDownRenderer(model, 32, 32)
    try:
        assert renderer.backend == (works or "numpy")
    finally:
        renderer.close()
    monkeypatch.setenv("MUJOCO_GL", "disable")
    renderer = TopDownRenderer(model, 32, 32)
    try:
        assert renderer.backend == "numpy"
    finally:
        renderer.close()
