"""PAIRED behind the UED method interface (native mode), docs/design.md §8.3.

Three learners [DCD]: the protagonist (the reported student), an antagonist (the same PPO, its
own state, kept in the method state) and an adversary that proposes levels. Each PPO iteration of
a budget step:

1. the adversary emits one level per slot: a one-shot tanh-Gaussian action u ∈ [-1, 1]^d from an
   observation z ~ U[0, 1]^10, mapped affinely to Θ (``param_space.from_unit``) [our choice; DCD's
   walker adversary is the same one-shot form with a random-noise observation];
2. protagonist and antagonist each roll out ``num_steps`` on those levels and take a PPO update;
3. per slot, regret = max(max_ep R_A - mean_ep R_P, 0) [DCD: "max over antagonist episodes minus
   mean over protagonist episodes", clipped at 0]. **Estimate** [our choice]: the episodes are
   those completed within the rollout; a slot where an agent completed none falls back to that
   agent's unfinished episode's return so far (the rollout end treated as a truncation: both
   agents then see the same horizon on the same level);
4. the adversary takes a PPO update on the batch of one-step episodes with reward
   regret / running std of regret [DCD return normalisation]; advantages are r - V(z).

tanh-Gaussian: the stored action is the pre-tanh sample x, so the PPO ratio needs no Jacobian
term (it cancels); the entropy bonus is the entropy of the pre-tanh Gaussian (the squashed entropy
has no closed form) [our choice]. The adversary networks reuse the student's Actor/Critic modules.

Budget: ``env_steps_train`` counts protagonist steps; antagonist steps are in
``extras["env_steps_antagonist"]``; ``teacher_reward`` is the mean (unnormalised) regret.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from shed_jax.levels import LevelCodec, new_seeds, slot_returns, teacher_space
from shed_jax.methods.base import StepInfo, mean_metrics, warn_if_rollouts_cut_episodes
from shed_jax.student import losses
from shed_jax.student.config import PPOHyperparams
from shed_jax.student.networks import Actor, Critic, gaussian_entropy, gaussian_log_prob
from shed_jax.student.normalization import RunningMeanStd
from shed_jax.student.sgd import minibatch_sgd


@dataclasses.dataclass(frozen=True)
class PAIREDConfig:
    """PAIRED settings; adversary PPO per docs/design.md §8.3 [DCD], lr and network size [our choice]."""

    updates_per_step: int = 10
    noise_dim: int = 10
    hidden: tuple[int, ...] = (64, 64)
    lr: float = 3e-4
    epochs: int = 8
    minibatches: int = 4
    ent_coef: float = 0.01
    clip_eps: float = 0.2
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    init_log_std: float = 0.0
    reset_on_episode: bool = True  # fresh antagonist and adversary with every fresh protagonist
    low: tuple[float, ...] | None = None
    high: tuple[float, ...] | None = None

    def __post_init__(self):
        for name in ("updates_per_step", "noise_dim", "epochs", "minibatches"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"PAIREDConfig.{name} must be a positive int, got {v!r}")
        hidden = tuple(self.hidden)
        if not all(isinstance(h, int) and h > 0 for h in hidden):
            raise ValueError(f"PAIREDConfig.hidden must be positive ints, got {self.hidden!r}")
        object.__setattr__(self, "hidden", hidden)
        for name in ("lr", "clip_eps", "max_grad_norm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PAIREDConfig.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("ent_coef", "vf_coef"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PAIREDConfig.{name} must be >= 0, got {getattr(self, name)!r}")


def regret(antagonist_max: jax.Array, protagonist_mean: jax.Array) -> jax.Array:
    """DCD's PAIRED regret, clipped at 0: max(max_ep R_A - mean_ep R_P, 0)."""
    return jnp.maximum(antagonist_max - protagonist_mean, 0.0)


@struct.dataclass
class AdversaryState:
    params: Any  # {"actor", "critic"}
    opt_state: Any
    regret_rms: RunningMeanStd  # running statistics of the regret (for the reward scale)


