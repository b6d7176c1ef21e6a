"""The PPO student: a frozen object of pure functions over an explicit `StudentState`.

    student = make_student(env, config)
    s = student.init(key, hparams=None)
    s = student.assign_levels(s, key, levels)        # slot j runs level j % n, envs reset
    s, traj = student.rollout(s, key)                # lax.scan over config.num_steps env steps
    s, metrics = student.update(s, key, traj)        # lax.scan over epochs x minibatches
    s, metrics = student.train(s, key, levels, num_updates)
    R = student.evaluate(s, key, levels, num_episodes, max_steps=None, deterministic=False)
    outs = student.evaluate_many(s, [(key, levels, num_episodes, max_steps), ...])  # one rollout
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

from envs.core import Discrete, Environment, restart_where
from shed_jax.student import losses
from shed_jax.student.config import PPOConfig, PPOHyperparams
from shed_jax.student.networks import Actor, Critic, dist_entropy, dist_log_prob, dist_mode, dist_sample
from shed_jax.student.normalization import ReturnNormalizer, RunningMeanStd
from shed_jax.student.sgd import minibatch_sgd


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
class Policy:
    """What acting reads: ``PPOStudent.act`` and ``evaluate`` take this or a ``StudentState`` (the
    same two fields); a saved policy (``shed_jax.training.save_policy``) is one of these per seed."""
    params: Any  # {"actor": ..., "critic": ...}
    obs_norm: RunningMeanStd


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


# Steps per while-loop iteration of an evaluation rollout (`PPOStudent._eval_rollout`).
EVAL_CHUNK = 16


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
            self, "actor", Actor(c.actor_hidden, action_dim, discrete, c.activation, c.init_log_std,
                                  c.log_std_min, c.log_std_max)
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

    @property
    def train_envs(self) -> int:
        """Environments one student state steps side by side in a training rollout (num_envs)."""
        return self.config.num_envs

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
        params = self._init_params(k_actor, k_critic)
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

    def _init_params(self, k_actor, k_critic):
        dummy = jnp.zeros(self.obs_shape, jnp.float32)
        return {
            "actor": self.actor.init(k_actor, dummy)["params"],
            "critic": self.critic.init(k_critic, dummy)["params"],
        }

    def init_policy(self, key) -> Policy:
        """Fresh networks and observation statistics, without env state (no env is reset)."""
        return Policy(params=self._init_params(*jax.random.split(key)), obs_norm=RunningMeanStd.create(self.obs_shape))

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

    def act_step(self, params, obs_norm: RunningMeanStd, key, obs):
        """The acting half of one rollout step, for [num_envs] raw observations: the observation
        statistics updated with them (if normalised), then (normalised obs, sampled action, its log-prob,
        V(obs)). ``rollout`` and the host-env rollouts (experiments/bipedal_box2d_ppo.py) share it."""
        if self.config.normalize_observations:
            obs_norm = obs_norm.update(obs)
        obs_n = self._norm_obs(obs_norm, obs)
        out = self.policy_output(params, obs_n)
        value = self.value(params, obs_n)
        action = dist_sample(key, out, self.discrete)
        return obs_norm, (obs_n, action, dist_log_prob(out, action, self.discrete), value)

    def record_step(self, params, hp: PPOHyperparams, obs_norm: RunningMeanStd, ret_norm, acted, reward, done, info):
        """The learning half of one rollout step: the step's ``Trajectory`` row from ``act_step``'s output and
        the env's answer (``info``: ``final_obs``, the pre-reset observation, ``terminated``, ``truncated``,
        ``episode_return``, ``episode_length``), with the bootstrap value V(final_obs) (0 on termination)
        and the learning reward (scaled if return normalisation is on) -> (ret_norm, row)."""
        cfg = self.config
        obs_n, action, log_prob, value = acted
        next_obs = self._norm_obs(obs_norm, info["final_obs"].astype(jnp.float32))
        next_value = losses.bootstrap_values(self.value(params, next_obs), info["terminated"])
        if cfg.normalize_returns:
            ret_norm, learn_reward = ret_norm.step(reward, done, hp.gamma, cfg.reward_clip)
        else:
            learn_reward = reward
        return ret_norm, Trajectory(
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

    @jax.named_scope("rollout")  # the scopes name a budget step's parts in a profile (experiments/trace_summary.py)
    def rollout(self, state: StudentState, key, next_levels=None):
        """config.num_steps steps of all slots with the current policy -> (state, Trajectory).

        ``next_levels`` (a params pytree with leading axis num_envs, optional): slot j moves to
        ``next_levels[j]`` when its current episode ends, at most once per rollout. Its next
        episode then starts there instead of on the same level, and ``state.levels`` holds each
        slot's level at the end. The slots that moved are those with an episode end in the rollout,
        ``traj.dones.any(axis=0)``. Without ``next_levels`` every slot keeps its level (the env's
        own auto-reset).

        ``config.reset_draw``: with "per_step" the resets are the env's own, drawn at the step that
        needs them; with "per_rollout" each slot's reset (on its level, or on its next level when
        switching) is drawn once before the scan, so the scan never computes ``reset_env``, and a
        slot whose episode ends twice on one level in a rollout restarts from the same drawn state
        twice (after a switch, from the state drawn on its new level).
        The steps before a slot's first episode end are identical under both.
        """
        cfg = self.config
        params, hp = state.params, state.hparams
        switching = next_levels is not None
        ahead = cfg.reset_draw == "per_rollout"
        n = cfg.num_envs
        drawn = drawn_next = None
        if ahead:  # keys folded from `key`, so the scan's own keys are those of "per_step"
            if switching:
                # every slot's first episode end moves it (`pending` starts True), so a draw on its
                # current level would never be played: only the next levels are drawn (one reset call
                # site in the program; the 2-D walker's reset holds a whole physics step)
                drawn_next = jax.vmap(self.env.reset)(jax.random.split(jax.random.fold_in(key, 2), n), next_levels)
                drawn = drawn_next
            else:
                drawn = jax.vmap(self.env.reset)(jax.random.split(jax.random.fold_in(key, 1), n), state.levels)

        def swap(moved, key, next_level, level, env_state, obs, drawn_next):
            """One slot: if ``moved``, a new episode on ``next_level`` replaces the auto-reset one."""
            obs_new, state_new = self.env.reset(key, next_level) if drawn_next is None else drawn_next
            return restart_where(moved, (next_level, state_new, obs_new), (level, env_state, obs))

        def env_step(keys, env_state, action, levels, drawn):
            if not ahead:
                return jax.vmap(self.env.step)(keys, env_state, action, levels)
            obs2, env_state2, reward, done, info = jax.vmap(self.env.step_without_reset)(keys, env_state, action, levels)
            obs2, env_state2 = jax.vmap(restart_where)(done, drawn, (obs2, env_state2))
            return obs2, env_state2, reward, done, info

        def step(carry, k):
            (env_state, obs, obs_norm, ret_norm), (levels, pending, drawn) = carry
            if switching:
                k, k_swap = jax.random.split(k)
            k_act, k_env = jax.random.split(k)
            obs_norm, acted = self.act_step(params, obs_norm, k_act, obs)
            keys = jax.random.split(k_env, n)
            obs2, env_state2, reward, done, info = env_step(keys, env_state, self._env_action(acted[1]), levels, drawn)
            ret_norm, tr = self.record_step(params, hp, obs_norm, ret_norm, acted, reward, done, info)
            if switching:  # an episode ended: the slot's next episode starts on its next level
                moved = done & pending
                levels, env_state2, obs2 = jax.vmap(swap)(moved, jax.random.split(k_swap, n), next_levels,
                                                           levels, env_state2, obs2, drawn_next)
                pending = pending & ~moved  # (per_rollout: `drawn` is already the next levels' draw)
            return ((env_state2, obs2.astype(jnp.float32), obs_norm, ret_norm), (levels, pending, drawn)), tr

        carry0 = ((state.env_state, state.obs, state.obs_norm, state.ret_norm),
                  (state.levels, jnp.ones((n,), bool), drawn))
        ((env_state, obs, obs_norm, ret_norm), (levels, pending, _)), traj = jax.lax.scan(
            step, carry0, jax.random.split(key, cfg.num_steps))
        state = state.replace(env_state=env_state, obs=obs, obs_norm=obs_norm, ret_norm=ret_norm)
        return state.replace(levels=levels), traj

    def advantages(self, state: StudentState, traj: Trajectory):
        """GAE advantages and value targets [num_steps, num_envs] under the state's gamma/lambda."""
        return losses.gae(
            traj.rewards, traj.values, traj.next_values, traj.dones, state.hparams.gamma, state.hparams.gae_lambda
        )

    @jax.named_scope("ppo_update")
    def update(self, state: StudentState, key, traj: Trajectory, mask=None):
        """PPO: update_epochs passes over the rollout in num_minibatches shuffled minibatches.

        ``mask`` ([num_steps, num_envs] bool, optional): only the transitions where it is True enter
        the loss (every mean, and the advantage normalisation, is over them); PLR⊥ uses it for slots
        on levels it scores without gradients. A mask with no True entry still moves the optimiser
        (Adam's moments decay), so callers skip the update then. GAE runs over every transition.
        """
        cfg, hp = self.config, state.hparams
        adv, targets = self.advantages(state, traj)
        flat = lambda x: x.reshape((cfg.batch_size,) + x.shape[2:])
        parts = (traj.obs, traj.actions, traj.log_probs, traj.values, adv, targets)
        batch = jax.tree_util.tree_map(flat, parts if mask is None else parts + (mask.astype(jnp.float32),))
        lr = hp.lr
        if cfg.anneal_lr:
            lr = lr * jnp.clip(1.0 - state.update_step.astype(jnp.float32) / cfg.anneal_updates, 0.0, 1.0)
        opt_state = state.opt_state._replace(
            hyperparams={**state.opt_state.hyperparams, "learning_rate": lr, "max_grad_norm": hp.max_grad_norm}
        )

        def loss_fn(params, mb):
            obs, actions, old_logp, old_values, mb_adv, mb_targets = mb[:6]
            w = mb[6] if mask is not None else None
            if cfg.normalize_advantages:
                mb_adv = losses.normalize_advantages(mb_adv, weights=w)
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
                w,
            )

        (params, opt_state), aux = minibatch_sgd(loss_fn, self.tx, state.params, opt_state, batch, key,
                                                 cfg.update_epochs, cfg.num_minibatches, grad_norm=True)
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
        """Env steps one `evaluate` call is charged (n x E x its step limit), for budget accounting.

        A nominal count: the rollout stops early once every episode has ended, and its ``info``
        reports the steps actually run (``steps_run``), but budgets and records keep this one."""
        return n_levels * num_episodes * (self.default_eval_steps if max_steps is None else int(max_steps))

    def _eval_levels(self, levels, num_episodes: int, max_steps: int | None):
        """(levels under the evaluation's time limit, its step limit), with the arguments checked."""
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
        return levels, length

    @jax.named_scope("evaluate")
    def evaluate_many(self, state: StudentState, requests, deterministic: bool = False, chunk: int = EVAL_CHUNK):
        """Several evaluations as ONE rollout: ``requests`` is a sequence of
        ``(key, levels, num_episodes, max_steps)``; returns a list of ``(returns, info)``, entry i
        computed as ``evaluate_with_info(state, key_i, levels_i, num_episodes_i, max_steps_i,
        deterministic)`` computes it: the same keys and the same per-row work, in a larger batch.
        The floats are equal where the backend computes a row the same at any batch size. That is
        not guaranteed: XLA:CPU compiles some ops (row sums, small matmuls) to different code for
        different batch sizes, and lander returns can differ in the last bits, and an episode can
        then take another path (cartpole's are equal; tests/test_eval_rollout.py).

        A request may carry a fifth element, ``active`` (a bool, traced or not; True without it):
        the rows of an inactive request step with the others but record nothing (returns and
        lengths 0) and do not keep the rollout going. So one program serves a rollout whether or not
        that request runs (a test set on some budget steps only), and the other requests' rows are
        computed in the same batch either way.

        Keys: row r of request i (level r // E_i, episode r % E_i) takes ``split(key_i, n_i E_i)[r]``,
        split again into its reset key and run key, and the run key into one key per step up to the
        request's own step limit, exactly as a request alone would. A row stops being recorded at
        its first episode end or at its request's step limit, and the whole rollout stops when no
        row is still recording (``info["steps_run"]``, the same number in every entry). Sequential
        env steps are what an evaluation pays for on a latency-bound simulator (MJX), so fusing the
        teacher's evaluation with the test set pays that latency once.
        """
        if chunk < 1:
            raise ValueError(f"evaluate: chunk must be >= 1, got {chunk}")
        groups, active = [], []
        for key, levels, num_episodes, max_steps, *on in requests:
            n = _leading_dim(levels)
            levels, length = self._eval_levels(levels, num_episodes, max_steps)
            flat = jax.tree_util.tree_map(lambda x: jnp.repeat(jnp.asarray(x), num_episodes, axis=0), levels)
            k_reset, k_run = jnp.moveaxis(jax.vmap(jax.random.split)(jax.random.split(key, n * num_episodes)), 1, 0)
            groups.append((n, num_episodes, length, flat, k_reset, k_run))
            active.append(on[0] if on else True)
        total = max(g[2] for g in groups)
        padded = -(-total // chunk) * chunk  # the key table covers whole chunks

        def step_keys(k_run, length):
            """[rows, padded] per-step keys: split(k_run, length), the last repeated past the limit."""
            keys = jax.vmap(lambda k: jax.random.split(k, length))(k_run)
            return keys[:, np.minimum(np.arange(padded), length - 1)]

        cat = lambda *xs: jnp.concatenate(xs, axis=0)  # noqa: E731
        levels = jax.tree_util.tree_map(cat, *[g[3] for g in groups])
        reset_keys = cat(*[g[4] for g in groups])
        keys = cat(*[step_keys(g[5], g[2]) for g in groups])
        limits = np.concatenate([np.full(g[0] * g[1], g[2], np.int32) for g in groups])
        if any(a is not True for a in active):  # a row of an inactive request has no steps to record
            on = jnp.concatenate([jnp.full(g[0] * g[1], a, bool) for g, a in zip(groups, active)])
            limits = jnp.where(on, limits, 0)
        limits = jnp.asarray(limits)
        rets, lens, steps_run = self._eval_rollout(state, reset_keys, keys, levels, limits, total, deterministic, chunk)

        out, r0 = [], 0
        for n, num_episodes, length, *_ in groups:
            r1 = r0 + n * num_episodes
            g_rets, g_lens = rets[r0:r1].reshape(n, num_episodes), lens[r0:r1].reshape(n, num_episodes)
            out.append((g_rets, {"lengths": g_lens, "env_steps": n * num_episodes * length,
                                 "episode_steps": g_lens.sum(), "steps_run": steps_run}))
            r0 = r1
        return out

    def _eval_rollout(self, state, reset_keys, keys, levels, limits, total: int, deterministic: bool, chunk: int):
        """Rows (one env run each) stepped together until no row records any more.

        A ``lax.while_loop`` over chunks of ``chunk`` steps, each a ``lax.scan``: the loop's test runs
        once a chunk, and at most ``chunk - 1`` steps run past the last episode end (unrecorded, so
        results do not depend on ``chunk``). Step t of row r uses ``keys[r, t]``. Returns (first
        episode's return [rows], its length [rows], steps run: a multiple of chunk capped at total).
        """
        obs, env_state = jax.vmap(self.env.reset)(reset_keys, levels)

        def row_step(kk, env_state, obs, level):
            k_act, k_step = jax.random.split(kk)
            action = self.act(state, k_act, obs.astype(jnp.float32), deterministic)
            # only a row's first episode is recorded, so no auto-reset (the same values until it ends)
            return self.env.step_without_reset(k_step, env_state, action, level)

        def one_step(c, xs):
            t, keys_t = xs
            env_state, obs, ret, ep_len, finished = c
            obs, env_state, _, done, info = jax.vmap(row_step)(keys_t, env_state, obs, levels)
            recording = jnp.logical_and(jnp.logical_not(finished), t < limits)
            first = jnp.logical_and(done, recording)
            # first episode end: its return/length; still running: the partial episode so far (kept
            # if the row reaches its step limit without an end, only possible for a traced level
            # whose own time limit exceeds the step limit)
            ret = jnp.where(first, info["episode_return"], jnp.where(recording, env_state.episode_return, ret))
            ep_len = jnp.where(first, info["episode_length"], jnp.where(recording, env_state.time, ep_len))
            return (env_state, obs, ret, ep_len, jnp.logical_or(finished, first)), None

        def any_recording(c, t):
            return jnp.any(jnp.logical_and(jnp.logical_not(c[4]), t < limits))

        def chunk_body(carry):
            c, t0 = carry
            ks = jnp.moveaxis(jax.lax.dynamic_slice_in_dim(keys, t0, chunk, axis=1), 1, 0)
            c, _ = jax.lax.scan(one_step, c, (t0 + jnp.arange(chunk, dtype=jnp.int32), ks))
            return c, t0 + chunk

        rows = limits.shape[0]
        c0 = (env_state, obs, jnp.zeros((rows,), jnp.float32), jnp.zeros((rows,), jnp.int32), jnp.zeros((rows,), bool))
        (_, _, ret, ep_len, _), t_end = jax.lax.while_loop(
            lambda carry: any_recording(*carry), chunk_body, (c0, jnp.zeros((), jnp.int32)))
        return ret, ep_len, jnp.minimum(t_end, total)

    def evaluate_with_info(self, state: StudentState, key, levels, num_episodes: int, max_steps: int | None = None,
                           deterministic: bool = False, chunk: int = EVAL_CHUNK):
        """Like `evaluate`, plus {"lengths": [n, E], "env_steps": the nominal steps n x E x limit
        (budget accounting), "episode_steps": sum of lengths, "steps_run": steps the rollout ran}.

        Each (level, episode) pair is one env run of up to a step limit (`max_steps`, else the env's
        default time limit); only its first episode counts. All runs stop together as soon as every
        one has ended its first episode or reached the limit (`evaluate_many`); the returns equal
        those of a full-length run. `max_steps` overrides the levels' own time limit; without it the
        levels' `max_steps` must not exceed the default limit (checked when the levels are concrete).
        """
        return self.evaluate_many(state, [(key, levels, num_episodes, max_steps)], deterministic, chunk)[0]

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
