"""student_gif: one seed's deterministic policy on one test level, rendered to a GIF.

A CartPole whose renderer paints the state's step counter into the frame checks which states become
frames (stop at done, the max_steps cap, frame thinning); the lander checks the real renderer with a
freshly initialised tiny student taken from a vmapped RunState.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image, ImageSequence

import envs
from envs.cartpole import CartPole
from shed_jax import eval_sets
from shed_jax.loop import RunState
from shed_jax.student import PPOConfig, make_student
from shed_jax.visualize import frame_indices, student_gif


class _CountingCartPole(CartPole):
    """CartPole whose frame is a flat grey of value 20 * time (the step the frame shows)."""

    def render(self, state, params=None):
        return np.full((24, 32, 3), 20 * int(state.time), np.uint8)


def _read_gif(path):
    with Image.open(path) as im:
        frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(im)]
        return frames, im.size, im.info.get("duration")


@pytest.fixture(scope="module")
def cartpole():
    env = _CountingCartPole()
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=2, num_steps=8, update_epochs=1, num_minibatches=1,
                                                  actor_hidden=(8,), critic_hidden=(8,)))
    # never terminates (huge thresholds), so each episode is truncated at exactly max_steps = 7
    level = env.default_params.replace(max_steps=jnp.int32(7), x_threshold=jnp.float32(1e6),
                                       theta_threshold=jnp.float32(1e6))
    levels = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), level)
    states = jax.jit(jax.vmap(student.init))(jax.random.split(jax.random.PRNGKey(0), 3))
    return env, student, states, levels


def test_frames_stop_at_done_and_at_max_steps(cartpole, tmp_path):
    env, student, states, levels = cartpole
    # the level's own time limit: 7 steps, frames show times 0..6
    path = student_gif(env, student, states, levels, tmp_path / "a.gif", seed_index=2, level_index=1, caption=False)
    frames, size, duration = _read_gif(path)
    assert size == (32, 24) and duration == 30  # fps 30: 33 ms, stored by GIF in 1/100 s
    assert [int(f[0, 0, 0]) for f in frames] == [0, 20, 40, 60, 80, 100, 120]
    # a longer scan still stops at the first done (the auto-reset episode is not shown)
    frames, _, _ = _read_gif(student_gif(env, student, states, levels, tmp_path / "b.gif", max_steps=20, caption=False))
    assert [int(f[0, 0, 0]) for f in frames] == [0, 20, 40, 60, 80, 100, 120]
    # a shorter cap cuts the episode
    frames, _, _ = _read_gif(student_gif(env, student, states, levels, tmp_path / "c.gif", max_steps=4, caption=False))
    assert [int(f[0, 0, 0]) for f in frames] == [0, 20, 40, 60]
    # thinning keeps every ceil(7/3) = 3rd step and the last one
    frames, _, _ = _read_gif(student_gif(env, student, states, levels, tmp_path / "d.gif", max_frames=3, caption=False))
    assert [int(f[0, 0, 0]) for f in frames] == [0, 60, 120]


def test_single_seed_state_and_bad_indices(cartpole, tmp_path):
    env, student, states, levels = cartpole
    one = jax.tree_util.tree_map(lambda x: x[0], states)  # an unbatched StudentState
    frames, _, _ = _read_gif(student_gif(env, student, one, levels, tmp_path / "one.gif", max_steps=3, caption=False))
    assert len(frames) == 3
    with pytest.raises(IndexError, match="seed_index 3 out of range for 3 seed"):
        student_gif(env, student, states, levels, tmp_path / "x.gif", seed_index=3)
    with pytest.raises(IndexError, match="level_index 2 out of range for 2 test level"):
        student_gif(env, student, states, levels, tmp_path / "x.gif", level_index=2)
    with pytest.raises(IndexError, match="unbatched"):
        student_gif(env, student, one, levels, tmp_path / "x.gif", seed_index=1)


def test_env_without_renderer_raises_not_implemented(tmp_path):
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=2, num_steps=8, num_minibatches=1))
    with pytest.raises(NotImplementedError, match="'cartpole' has no renderer"):
        student_gif(env, student, None, None, tmp_path / "x.gif")
    assert not (tmp_path / "x.gif").exists()


def test_frame_indices():
    assert frame_indices(5, None) == [0, 1, 2, 3, 4]
    assert frame_indices(5, 10) == [0, 1, 2, 3, 4]
    assert frame_indices(10, 4) == [0, 3, 6, 9]
    assert frame_indices(11, 4) == [0, 3, 6, 9, 10]
    with pytest.raises(ValueError):
        frame_indices(0, 4)


def test_lander_gif_from_a_vmapped_run_state(tmp_path):
    env = envs.make("lander")
    student = make_student(env, PPOConfig.for_env("lander", num_envs=2, num_steps=8, update_epochs=1, num_minibatches=1))
    keys = jax.random.split(jax.random.PRNGKey(1), 2)
    state = RunState(student=jax.jit(jax.vmap(student.init))(keys), method=None, key=keys, step=jnp.zeros(2, jnp.int32))
    tests = eval_sets.lander_test_set().to_params(env.default_params)
    path = student_gif(env, student, state, tests, tmp_path / "lander.gif", seed_index=1, level_index=3, max_steps=10, fps=25)
    frames, size, duration = _read_gif(path)
    assert len(frames) == 10  # a falling lander does not land or crash within 10 steps
    assert size == (600, 400) and duration == 40
    assert all(f.shape == (400, 600, 3) for f in frames)
    # the frames show motion (the lander falls) and real drawing (sky, ground, lander colours)
    centre = (slice(None), slice(200, 400))  # the lander starts top centre; the caption is top left
    assert np.abs(frames[0][centre].astype(int) - frames[-1][centre].astype(int)).sum() > 0
    assert len(np.unique(frames[0].reshape(-1, 3), axis=0)) >= 4
