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

**Whole episodes** (``level_switch="episode"``): slot j holds the adversary's newest level for it;
each agent's slot moves to that level at its next episode end (``student.rollout``'s
``next_levels``), so no episode is cut. A level is complete once both agents have ended at least
one episode on it; its regret is max over the antagonist's episodes on it minus the mean over the
protagonist's, clipped at 0, from every episode they ended on it (across rollouts, no fallback to
unfinished ones). Each rollout, the adversary takes a PPO update on the levels completed in it (a
masked batch; none: no update) and proposes a new level for each of those slots. Both agents
train on every transition, as in native mode.

Budget: ``env_steps_train`` counts protagonist steps; antagonist steps are in
``extras["env_steps_antagonist"]``; ``teacher_reward`` is the mean (unnormalised) regret.
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from shed_jax.configs import check_modes
from shed_jax.levels import LevelCodec, new_seeds, slot_returns, teacher_space
from shed_jax.methods.base import StepInfo, mean_metrics, nan_like, warn_if_rollouts_cut_episodes
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
    # "rollout": every rollout puts every slot of both agents on a new adversary level. "episode": a
    # slot's level stays until both agents have ended an episode on it (module docstring).
    level_switch: Literal["rollout", "episode"] = "episode"
    # what a run saved before a field existed ran with (experiment_from_dict fills it in)
    SAVED_BEFORE: ClassVar[dict] = {"level_switch": "rollout"}

    def __post_init__(self):
        check_modes(self)
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

    def update(self, astate: AdversaryState, key: jax.Array, z, x, old_log_prob, old_values, rewards, mask=None):
        """PPO on a batch of one-step episodes; ``rewards`` raw (scaled here by the running std).
        ``mask`` [n] (optional): only those episodes count (every mean is over them)."""
        c = self.config
        rms = astate.regret_rms.update(rewards, mask)
        r = rewards / jnp.sqrt(rms.var + 1e-8)
        adv = r - old_values  # one-step episode: GAE = reward - V(z)
        batch = (z, x, old_log_prob, old_values, adv, r)
        if mask is not None:
            batch = batch + (jnp.asarray(mask, jnp.float32),)

        def loss_fn(params, b):
            bz, bx, blp, bv, badv, btarget = b[:6]
            w = b[6] if mask is not None else None
            mean, log_std = self.actor.apply({"params": params["actor"]}, bz)
            values = self.critic.apply({"params": params["critic"]}, bz)
            return losses.ppo_loss(
                gaussian_log_prob(mean, log_std, bx), blp, losses.normalize_advantages(badv, weights=w), values, bv,
                btarget, gaussian_entropy(log_std), self.hparams, False, w,
            )

        (params, opt_state), aux = minibatch_sgd(loss_fn, self.tx, astate.params, astate.opt_state, batch, key,
                                                 c.epochs, c.minibatches)
        metrics = jax.tree_util.tree_map(jnp.mean, aux)
        metrics["normalised_reward"] = r.mean()
        return AdversaryState(params=params, opt_state=opt_state, regret_rms=rms), metrics


@struct.dataclass
class PairedSlots:
    """Whole-episode mode: per slot, the newest adversary level and what both agents did on it ([n] each)."""

    vecs: jax.Array  # [n, d] the newest level of each slot
    seeds: jax.Array  # [n] its terrain seed
    z: jax.Array  # [n, noise] the adversary's observation, x / log_prob / value its action and estimates
    x: jax.Array
    log_prob: jax.Array
    value: jax.Array
    pro_on: jax.Array  # [n] bool: the protagonist's slot plays the newest level
    ant_on: jax.Array
    pro_sum: jax.Array  # [n] sum and count of the protagonist's episode returns on it
    pro_count: jax.Array
    ant_max: jax.Array  # [n] the antagonist's best episode return on it, and its count
    ant_count: jax.Array


