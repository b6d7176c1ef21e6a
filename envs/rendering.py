"""Frames -> GIF helpers shared by all environments (host side, PIL)."""
from __future__ import annotations

import os
from typing import Callable, Sequence

import jax
import numpy as np
from PIL import Image


def save_gif(frames: Sequence[np.ndarray], path: str, fps: int = 50) -> str:
    """Write RGB uint8 frames (H, W, 3) as a looping GIF; returns the path."""
    frames = [np.asarray(f) for f in frames]
    if not frames:
        raise ValueError("save_gif needs at least one frame")
    for k, f in enumerate(frames):
        if f.dtype != np.uint8 or f.ndim != 3 or f.shape[-1] != 3:
            raise ValueError(f"frame {k} must be uint8 (H, W, 3), got {f.dtype} {f.shape}")
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    duration = max(int(round(1000 / fps)), 20)  # GIF viewers clamp faster frames anyway
    images[0].save(path, save_all=True, append_images=images[1:], duration=duration, loop=0)
    return path


def unstack(tree, index: int):
    """The ``index``-th element along the leading axis of every leaf of a pytree."""
    return jax.tree_util.tree_map(lambda x: x[index], tree)


def trajectory_frames(render: Callable, states, env_index: int | None = None, stop: int | None = None,
                      every: int = 1) -> list[np.ndarray]:
    """Frames from a trajectory of (optionally batched) states stacked along axis 0 (time).

    ``states`` leaves have shape [T, ...] or [T, N, ...] (pick ``env_index``); ``render`` maps one
    unbatched state to a frame; ``stop`` truncates the trajectory (e.g. at the first done).
    """
    states = jax.tree_util.tree_map(np.asarray, states)
    if env_index is not None:
        states = jax.tree_util.tree_map(lambda x: x[:, env_index], states)
    n = jax.tree_util.tree_leaves(states)[0].shape[0]
    stop = n if stop is None else min(int(stop), n)
    return [render(unstack(states, t)) for t in range(0, stop, max(int(every), 1))]