@dataclasses.dataclass(frozen=True)
class Adversary:
    """The level-proposing PPO agent for one-step episodes z -> u ∈ [-1, 1]^d."""

    action_dim: int
    config: PAIREDConfig = PAIREDConfig()

    def __post_init__(self):
        c = self.config
        object.__setattr__(self, "actor", Actor(c.hidden, self.action_dim, False, "tanh", c.init_log_std))
        object.__setattr__(self, "critic", Critic(c.hidden, "tanh"))
        tx = optax.chain(optax.clip_by_global_norm(c.max_grad_norm), optax.adam(c.lr, eps=1e-5))
        object.__setattr__(self, "tx", tx)
        object.__setattr__(
            self, "hparams", PPOHyperparams(lr=c.lr, ent_coef=c.ent_coef, clip_eps=c.clip_eps, vf_coef=c.vf_coef)
        )

    def init(self, key: jax.Array) -> AdversaryState:
        k_a, k_c = jax.random.split(key)
        z = jnp.zeros((self.config.noise_dim,), jnp.float32)
        params = {"actor": self.actor.init(k_a, z)["params"], "critic": self.critic.init(k_c, z)["params"]}
        return AdversaryState(params=params, opt_state=self.tx.init(params), regret_rms=RunningMeanStd.create(()))

    def observe(self, key: jax.Array, n: int) -> jax.Array:
        return jax.random.uniform(key, (n, self.config.noise_dim), jnp.float32)

    def act(self, params, key: jax.Array, z: jax.Array):
        """Sample pre-tanh actions x for observations z [n, noise] -> (x, log_prob, value, u = tanh x)."""
        mean, log_std = self.actor.apply({"params": params["actor"]}, z)
        x = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        value = self.critic.apply({"params": params["critic"]}, z)
        return x, gaussian_log_prob(mean, log_std, x), value, jnp.tanh(x)

    def update(self, astate: AdversaryState, key: jax.Array, z, x, old_log_prob, old_values, rewards):
        """PPO on a batch of one-step episodes; ``rewards`` raw (scaled here by the running std)."""
        c = self.config
        rms = astate.regret_rms.update(rewards)
        r = rewards / jnp.sqrt(rms.var + 1e-8)
        adv = r - old_values  # one-step episode: GAE = reward - V(z)
        batch = (z, x, old_log_prob, old_values, adv, r)

        def loss_fn(params, b):
            bz, bx, blp, bv, badv, btarget = b
            mean, log_std = self.actor.apply({"params": params["actor"]}, bz)
            values = self.critic.apply({"params": params["critic"]}, bz)
            return losses.ppo_loss(
                gaussian_log_prob(mean, log_std, bx), blp, losses.normalize_advantages(badv), values, bv,
                btarget, gaussian_entropy(log_std), self.hparams, False,
            )

        (params, opt_state), aux = minibatch_sgd(loss_fn, self.tx, astate.params, astate.opt_state, batch, key,
                                                 c.epochs, c.minibatches)
        metrics = jax.tree_util.tree_map(jnp.mean, aux)
        metrics["normalised_reward"] = r.mean()
        return AdversaryState(params=params, opt_state=opt_state, regret_rms=rms), metrics


@struct.dataclass
class PAIREDState:
    antagonist: Any  # StudentState
    adversary: AdversaryState


@dataclasses.dataclass(frozen=True)
class PAIRED:
    env: Any
    student: Any
    config: PAIREDConfig = PAIREDConfig()
    name: str = "paired"

    def __post_init__(self):
        e = self.student.config.num_envs
        if e < self.config.minibatches:
            raise ValueError(f"PAIRED: num_envs ({e}) must be >= the adversary's minibatches ({self.config.minibatches})")
        codec = LevelCodec(teacher_space(self.env, self.config.low, self.config.high))
        object.__setattr__(self, "codec", codec)
        object.__setattr__(self, "adversary", Adversary(codec.dim, self.config))
        warn_if_rollouts_cut_episodes(self.name, self.student, codec.space)

    def init(self, key: jax.Array, hparams=None) -> PAIREDState:
        k_ant, k_adv = jax.random.split(key)
        return PAIREDState(antagonist=self.student.init(k_ant, hparams), adversary=self.adversary.init(k_adv))

    def begin_episode(self, key: jax.Array, mstate: PAIREDState, sstate):
        if self.config.reset_on_episode:
            mstate = self.init(key, sstate.hparams)
        else:  # keep the learners, but the antagonist follows the protagonist's hyperparameters
            mstate = mstate.replace(antagonist=mstate.antagonist.replace(hparams=sstate.hparams))
        return mstate, sstate

    def step(self, key: jax.Array, mstate: PAIREDState, sstate):
        student, adv = self.student, self.adversary
        n, u = student.config.num_envs, self.config.updates_per_step

        def agent_update(s, k, params):
            k_a, k_r, k_u = jax.random.split(k, 3)
            s = student.assign_levels(s, k_a, params)
            s, traj = student.rollout(s, k_r)
            mean_ret, max_ret = slot_returns(traj, s.env_state.episode_return)
            s, metrics = student.update(s, k_u, traj)
            return s, metrics, mean_ret, max_ret

        def one_update(carry, k):
            pro, ant, astate = carry
            k_z, k_act, k_seed, k_pro, k_ant, k_adv = jax.random.split(k, 6)
            z = adv.observe(k_z, n)
            x, logp, value, unit = adv.act(astate.params, k_act, z)
            vecs = self.codec.space.from_unit(unit)
            params = self.codec.to_params(vecs, new_seeds(k_seed, n))
            pro, m_pro, pro_mean, _ = agent_update(pro, k_pro, params)
            ant, m_ant, _, ant_max = agent_update(ant, k_ant, params)
            r = regret(ant_max, pro_mean)
            astate, m_adv = adv.update(astate, k_adv, z, x, logp, value, r)
            rec = dict(
                levels=vecs, regret=r.mean(), pro=m_pro, ant=m_ant, adv=m_adv,
                pro_return=pro_mean.mean(), ant_return=ant_max.mean(),
            )
            return (pro, ant, astate), rec

        carry = (sstate, mstate.antagonist, mstate.adversary)
        (sstate, ant, astate), rec = jax.lax.scan(one_update, carry, jax.random.split(key, u))
        steps = u * student.env_steps_per_update
        info = StepInfo(
            levels=rec["levels"].reshape(u * n, -1),
            env_steps_train=jnp.int32(steps),
            env_steps_eval=jnp.int32(0),
            teacher_reward=rec["regret"].mean(),
            num_new_levels=jnp.int32(u * n),
            extras={
                "env_steps_antagonist": jnp.int32(steps),
                "ppo": mean_metrics(rec["pro"]),
                "antagonist_ppo": mean_metrics(rec["ant"]),
                "adversary": mean_metrics(rec["adv"]),
                "protagonist_return": rec["pro_return"].mean(),
                "antagonist_max_return": rec["ant_return"].mean(),
                "levels_trained_mask": jnp.ones((u * n,), bool),
            },
        )
        return PAIREDState(antagonist=ant, adversary=astate), sstate, info
