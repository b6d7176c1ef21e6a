"""The PPO student: a frozen object of pure functions over an explicit `StudentState`.

    student = make_student(env, config)
    s = student.init(key, hparams=None)
    s = student.assign_levels(s, key, levels)        # slot j runs level j % n, envs reset
    s, traj = student.rollout(s, key)                # lax.scan over config.num_steps env steps
    s, metrics = student.update(s, key, traj)        # lax.scan over epochs x minibatches
    s, metrics = student.train(s, key, levels, num_updates)
    R = student.evaluate(s, key, levels, num_episodes, max_steps=None, deterministic=False)
    scores = student.level_scores(s, traj)

Everything is jittable, vmappable (over seeds and over `PPOHyperparams`) and usable inside
``lax.scan``; only `num_updates`, `num_episodes`, `max_steps` and `deterministic` are static.
Design follows PureJaxRL (rollout scan of vmapped env.step + policy, minibatch scan), turned into
a library: the level assignment, the hyperparameters and the normalisers live in the state.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from envs.core import Discrete, Environment
from shed_jax.student import losses
from shed_jax.student.config import PPOConfig, PPOHyperparams
from shed_jax.student.networks import Actor, Critic, dist_entropy, dist_log_prob, dist_mode, dist_sample
from shed_jax.student.normalization import ReturnNormalizer, RunningMeanStd


@struct.dataclass
class StudentState:
    params: Any  # {"actor": ..., "critic": ...}
    opt_state: Any  # optax inject_hyperparams state (lr and max_grad_norm are dynamic)
    hparams: PPOHyperparams
    obs_norm: RunningMeanStd
    ret_norm: ReturnNormalizer
    env_state: Any  # [num_envs] env states
    obs: jax.Array  # [num_envs, *obs_shape] raw current observations
    levels: Any  # [num_envs] per-slot level params
    update_step: jax.Array  # int32: number of PPO updates done (drives lr annealing)


@struct.dataclass
class Trajectory:
    """One rollout, time-major [num_steps, num_envs, ...]."""

    obs: jax.Array  # observations the policy saw (normalised if observation normalisation is on)
    actions: jax.Array  # sampled actions (unclipped, for the log-prob)
    log_probs: jax.Array
    values: jax.Array  # V(obs)
    rewards: jax.Array  # rewards used for learning (scaled if return normalisation is on)
    raw_rewards: jax.Array
    dones: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    next_obs: jax.Array  # pre-reset observation after the step (info["final_obs"], normalised like obs)
    next_values: jax.Array  # bootstrap value: V(next_obs), or 0 on termination
    episode_returns: jax.Array  # undiscounted return of the episode ending at this step (0 otherwise)
    episode_lengths: jax.Array


def _make_optimizer(learning_rate, max_grad_norm):
    return optax.chain(optax.clip_by_global_norm(max_grad_norm), optax.adam(learning_rate, eps=1e-5))


def _leading_dim(tree) -> int:
    leaves = jax.tree_util.tree_leaves(tree)
    dims = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if len(dims) != 1 or None in dims:
        raise ValueError(f"levels must be a params pytree whose leaves share one leading axis, got leading dims {dims}")
    return dims.pop()


@dataclasses.dataclass(frozen=True)
class PPOStudent:
    """PPO on `env` with static `config`: holds only static things (modules, optimiser, action box).

    Every method is a pure function of its arguments (state, key, levels, traj); jit them at the
    top with the static ints (num_updates, num_episodes, max_steps, deterministic) marked static.
    """

    env: Environment
    config: PPOConfig

    def __post_init__(self):
        space = self.env.action_space(None)
        obs_space = self.env.observation_space(None)
        discrete = isinstance(space, Discrete)
        if not discrete and len(space.shape) != 1:
            raise ValueError(f"PPO supports Discrete or 1-D Box action spaces, got a Box of shape {space.shape}")
        c = self.config
        action_dim = space.n if discrete else space.shape[0]
        object.__setattr__(self, "discrete", discrete)
        object.__setattr__(self, "obs_shape", tuple(obs_space.shape))
        object.__setattr__(
            self, "actor", Actor(c.actor_hidden, action_dim, discrete, c.activation, c.init_log_std)
        )
        object.__setattr__(self, "critic", Critic(c.critic_hidden, c.activation))
        object.__setattr__(self, "tx", optax.inject_hyperparams(_make_optimizer)(learning_rate=3e-4, max_grad_norm=0.5))
        if not discrete:
            object.__setattr__(self, "action_low", np.broadcast_to(np.asarray(space.low, np.float32), space.shape))
            object.__setattr__(self, "action_high", np.broadcast_to(np.asarray(space.high, np.float32), space.shape))
        object.__setattr__(self, "default_eval_steps", int(np.asarray(self.env.default_params.max_steps)))

    # ----------------------------------------------------------------------------------------
    # small helpers
    # ----------------------------------------------------------------------------------------
    @property
    def env_steps_per_update(self) -> int:
        """Env steps of one rollout (num_envs * num_steps), for budget accounting."""
        return self.config.num_envs * self.config.num_steps

    def _norm_obs(self, obs_norm: RunningMeanStd, obs):
        return obs_norm.normalize(obs, self.config.obs_clip) if self.config.normalize_observations else obs

    def _env_action(self, action):
        """What is sent to the env: continuous actions are clipped to the action box."""
        if self.discrete:
            return action
        return jnp.clip(action, self.action_low, self.action_high)

    def policy_output(self, params, obs):
        return self.actor.apply({"params": params["actor"]}, obs)

    def value(self, params, obs):
        return self.critic.apply({"params": params["critic"]}, obs)

    def act(self, state: StudentState, key, obs, deterministic: bool = False):
        """Env actions for raw observations (normalised with the state's frozen statistics)."""
        out = self.policy_output(state.params, self._norm_obs(state.obs_norm, obs))
        a = dist_mode(out, self.discrete) if deterministic else dist_sample(key, out, self.discrete)
        return self._env_action(a)

    # ----------------------------------------------------------------------------------------
    # API
    # ----------------------------------------------------------------------------------------
    def init(self, key, hparams: PPOHyperparams | None = None) -> StudentState:
        """A fresh student on the env's default level in every slot."""
        hp = self.config.hparams if hparams is None else hparams
        if not isinstance(hp, PPOHyperparams):
            raise TypeError(f"hparams must be a PPOHyperparams, got {type(hp).__name__}")
        hp = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), hp.validate())
        k_actor, k_critic, k_env = jax.random.split(key, 3)
        dummy = jnp.zeros(self.obs_shape, jnp.float32)
        params = {
            "actor": self.actor.init(k_actor, dummy)["params"],
            "critic": self.critic.init(k_critic, dummy)["params"],
        }
        opt_state = self.tx.init(params)
        opt_state = opt_state._replace(
            hyperparams={**opt_state.hyperparams, "learning_rate": hp.lr, "max_grad_norm": hp.max_grad_norm}
        )
        levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], self.env.default_params)
        state = StudentState(
            params=params,
            opt_state=opt_state,
            hparams=hp,
            obs_norm=RunningMeanStd.create(self.obs_shape),
            ret_norm=ReturnNormalizer.create(self.config.num_envs),
            env_state=None,
            obs=None,
            levels=None,
            update_step=jnp.asarray(0, jnp.int32),
        )
        return self.assign_levels(state, k_env, levels)

    def assign_levels(self, state: StudentState, key, levels) -> StudentState:
        """Slot j runs level j % n (n = leading axis of `levels`); every slot is reset."""
        n = _leading_dim(levels)
        idx = jnp.arange(self.config.num_envs) % n
        slot_levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[idx], levels)
        keys = jax.random.split(key, self.config.num_envs)
        obs, env_state = jax.vmap(self.env.reset)(keys, slot_levels)
        return state.replace(
            env_state=env_state, obs=obs.astype(jnp.float32), levels=slot_levels, ret_norm=state.ret_norm.reset()
        )

    def rollout(self, state: StudentState, key, next_levels=None):
        """config.num_steps steps of all slots with the current policy -> (state, Trajectory).

        ``next_levels`` (a params pytree with leading axis num_envs, optional): slot j moves to
        ``next_levels[j]`` when its current episode ends, at most once per rollout. Its next
        episode then starts there instead of on the same level, and ``state.levels`` holds each
        slot's level at the end. The slots that moved are those with an episode end in the rollout,
        ``traj.dones.any(axis=0)``. Without ``next_levels`` every slot keeps its level (the env's
        own auto-reset).
        """
        cfg = self.config
        params, hp = state.params, state.hparams
        switching = next_levels is not None

        def swap(moved, key, next_level, level, env_state, obs):
            """One slot: if ``moved``, a new episode on ``next_level`` replaces the auto-reset one."""
            obs_new, state_new = self.env.reset(key, next_level)
            pick = lambda new, old: jnp.where(moved, new, old)  # noqa: E731
            return jax.tree_util.tree_map(pick, (next_level, state_new, obs_new), (level, env_state, obs))

        def step(carry, k):
            (env_state, obs, obs_norm, ret_norm), (levels, pending) = carry
            if switching:
                k, k_swap = jax.random.split(k)
            k_act, k_env = jax.random.split(k)
            if cfg.normalize_observations:
                obs_norm = obs_norm.update(obs)
            obs_n = self._norm_obs(obs_norm, obs)
            out = self.policy_output(params, obs_n)
            value = self.value(params, obs_n)
            action = dist_sample(k_act, out, self.discrete)
            log_prob = dist_log_prob(out, action, self.discrete)
            keys = jax.random.split(k_env, cfg.num_envs)
            obs2, env_state2, reward, done, info = jax.vmap(self.env.step)(keys, env_state, self._env_action(action), levels)
            next_obs = self._norm_obs(obs_norm, info["final_obs"].astype(jnp.float32))
            next_value = losses.bootstrap_values(self.value(params, next_obs), info["terminated"])
            if cfg.normalize_returns:
                ret_norm, learn_reward = ret_norm.step(reward, done, hp.gamma, cfg.reward_clip)
            else:
                learn_reward = reward
            tr = Trajectory(
                obs=obs_n,
                actions=action,
                log_probs=log_prob,
                values=value,
                rewards=learn_reward,
                raw_rewards=reward,
                dones=done,
                terminated=info["terminated"],
                truncated=info["truncated"],
                next_obs=next_obs,
                next_values=next_value,
                episode_returns=info["episode_return"],
                episode_lengths=info["episode_length"],
            )
            if switching:  # an episode ended: the slot's next episode starts on its next level
                moved = done & pending
                levels, env_state2, obs2 = jax.vmap(swap)(moved, jax.random.split(k_swap, cfg.num_envs), next_levels,
                                                           levels, env_state2, obs2)
                pending = pending & ~moved
            return ((env_state2, obs2.astype(jnp.float32), obs_norm, ret_norm), (levels, pending)), tr

        carry0 = ((state.env_state, state.obs, state.obs_norm, state.ret_norm),
                  (state.levels, jnp.ones((cfg.num_envs,), bool)))
        ((env_state, obs, obs_norm, ret_norm), (levels, pending)), traj = jax.lax.scan(
            step, carry0, jax.random.split(key, cfg.num_steps))
        state = state.replace(env_state=env_state, obs=obs, obs_norm=obs_norm, ret_norm=ret_norm)
        return state.replace(levels=levels), traj

    def advantages(self, state: StudentState, traj: Trajectory):
        """GAE advantages and value targets [num_steps, num_envs] under the state's gamma/lambda."""
        return losses.gae(
            traj.rewards, traj.values, traj.next_values, traj.dones, state.hparams.gamma, state.hparams.gae_lambda
        )

    def update(self, state: StudentState, key, traj: Trajectory):
        """PPO: update_epochs passes over the rollout in num_minibatches shuffled minibatches."""
        cfg, hp = self.config, state.hparams
        adv, targets = self.advantages(state, traj)
        flat = lambda x: x.reshape((cfg.batch_size,) + x.shape[2:])
        batch = jax.tree_util.tree_map(
            flat, (traj.obs, traj.actions, traj.log_probs, traj.values, adv, targets)
        )
        lr = hp.lr
        if cfg.anneal_lr:
            lr = lr * jnp.clip(1.0 - state.update_step.astype(jnp.float32) / cfg.anneal_updates, 0.0, 1.0)
        opt_state = state.opt_state._replace(
            hyperparams={**state.opt_state.hyperparams, "learning_rate": lr, "max_grad_norm": hp.max_grad_norm}
        )

        def loss_fn(params, mb):
            obs, actions, old_logp, old_values, mb_adv, mb_targets = mb
            if cfg.normalize_advantages:
                mb_adv = losses.normalize_advantages(mb_adv)
            out = self.policy_output(params, obs)
            values = self.value(params, obs)
            return losses.ppo_loss(
                dist_log_prob(out, actions, self.discrete),
                old_logp,
                mb_adv,
                values,
                old_values,
                mb_targets,
                dist_entropy(out, self.discrete),
                hp,
                cfg.clip_value_loss,
            )

        def minibatch(carry, mb):
            params, opt_state = carry
            grads, aux = jax.grad(loss_fn, has_aux=True)(params, mb)
            updates, opt_state = self.tx.update(grads, opt_state, params)
            aux = dict(aux, grad_norm=optax.tree.norm(grads))
            return (optax.apply_updates(params, updates), opt_state), aux

        def epoch(carry, k):
            perm = jax.random.permutation(k, cfg.batch_size)
            mbs = jax.tree_util.tree_map(
                lambda x: x[perm].reshape((cfg.num_minibatches, cfg.minibatch_size) + x.shape[1:]), batch
            )
            return jax.lax.scan(minibatch, carry, mbs)

        (params, opt_state), aux = jax.lax.scan(
            epoch, (state.params, opt_state), jax.random.split(key, cfg.update_epochs)
        )
        metrics = jax.tree_util.tree_map(jnp.mean, aux)
        metrics.update(self.episode_metrics(traj))
        metrics["learning_rate"] = lr
        metrics["value_target_mean"] = targets.mean()
        new_state = state.replace(params=params, opt_state=opt_state, update_step=state.update_step + 1)
        return new_state, metrics

    @staticmethod
    def episode_metrics(traj: Trajectory) -> dict:
        """Mean undiscounted return/length of the episodes that ended in `traj` (NaN if none did)."""
        n = traj.dones.sum()
        safe = jnp.maximum(n, 1)
        return {
            "episode_return": jnp.where(n > 0, (traj.episode_returns * traj.dones).sum() / safe, jnp.nan),
            "episode_length": jnp.where(n > 0, (traj.episode_lengths * traj.dones).sum() / safe, jnp.nan),
            "num_episodes": n,
        }

    def run_updates(self, state: StudentState, key, num_updates: int):
        """`num_updates` x (rollout, update) on the current slots, without resetting them."""

        def body(s, k):
            k_roll, k_upd = jax.random.split(k)
            s, traj = self.rollout(s, k_roll)
            return self.update(s, k_upd, traj)

        return jax.lax.scan(body, state, jax.random.split(key, num_updates))

    def train(self, state: StudentState, key, levels, num_updates: int):
        """Assign `levels` to the slots, then `num_updates` PPO iterations; metrics per update."""
        k_assign, k_run = jax.random.split(key)
        return self.run_updates(self.assign_levels(state, k_assign, levels), k_run, num_updates)

    def level_scores(self, state: StudentState, traj: Trajectory, max_returns=None):
        """Per-slot replay scores for PLR/ACCEL, [num_envs] each.

        pvl:    positive value loss, mean over steps of max(GAE advantage, 0).
        maxmc:  mean over steps of (max_return - V(s_t)), with max_return the largest value target
                (discounted return estimate) seen in this rollout, or in `max_returns` (a per-slot
                running maximum kept by the caller, e.g. a level buffer), whichever is larger.
        max_returns: the updated per-slot maximum, for the caller to store.
        """
        adv, targets = self.advantages(state, traj)
        max_ret = targets.max(axis=0)
        if max_returns is not None:
            max_ret = jnp.maximum(max_ret, max_returns)
        return {
            "pvl": jnp.maximum(adv, 0.0).mean(axis=0),
            "maxmc": (max_ret[None] - traj.values).mean(axis=0),
            "max_returns": max_ret,
        }

    def eval_env_steps(self, n_levels: int, num_episodes: int, max_steps: int | None = None) -> int:
        """Env steps one `evaluate` call simulates (fixed-length scans), for budget accounting."""
        return n_levels * num_episodes * (self.default_eval_steps if max_steps is None else int(max_steps))

    def evaluate_with_info(self, state: StudentState, key, levels, num_episodes: int, max_steps: int | None = None, deterministic: bool = False):
        """Like `evaluate`, plus {"lengths": [n, E], "env_steps": simulated steps, "episode_steps": sum of lengths}.

        Each (level, episode) pair is one env run for a fixed number of steps (`max_steps`, else
        the env's default time limit); only its first episode counts (done masking). `max_steps`
        overrides the levels' own time limit; without it the levels' `max_steps` must not exceed
        the default limit (checked when the levels are concrete).
        """
        n = _leading_dim(levels)
        if max_steps is None:
            length = self.default_eval_steps
            ms = levels.max_steps
            if not isinstance(ms, jax.core.Tracer) and np.any(np.asarray(ms) > length):
                raise ValueError(
                    f"evaluate: levels have max_steps up to {int(np.max(ms))} > the scan length {length}; pass max_steps"
                )
        else:
            length = int(max_steps)
            if length < 1:
                raise ValueError(f"evaluate: max_steps must be >= 1, got {max_steps}")
            levels = levels.replace(max_steps=jnp.full_like(jnp.asarray(levels.max_steps), length))
        if num_episodes < 1:
            raise ValueError(f"evaluate: num_episodes must be >= 1, got {num_episodes}")
        flat_levels = jax.tree_util.tree_map(lambda x: jnp.repeat(jnp.asarray(x), num_episodes, axis=0), levels)

        def one(k, level):
            k_reset, k_run = jax.random.split(k)
            obs, env_state = self.env.reset(k_reset, level)

            def body(c, kk):
                env_state, obs, ret, ep_len, finished = c
                k_act, k_step = jax.random.split(kk)
                action = self.act(state, k_act, obs.astype(jnp.float32), deterministic)
                obs, env_state, _, done, info = self.env.step(k_step, env_state, action, level)
                first = jnp.logical_and(done, jnp.logical_not(finished))
                ret = jnp.where(first, info["episode_return"], ret)
                ep_len = jnp.where(first, info["episode_length"], ep_len)
                return (env_state, obs, ret, ep_len, jnp.logical_or(finished, done)), None

            c0 = (env_state, obs, jnp.zeros((), jnp.float32), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
            (env_state, _, ret, ep_len, finished), _ = jax.lax.scan(body, c0, jax.random.split(k_run, length))
            # only reachable if a traced level's time limit exceeds the scan: report the partial episode
            ret = jnp.where(finished, ret, env_state.episode_return)
            ep_len = jnp.where(finished, ep_len, env_state.time)
            return ret, ep_len

        rets, lens = jax.vmap(one)(jax.random.split(key, n * num_episodes), flat_levels)
        rets = rets.reshape(n, num_episodes)
        lens = lens.reshape(n, num_episodes)
        info = {"lengths": lens, "env_steps": n * num_episodes * length, "episode_steps": lens.sum()}
        return rets, info

    def evaluate(self, state: StudentState, key, levels, num_episodes: int, max_steps: int | None = None, deterministic: bool = False):
        """Undiscounted returns [n_levels, num_episodes] of the first episode of each run."""
        return self.evaluate_with_info(state, key, levels, num_episodes, max_steps, deterministic)[0]


def make_student(env: Environment, config: PPOConfig | None = None) -> PPOStudent:
    """The student for `env`; `config` defaults to the env's preset (PPOConfig.for_env(env.name))."""
    if config is None:
        config = PPOConfig.for_env(env.name)
    if not isinstance(config, PPOConfig):
        raise TypeError(f"config must be a PPOConfig, got {type(config).__name__}")
    return PPOStudent(env, config)
