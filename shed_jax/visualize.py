"""A GIF of a trained student playing one test level.

``student_gif`` takes one seed of a (vmapped) run state, rolls out its deterministic policy (the
policy's mean action, or argmax for discrete actions; observations normalised with the state's
frozen statistics, exactly as ``student.act`` does during evaluation) for one episode in one jitted
``lax.scan``, then renders the visited states on the host with ``env.render`` and writes a GIF.

Frame ``k`` shows the state the policy acted on at step ``k`` (the episode's first state is frame
0); a caption gives the step and the return so far. The episode stops at its first ``done``
(termination or the level's time limit) or after ``max_steps`` steps, whichever comes first. The
environment auto-resets on done, so the state *after* the final action is not available: the
last frame is the state the final action was taken in.
"""
from __future__ import annotations

import functools
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from envs.core import Environment
from envs.rendering import save_gif, unstack


def has_renderer(env) -> bool:
    """Whether ``env`` overrides ``Environment.render``."""
    return getattr(type(env), "render", Environment.render) is not Environment.render


def select_student(student, state, seed_index: int = 0):
    """The ``StudentState`` of seed ``seed_index`` from a RunState/StudentState with a leading seed axis.

    An unbatched state (one seed) is accepted with ``seed_index == 0``.
    """
    sstate = state.student if hasattr(state, "student") else state
    if not hasattr(sstate, "obs") or not hasattr(sstate, "params"):
        raise TypeError(f"expected a RunState or a StudentState, got {type(state).__name__}")
    obs_ndim = np.ndim(sstate.obs)
    base = 1 + len(student.obs_shape)  # [num_envs, *obs_shape]
    if obs_ndim == base:
        if seed_index != 0:
            raise IndexError(f"seed_index {seed_index} given for an unbatched (single-seed) state")
        return sstate
    if obs_ndim != base + 1:
        raise ValueError(f"student state obs has shape {np.shape(sstate.obs)}; expected [seeds, num_envs, "
                         f"{', '.join(map(str, student.obs_shape))}] or [num_envs, ...]")
    num_seeds = np.shape(sstate.obs)[0]
    if not 0 <= seed_index < num_seeds:
        raise IndexError(f"seed_index {seed_index} out of range for {num_seeds} seed(s)")
    return jax.tree_util.tree_map(lambda x: x[seed_index], sstate)


def select_level(levels, level_index: int = 0):
    """Level ``level_index`` of a params pytree with a leading level axis."""
    leaves = jax.tree_util.tree_leaves(levels)
    if not leaves or np.ndim(leaves[0]) == 0:
        raise ValueError("test_levels must be an env params pytree with a leading level axis")
    n = np.shape(leaves[0])[0]
    if not 0 <= level_index < n:
        raise IndexError(f"level_index {level_index} out of range for {n} test level(s)")
    return jax.tree_util.tree_map(lambda x: x[level_index], levels)


@functools.lru_cache(maxsize=8)
def _episode_fn(env, student, num_steps: int):
    """Jitted ``(student_state, level, key) -> (states [T], rewards [T], dones [T])``, one per shape."""

    def run(sstate, level, key):
        k_reset, k_run = jax.random.split(key)
        obs, env_state = env.reset(k_reset, level)

        def body(carry, k):
            obs, env_state = carry
            k_act, k_step = jax.random.split(k)
            action = student.act(sstate, k_act, obs.astype(jnp.float32), deterministic=True)
            obs2, env_state2, reward, done, _ = env.step(k_step, env_state, action, level)
            return (obs2, env_state2), (env_state, reward, done)

        _, out = jax.lax.scan(body, (obs, env_state), jax.random.split(k_run, num_steps))
        return out

    return jax.jit(run)


def record_episode(env, student, sstate, level, key, num_steps: int):
    """One deterministic-policy episode of an unbatched student on one level, as host arrays.

    Returns ``(states, rewards, length)``: the ``num_steps`` pre-step states and rewards of one
    scan, and the length of the first episode in it (index of the first done + 1, else
    ``num_steps``). Entries past ``length`` belong to the next (auto-reset) episode.
    """
    if int(num_steps) < 1:
        raise ValueError(f"num_steps must be >= 1, got {num_steps}")
    states, rewards, dones = jax.device_get(_episode_fn(env, student, int(num_steps))(sstate, level, key))
    dones = np.asarray(dones)
    length = int(np.argmax(dones)) + 1 if dones.any() else int(num_steps)
    return states, np.asarray(rewards, np.float64), length


def frame_indices(length: int, max_frames: int | None) -> list[int]:
    """Steps shown in a GIF of ``length`` steps: every k-th with k = ceil(length / max_frames), and
    always the last step."""
    if length < 1:
        raise ValueError(f"length must be >= 1, got {length}")
    stride = 1 if max_frames is None else max(1, math.ceil(length / int(max_frames)))
    idx = list(range(0, length, stride))
    if idx[-1] != length - 1:
        idx.append(length - 1)
    return idx


def _caption(frame: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw

    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    left, top, right, bottom = draw.textbbox((4, 3), text)
    draw.rectangle((left - 2, top - 2, right + 2, bottom + 2), fill=(255, 255, 255))
    draw.text((4, 3), text, fill=(0, 0, 0))
    return np.asarray(img, np.uint8)


def student_gif(env, student, state, test_levels, path, seed_index: int = 0, level_index: int = 0,
                max_steps: int | None = None, fps: int = 30, *, seed: int = 0, max_frames: int | None = 500,
                caption: bool = True) -> pathlib.Path:
    """Write a GIF of seed ``seed_index``'s deterministic policy on test level ``level_index``.

    ``state``: the run's ``RunState`` (or a ``StudentState``) with a leading seed axis, as returned
    by the vmapped ``init``/``run``. ``test_levels``: env params with a leading level axis.
    ``max_steps``: cap on the episode's steps (default: the level's own time limit). ``seed``: the
    key of the env's reset and stochastic dynamics. ``max_frames``: longer episodes show every k-th
    step (k = ceil(length / max_frames), plus the last step); None keeps every step. Returns the
    path. Raises NotImplementedError (before compiling anything) if ``env`` has no renderer.
    """
    if not has_renderer(env):
        raise NotImplementedError(f"environment {getattr(env, 'name', type(env).__name__)!r} has no renderer "
                                  "(env.render is not implemented), so no GIF can be made")
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
    sstate = select_student(student, state, seed_index)
    level = select_level(test_levels, level_index)
    num_steps = int(np.asarray(level.max_steps)) if max_steps is None else int(max_steps)
    if num_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {num_steps}")
    states, rewards, length = record_episode(env, student, sstate, level, jax.random.PRNGKey(seed), num_steps)
    level_host = jax.tree_util.tree_map(np.asarray, jax.device_get(level))
    returns = np.concatenate([[0.0], np.cumsum(rewards[:length])])  # return before step k
    frames = []
    for k in frame_indices(length, max_frames):
        frame = np.asarray(env.render(unstack(states, k), level_host), np.uint8)
        if caption:
            frame = _caption(frame, f"level {level_index}  step {k}  return {returns[k]:.1f}")
        frames.append(frame)
    path = pathlib.Path(path)
    save_gif(frames, str(path), fps=fps)
    return path
