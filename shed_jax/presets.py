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
* ``dcd`` (walker and bipedal only): DCD's BipedalWalker budget (Parker-Holder et al. 2022, ACCEL:
  about 6.6e8 student steps per seed) with the paper preset's student and levels: T = 3,360 budget
  steps of 196,608 (6.606e8 steps), one teacher episode, test set B at every 168th step (20 points,
  the last included). The student is this project's walker preset, not DCD's PPO settings, so the
  comparison with DCD's table is at equal student steps, not an equal learner.

``build_experiment(env, method, preset, **overrides)`` returns an :class:`Experiment`; the CLI and
the sweep tools are the only places that read presets, so a library user can ignore this module and
build the parts directly.
"""
from __future__ import annotations

import dataclasses
from typing import Any

from shed_jax import configs
from shed_jax.loop import LoopSpec
from shed_jax.student import PPOConfig

PRESETS = ("quick", "paper", "dcd")


@dataclasses.dataclass(frozen=True)
class Experiment:
    """Everything a run needs besides its seeds. ``method_config`` is the method's own config
    dataclass (``methods.registry.config_class``); a dict given here is read as its fields."""

    env: str
    method: str
    preset: str
    ppo: PPOConfig
    method_config: Any
    loop: LoopSpec
    test_set: str  # a name in the env's ued.test_sets (envs.core.UEDSpec)

    def __post_init__(self):
        from shed_jax.methods.registry import METHODS, config_class

        cls = config_class(self.method)
        if cls is None:
            raise ValueError(f"unknown method {self.method!r}; known: {', '.join(METHODS)}")
        object.__setattr__(self, "method_config", configs.coerce(cls, self.method_config, f"method {self.method!r}"))

    def to_dict(self) -> dict:
        """The JSON form (``config.json``); ``experiment.experiment_from_dict`` inverts it."""
        return dataclasses.asdict(self)

    @property
    def episodic(self) -> bool:
        """Whether the method trains a fresh student in each of ``loop.num_episodes`` teacher episodes."""
        return episodic(self.method_config)

    @property
    def env_steps_per_budget_step(self) -> int:
        return self.ppo.batch_size * self.method_config.updates_per_step


def episodic(method_config) -> bool:
    """Whether a method (by its config) runs teacher episodes, each with a fresh student (SHED, h-MDP):
    its config has the teacher's episode length ``budget_steps``. The baselines train one student."""
    return hasattr(method_config, "budget_steps")


@dataclasses.dataclass(frozen=True)
class Preset:
    """One row of the preset table: an environment's budgets at one preset.

    Method fields (``updates_per_step`` and the rest of ``method``) are applied to every method whose
    config has the field; ``teacher_episodes``, ``test_episode_every`` and ``teacher`` apply to the
    episodic methods (SHED, h-MDP) only, whose teacher episode length ``budget_steps`` is T.
    """

    student: dict  # PPOConfig overrides on top of the environment's student (PPOConfig.for_env)
    steps_per_episode: int  # T
    teacher_episodes: int  # N_ep of the episodic methods (the baselines run one student: 1)
    test_set: str
    test_episodes: int
    test_max_steps: int
    method: dict  # fields of every method's config that has them
    teacher: dict = dataclasses.field(default_factory=dict)  # fields of the episodic methods' configs
    test_episode_every: int = 1  # episodic methods: test in every k-th teacher episode (and the last)
    test_every: int = 1  # the baselines (one student, one episode): test every k-th budget step
    test_every_episodic: int = 1  # episodic methods: test every k-th budget step of a tested episode
    chunk: int | None = None  # budget steps per compiled chunk; None: one teacher episode
    max_recorded_levels: int | None = LoopSpec.max_recorded_levels  # generated levels kept per budget step


# The table: (environment, preset) -> its budgets. ``paper`` is docs/design.md §10.3; ``quick`` is
# CPU-sized (a few minutes on 2 cores), for smoke runs and the test suite.
_LANDER_PAPER = Preset(
    student={}, steps_per_episode=20, teacher_episodes=50, test_set="lander-test", test_episodes=10, test_max_steps=500,
    method={"updates_per_step": 10, "num_levels": 5},
    # test the students of teacher episodes 0, 10, 20, ... and the last (docs/design.md §9.3 reports the
    # first and last episodes); by step counts this saves about a fifth
    test_episode_every=10,
)
_LANDER_QUICK = Preset(
    student=dict(num_envs=16, num_steps=64, update_epochs=2, num_minibatches=4), steps_per_episode=4, teacher_episodes=2,
    test_set="lander-test", test_episodes=2, test_max_steps=200,
    method={"updates_per_step": 2, "num_levels": 4},
    teacher={"num_eval_episodes": 1, "eval_max_steps": 200},  # a cheap teacher state: one short episode per eval level
)
TABLE: dict[tuple[str, str], Preset] = {
    ("lander", "paper"): _LANDER_PAPER,
    ("lander", "quick"): _LANDER_QUICK,
    ("lander-continuous", "paper"): _LANDER_PAPER,
    ("lander-continuous", "quick"): _LANDER_QUICK,
    # 3 x 1,024 x 64 = 196,608 steps per budget step; x 50 = 9.83e6 (the paper's 1e7 to 2 %). A SHED
    # budget step costs about 15 s on an H200 (MJX's per-step latency in the evaluations), so chunks
    # are 2 budget steps and the progress line moves at least once a minute.
    ("walker", "paper"): Preset(
        student={}, steps_per_episode=50, teacher_episodes=20, test_set="walker-test-b", test_episodes=10,
        test_max_steps=2000, method={"updates_per_step": 3, "num_levels": 4},
        teacher={"num_eval_episodes": 4},  # E_eval = 4 evaluation episodes per eval level (lander: 8)
        # the baselines test at every 5th budget step (10 points of the curve, the last included):
        # a test-set rollout costs several training steps on MJX
        test_episode_every=10, test_every=5, chunk=2,
    ),
    ("walker", "quick"): Preset(
        student=dict(num_envs=16, num_steps=16, update_epochs=1, num_minibatches=2), steps_per_episode=4,
        teacher_episodes=2, test_set="walker-test-b", test_episodes=1, test_max_steps=100,
        method={"updates_per_step": 2, "num_levels": 4}, teacher={"num_eval_episodes": 1, "eval_max_steps": 100},
    ),}
