"""Named experiment presets: everything a run needs besides the seed, as one frozen value.

* ``quick``: CPU-sized (a few minutes on 2 cores), for smoke runs and the test suite.
* ``paper``: docs/design.md §10.3 budgets. Lander: C = 10 PPO updates of 40 x 128 = 51,200 env steps per budget
  step, T = 20 budget steps (1.02e6 student steps, the paper's 1e6), n = 5 levels, m = 10 eval
  envs with 8 episodes each, the official 10 test landers (10 episodes, 500 steps). SHED and h-MDP
  run N_ep = 50 teacher episodes (the student is re-initialised each episode; the test set runs in
  episodes 0, 10, 20, 30, 40 and 49); the baselines train
  one student over the same T budget steps. Walker: C = 3 updates of 1,024 x 64 = 196,608 steps,
  T = 50 (9.83e6 student steps, the paper's 1e7 to 2 %), n = 4, E_eval = 4, N_ep = 20, test set B (10 ladder levels, 2000
  steps).

``build_experiment(env, method, preset, **overrides)`` returns an :class:`Experiment`; the CLI and
the sweep tools are the only places that read presets, so a library user can ignore this module and
build the parts directly.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from shed_jax.loop import LoopSpec
from shed_jax.student import PPOConfig

PRESETS = ("quick", "paper")
EPISODIC_METHODS = ("shed", "hmdp", "shed-x", "hmdp-x")


@dataclasses.dataclass(frozen=True)
class Experiment:
    env: str
    method: str
    preset: str
    ppo: PPOConfig
    method_config: dict  # field overrides for the method's own config (see methods.registry)
    loop: LoopSpec
    test_set: str  # a name in the env's ued.test_sets (envs.core.UEDSpec)

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["ppo"]["hparams"] = dataclasses.asdict(self.ppo.hparams) if dataclasses.is_dataclass(self.ppo.hparams) else {
            f: getattr(self.ppo.hparams, f) for f in self.ppo.hparams.__dataclass_fields__
        }
        return out

    @property
    def env_steps_per_budget_step(self) -> int:
        return self.ppo.batch_size * int(self.method_config.get("updates_per_step", 1))


def default_chunk(exp: Experiment) -> int:
    """Budget steps per compiled chunk (progress line, checkpoint) when ``--chunk`` is not given.

    A walker budget step costs about 20 s on an H200 (MJX's per-step latency in its evaluations), so
    its chunks are 2 budget steps and the progress bar moves at least once a minute; the lander's are
    one teacher episode.
    Always a divisor of the episode length, so chunks never straddle two episodes unevenly.
    """
    T = exp.loop.steps_per_episode
    if _base_env(exp.env) == "walker" and exp.preset == "paper" and T % 2 == 0:
        return 2
    return T


def _base_env(env: str) -> str:
    return "lander" if env.startswith("lander") else env


def build_experiment(env: str, method: str, preset: str, *, episodes: int | None = None,
                     steps_per_episode: int | None = None, test_episode_every: int | None = None,
                     method_overrides: dict | None = None, ppo_overrides: dict | None = None) -> Experiment:
    """The named preset for (env, method); ``episodes``/``steps_per_episode`` override N_ep/T,
    ``test_episode_every`` the teacher episodes in which the test set runs (``LoopSpec``),
    ``method_overrides`` fields of the method's config and ``ppo_overrides`` fields of the student's
    PPO config (``PPOConfig.with_overrides``)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; known: {', '.join(PRESETS)}")
    kind = _base_env(env)
    if kind not in ("lander", "walker"):
        raise ValueError(f"no UED presets for environment {env!r}; use lander, lander-continuous or walker")
    episodic = method in EPISODIC_METHODS
    if preset == "paper":
        if kind == "lander":
            ppo = PPOConfig.for_env(env)
            mcfg: dict[str, Any] = {"updates_per_step": 10}
            T, n_ep = 20, (50 if episodic else 1)
            test = dict(test_episodes=10, test_max_steps=500)
            test_set = "lander-test"
            if method in ("shed", "hmdp", "accel-norevisit", "shed-x", "hmdp-x"):
                mcfg["num_levels"] = 5
        else:
            ppo = PPOConfig.for_env("walker")
            mcfg = {"updates_per_step": 3}  # 3 x 1,024 x 64 = 196,608 steps; x 50 = 9.83e6
            T, n_ep = 50, (20 if episodic else 1)
            test = dict(test_episodes=10, test_max_steps=2000)
            test_set = "walker-test-b"
            if method in ("shed", "hmdp", "accel-norevisit", "shed-x", "hmdp-x"):
                mcfg["num_levels"] = 4
            if episodic:  # docs/design.md §10.3: E_eval = 4 evaluation episodes per eval level (lander: 8)
                mcfg["num_eval_episodes"] = 4
    else:  # quick
        if kind == "lander":
            ppo = PPOConfig.for_env(env, num_envs=16, num_steps=64, update_epochs=2, num_minibatches=4)
            test = dict(test_episodes=2, test_max_steps=200)
            test_set = "lander-test"
        else:
            ppo = PPOConfig.for_env("walker", num_envs=16, num_steps=16, update_epochs=1, num_minibatches=2)
            test = dict(test_episodes=1, test_max_steps=100)
            test_set = "walker-test-b"
        mcfg = {"updates_per_step": 2}
        T, n_ep = 4, (2 if episodic else 1)
        if method in ("shed", "hmdp", "accel-norevisit", "shed-x", "hmdp-x"):
            mcfg["num_levels"] = 4
        if episodic:  # a cheap teacher state: one short evaluation episode per eval level
            mcfg.update(num_eval_episodes=1, eval_max_steps=test["test_max_steps"])
    # None means "the preset's value"; 0 or a negative count is an error (LoopSpec names the field),
    # never silently the default
    T = T if steps_per_episode is None else steps_per_episode
    # SHED/h-MDP paper runs: test the students of teacher episodes 0, 10, 20, ... and the last
    # (docs/design.md §9.3 reports the first and last episodes); by step counts this saves about a fifth
    test_ep = 10 if (preset == "paper" and episodic) else 1
    if test_episode_every is not None:  # LoopSpec rejects values < 1
        test_ep = test_episode_every
    if episodic:
        mcfg["budget_steps"] = T  # the teacher's done flag marks the T-th transition
    if method_overrides:
        mcfg.update(method_overrides)
    if ppo_overrides:
        ppo = ppo.with_overrides(ppo_overrides)
    loop = LoopSpec(
        steps_per_episode=T,
        num_episodes=n_ep if episodes is None else episodes,
        test_episode_every=test_ep,
        **test,
    )
    return Experiment(env=env, method=method, preset=preset, ppo=ppo, method_config=mcfg, loop=loop, test_set=test_set)