def newest_level_returns(on, traj):
    """Per slot, the (sum, count, max) of the episode returns a rollout ended on the slot's newest
    level: every episode if the slot was on it (``on``), else those after its first episode end (the
    slot then moved to it). [n] each."""
    done = traj.dones.astype(bool)
    T = done.shape[0]
    first = jnp.where(done.any(axis=0), jnp.argmax(done, axis=0), T)
    counts = done & (on[None] | (jnp.arange(T)[:, None] > first[None]))
    ret = traj.episode_returns
    return (jnp.sum(jnp.where(counts, ret, 0.0), axis=0), counts.sum(axis=0).astype(jnp.float32),
            jnp.max(jnp.where(counts, ret, -jnp.inf), axis=0))


@struct.dataclass
class PAIREDState:
    antagonist: Any  # StudentState
    adversary: AdversaryState
    slots: Any = None  # PairedSlots in whole-episode mode, else None


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
        if self.config.level_switch == "rollout":
            warn_if_rollouts_cut_episodes(self.name, self.student, codec.space, " So does level_switch=episode, the default.")

    def init(self, key: jax.Array, hparams=None) -> PAIREDState:
        k_ant, k_adv = jax.random.split(key)
        state = PAIREDState(antagonist=self.student.init(k_ant, hparams), adversary=self.adversary.init(k_adv))
        if self.config.level_switch == "episode":
            state = state.replace(slots=self._propose(jax.random.fold_in(key, 1), state.adversary))
        return state

    def _propose(self, key, astate: AdversaryState) -> PairedSlots:
        """One new adversary level per slot, with empty statistics (no agent on it yet)."""
        n = self.student.config.num_envs
        k_z, k_act, k_seed = jax.random.split(key, 3)
        z = self.adversary.observe(k_z, n)
        x, logp, value, unit = self.adversary.act(astate.params, k_act, z)
        zeros, off = jnp.zeros((n,), jnp.float32), jnp.zeros((n,), bool)
        return PairedSlots(vecs=self.codec.space.from_unit(unit), seeds=new_seeds(k_seed, n), z=z, x=x, log_prob=logp,
                           value=value, pro_on=off, ant_on=off, pro_sum=zeros, pro_count=zeros,
                           ant_max=jnp.full((n,), -jnp.inf, jnp.float32), ant_count=zeros)

    def begin_episode(self, key: jax.Array, mstate: PAIREDState, sstate):
        k_init, k_assign = (jax.random.split(key) if self.config.level_switch == "episode" else (key, None))
        if self.config.reset_on_episode:
            mstate = self.init(k_init, sstate.hparams)
        else:  # keep the learners, but the antagonist follows the protagonist's hyperparameters
            mstate = mstate.replace(antagonist=mstate.antagonist.replace(hparams=sstate.hparams))
        if self.config.level_switch == "episode":  # both agents start every slot on its newest level
            sl = mstate.slots
            params = self.codec.to_params(sl.vecs, sl.seeds)
            k_p, k_a = jax.random.split(k_assign)
            sstate = self.student.assign_levels(sstate, k_p, params)
            on, zeros = jnp.ones_like(sl.pro_on), jnp.zeros_like(sl.pro_sum)
            sl = sl.replace(pro_on=on, ant_on=on, pro_sum=zeros, pro_count=zeros, ant_max=jnp.full_like(zeros, -jnp.inf),
                            ant_count=zeros)
            mstate = mstate.replace(antagonist=self.student.assign_levels(mstate.antagonist, k_a, params), slots=sl)
        return mstate, sstate

    def step(self, key: jax.Array, mstate: PAIREDState, sstate):
        if self.config.level_switch == "episode":
            return self._step_episodes(key, mstate, sstate)
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

    def _step_episodes(self, key: jax.Array, mstate: PAIREDState, sstate):
        """Whole-episode mode: each rollout, both agents' slots move to their slot's newest level at
        their next episode end; a level whose every agent has ended an episode on it is complete:
        its regret trains the adversary (a masked batch) and the slot gets a new adversary level."""
        student, adv = self.student, self.adversary
        n, u = student.config.num_envs, self.config.updates_per_step

        def agent(s, k, sl, on):
            k_r, k_u = jax.random.split(k)
            s, traj = student.rollout(s, k_r, next_levels=self.codec.to_params(sl.vecs, sl.seeds))
            total, count, best = newest_level_returns(on, traj)
            s, metrics = student.update(s, k_u, traj)
            return s, metrics, on | traj.dones.any(axis=0), total, count, best

        def one_update(carry, k):
            pro, ant, astate, sl = carry
            k_pro, k_ant, k_adv, k_new = jax.random.split(k, 4)
            pro, m_pro, pro_on, p_sum, p_cnt, _ = agent(pro, k_pro, sl, sl.pro_on)
            ant, m_ant, ant_on, _, a_cnt, a_max = agent(ant, k_ant, sl, sl.ant_on)
            sl = sl.replace(pro_on=pro_on, ant_on=ant_on, pro_sum=sl.pro_sum + p_sum, pro_count=sl.pro_count + p_cnt,
                            ant_max=jnp.maximum(sl.ant_max, a_max), ant_count=sl.ant_count + a_cnt)
            complete = (sl.pro_count > 0) & (sl.ant_count > 0)
            pro_mean = sl.pro_sum / jnp.maximum(sl.pro_count, 1.0)
            r = jnp.where(complete, regret(jnp.where(complete, sl.ant_max, 0.0), pro_mean), 0.0)
            astate, m_adv = jax.lax.cond(
                complete.any(),
                lambda: adv.update(astate, k_adv, sl.z, sl.x, sl.log_prob, sl.value, r, mask=complete),
                lambda: (astate, nan_like(jax.eval_shape(adv.update, astate, k_adv, sl.z, sl.x, sl.log_prob, sl.value, r)[1])))
            ant_best = jnp.where(complete, sl.ant_max, 0.0)  # read before the completed slots are refilled
            fresh = self._propose(k_new, astate)
            sl = jax.tree_util.tree_map(lambda a, b: jnp.where(complete.reshape((n,) + (1,) * (a.ndim - 1)), a, b), fresh, sl)
            m = jnp.maximum(complete.sum(), 1)
            rec = dict(
                levels=sl.vecs, new=complete, regret=jnp.where(complete.any(), r.sum() / m, jnp.nan), pro=m_pro,
                ant=m_ant, adv=m_adv,
                pro_return=jnp.where(complete.any(), jnp.where(complete, pro_mean, 0.0).sum() / m, jnp.nan),
                ant_return=jnp.where(complete.any(), ant_best.sum() / m, jnp.nan),
            )
            return (pro, ant, astate, sl), rec

        carry = (sstate, mstate.antagonist, mstate.adversary, mstate.slots)
        (sstate, ant, astate, sl), rec = jax.lax.scan(one_update, carry, jax.random.split(key, u))
        steps = u * student.env_steps_per_update
        info = StepInfo(
            levels=rec["levels"].reshape(u * n, -1),
            env_steps_train=jnp.int32(steps),
            env_steps_eval=jnp.int32(0),
            teacher_reward=jnp.nanmean(rec["regret"]),
            num_new_levels=rec["new"].sum().astype(jnp.int32),
            extras={
                "env_steps_antagonist": jnp.int32(steps),
                "ppo": mean_metrics(rec["pro"]),
                "antagonist_ppo": mean_metrics(rec["ant"]),
                "adversary": mean_metrics(rec["adv"]),
                "protagonist_return": jnp.nanmean(rec["pro_return"]),
                "antagonist_max_return": jnp.nanmean(rec["ant_return"]),
                # the new levels the adversary proposed in each rollout (a slot plays one until both agents end an episode)
                "levels_trained_mask": rec["new"].reshape(u * n),
            },
        )
        return PAIREDState(antagonist=ant, adversary=astate, slots=sl), sstate, info