# DCD's budget: 3,360 x 196,608 = 6.606e8 steps per seed (DCD's 6.6e8 to 0.1 %), one student and one
# teacher episode for every method. Chunks of 8 budget steps keep the host's progress line and the
# checkpoints about once a minute on the 2-D walker; the test set runs 20 times. The record keeps 8
# generated levels per budget step (not 64), so 5 seeds' metrics.jsonl stays near 27 MB (DR's rows of
# 2026-11-28, thinned) and the checkpoint's history near 10 MB over 3,360 steps: small enough to
# carry between device machines. SHED and h-MDP at this preset are one teacher episode of 3,360
# steps, not the paper's protocol: a budget comparison with DCD's baselines, not a SHED reproduction.
TABLE[("walker", "dcd")] = dataclasses.replace(
    TABLE[("walker", "paper")], steps_per_episode=3360, teacher_episodes=1, test_every=168, test_every_episodic=168,
    test_episode_every=1, chunk=8, max_recorded_levels=8)
# The Box2D-faithful walker on physics2d shares the MJX walker's level space, level sets and student
# (docs/bipedal.md), so it runs the walker's protocol; only its physics (and speed) differ.
TABLE[("bipedal", "paper")] = TABLE[("walker", "paper")]
TABLE[("bipedal", "quick")] = TABLE[("walker", "quick")]
TABLE[("bipedal", "dcd")] = TABLE[("walker", "dcd")]


def preset_row(env: str, name: str) -> Preset:
    """The table's row for (env, preset); ValueError naming what exists."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    if (env, name) not in TABLE:
        envs = sorted({e for e, _ in TABLE})
        if env not in envs:
            raise ValueError(f"no UED presets for environment {env!r}; use {', '.join(envs)}")
        own = [n for n in PRESETS if (env, n) in TABLE]
        raise ValueError(f"environment {env!r} has no preset {name!r}; its presets: {', '.join(own)}")
    return TABLE[(env, name)]


def default_chunk(exp: Experiment) -> int:
    """Budget steps per compiled chunk (progress line, checkpoint) when ``--chunk`` is not given: the
    largest divisor of the episode length T not above the preset's ``chunk`` (so chunks never straddle
    two episodes unevenly, and a T the preset did not plan for never becomes one long silent chunk);
    T where the preset sets no chunk."""
    T = exp.loop.steps_per_episode
    chunk = TABLE[(exp.env, exp.preset)].chunk if (exp.env, exp.preset) in TABLE else None
    if not chunk:
        return T
    return max(d for d in range(1, min(chunk, T) + 1) if T % d == 0)


def _fields_of(config, values: dict) -> dict:
    names = {f.name for f in dataclasses.fields(config)}
    return {k: v for k, v in values.items() if k in names}


def build_experiment(env: str, method: str, preset: str, *, episodes: int | None = None,
                     steps_per_episode: int | None = None, test_episode_every: int | None = None,
                     method_overrides: dict | None = None, ppo_overrides: dict | None = None) -> Experiment:
    """The named preset for (env, method); ``episodes``/``steps_per_episode`` override N_ep/T,
    ``test_episode_every`` the teacher episodes in which the test set runs (``LoopSpec``),
    ``method_overrides`` fields of the method's config (``configs.with_overrides``: nested dicts
    merge) and ``ppo_overrides`` fields of the student's PPO config (``PPOConfig.with_overrides``).
    None means the preset's value; 0 or a negative count is an error naming the field."""
    from shed_jax.methods.registry import METHODS, config_class

    row = preset_row(env, preset)
    cls = config_class(method)
    if cls is None:
        raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")
    base = cls()
    is_episodic = episodic(base)
    T = row.steps_per_episode if steps_per_episode is None else steps_per_episode
    fields = {**row.method, **(row.teacher if is_episodic else {})}
    if is_episodic:
        fields["budget_steps"] = T  # the teacher's done flag marks the T-th transition
    mcfg = configs.with_overrides(base, _fields_of(base, fields))
    mcfg = configs.with_overrides(mcfg, method_overrides, "--set ")
    ppo = PPOConfig.for_env(env, **row.student)
    if ppo_overrides:
        ppo = ppo.with_overrides(ppo_overrides)
    loop = LoopSpec(
        steps_per_episode=T,
        num_episodes=(row.teacher_episodes if is_episodic else 1) if episodes is None else episodes,
        test_episode_every=(row.test_episode_every if is_episodic else 1) if test_episode_every is None else test_episode_every,
        test_every=row.test_every_episodic if is_episodic else row.test_every,
        test_episodes=row.test_episodes,
        test_max_steps=row.test_max_steps,
        max_recorded_levels=row.max_recorded_levels,
    )
    return Experiment(env=env, method=method, preset=preset, ppo=ppo, method_config=mcfg, loop=loop, test_set=row.test_set)
