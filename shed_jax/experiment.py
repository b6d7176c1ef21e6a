"""Experiments from flags and from saved dicts, and the parts they build.

An :class:`shed_jax.presets.Experiment` is everything a run needs besides its seeds. This module
makes one from the command line's values (``experiment_from_args``: a preset, ``--set`` method
fields routed into the method's config, ``--ppo`` student fields), rebuilds one from
``Experiment.to_dict()`` as ``config.json`` and checkpoints hold it (``experiment_from_dict``),
compares the flags given with ``--resume`` against a saved one (``check_resume_flags``) and builds
the environment, student, method and test levels (``build``).

Bad values raise :class:`shed_jax.errors.UsageError` (one line naming the field and what it takes).
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np

from shed_jax.errors import UsageError

ENVS = ("lander", "lander-continuous", "walker", "bipedal")  # the environments with UED presets (shed_jax/presets.py)

DEFAULT_ENV = "lander"
DEFAULT_METHOD = "shed"
DEFAULT_PRESET = "auto"
DEFAULT_ROOT_SEED = 0


# ---------------------------------------------------------------------------------------------
# --set / --ppo
# ---------------------------------------------------------------------------------------------

def parse_overrides(items: list[str]) -> dict:
    """``--set KEY=VALUE`` items -> ``{key: value}``; values are JSON where they parse, else strings."""
    out = {}
    for item in items:
        if "=" not in item:
            raise UsageError(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def parse_ppo_overrides(items: list[str]) -> dict:
    """``--ppo KEY=VALUE`` items -> PPOConfig / PPOHyperparams overrides (UsageError for unknown fields)."""
    from shed_jax.student.config import parse_overrides as parse_ppo

    try:
        return parse_ppo(items)
    except ValueError as err:
        raise UsageError(str(err)) from err


def _reward_fields() -> tuple[str, ...]:
    from shed_jax.teacher.reward import RewardConfig

    return tuple(f.name for f in dataclasses.fields(RewardConfig))


def route_method_overrides(method: str, overrides: dict) -> dict:
    """``--set`` items -> overrides of the method's config (``configs.with_overrides``).

    SHED and h-MDP keep the teacher reward's options (``eta``, ``form``, ... of
    ``shed_jax.teacher.reward.RewardConfig``) in their ``reward`` field: a key that is one of those
    and no field of the method's own config goes inside ``reward``, so ``--set eta=10`` means
    ``--set 'reward={"eta": 10}'`` (a dict for a nested config is merged into it).
    """
    cls = method_config_class(method)
    own = {f.name for f in dataclasses.fields(cls)} if cls is not None else set()
    out: dict = {}
    for key, value in overrides.items():
        if "reward" in own and key not in own and key in _reward_fields():
            out["reward"] = {**out.get("reward", {}), key: value}
        elif key == "reward" and isinstance(value, dict) and isinstance(out.get("reward"), dict):
            out["reward"] = {**out["reward"], **value}
        else:
            out[key] = value
    return out


def check_method_overrides(method: str, overrides: dict) -> None:
    """UsageError for a ``--set`` key the method's config does not have, naming the known ones (kinds
    and values are checked when the overrides are applied)."""
    cls = method_config_class(method)
    if cls is None:
        return
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        reward = f"; the teacher reward's: {', '.join(_reward_fields())}" if "reward" in fields else ""
        raise UsageError(f"--set: method {method!r} has no config field(s) {', '.join(map(repr, unknown))}; "
                         f"known: {', '.join(sorted(fields))}{reward}")


def method_config_class(name: str):
    """The method's config dataclass (None for an unknown method: make_method reports it)."""
    from shed_jax.methods.registry import config_class

    return config_class(name)


# ---------------------------------------------------------------------------------------------
# building
# ---------------------------------------------------------------------------------------------

def check_bounds(config, env) -> None:
    """ValueError unless the teacher box's ``low``/``high`` (if the method's config sets them) hold one
    number per env parameter."""
    space = env.param_space
    for key in ("low", "high"):
        value = getattr(config, key, None)
        if value is None:
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        if len(values) != space.dim or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            name = getattr(env, "name", "this environment")
            from shed_jax.levels import teacher_space

            example = ",".join(f"{float(v):g}" for v in getattr(teacher_space(env), key))  # Θ's own bound
            raise ValueError(f"--set {key}: expected a list of {space.dim} numbers for {name} "
                             f"({', '.join(space.names)}), e.g. {key}=[{example}], got {json.dumps(value, default=str)}")


def test_levels(name: str, env):
    """The named test set's levels (a params pytree with a leading axis), from the env (``env.ued.test_sets``)."""
    from shed_jax import levels

    return levels.test_set(env, name)[0]


def build(exp):
    """Environment, student (the method's pool of students if it has one), method and test levels for an Experiment."""
    import envs
    from shed_jax.methods.registry import make_method
    from shed_jax.student import make_student

    env = envs.make(exp.env)
    check_bounds(exp.method_config, env)  # else numpy's broadcast error, far from the flag
    student = make_student(env, exp.ppo)
    method = make_method(exp.method, env, student, exp.method_config)
    # a method that trains several students at once (hmdp-x/shed-x with students > 1) has their pool:
    # the loop's student, whose state carries the students' axis
    return env, getattr(method, "pool", student), method, test_levels(exp.test_set, env)


def build_checked(exp, fresh: bool):
    """``build(exp)``; a value the configs refuse is a UsageError (``fresh``) or a CheckpointError (a saved run)."""
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.errors import one_line

    try:
        return build(exp)
    except (ValueError, TypeError) as err:
        if not fresh:
            raise CheckpointError(f"the saved configuration cannot be built: {one_line(str(err), 300)}") from err
        hint = " (a --set/--ppo value of the wrong type?)" if isinstance(err, TypeError) else ""
        raise UsageError(f"{err}{hint}") from err


def seed_keys(root_seed: int, num_seeds: int):
    """Seed i's key: ``fold_in(PRNGKey(root_seed), i)`` (every run and every sweep point)."""
    import jax

    root = jax.random.PRNGKey(root_seed)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(np.arange(num_seeds))


def default_seeds(exp) -> int:
    """Seeds when --seeds is not given: quick 2, the GPU presets (paper, dcd) 5 (on any backend: the walker's CPU deadlock
    with two seeds was the batched-LAPACK one of shed_jax/xla_cpu.py, which the student init avoids)."""
    return preset_default_seeds(exp.preset)


def preset_default_seeds(preset: str) -> int:
    """:func:`default_seeds` by the preset's name (a sweep resolves its preset before its experiments)."""
    return 2 if preset == "quick" else 5


# ---------------------------------------------------------------------------------------------
# from flags, from a saved dict
# ---------------------------------------------------------------------------------------------

def resolve_preset(preset: str | None, backend: str, say: bool = True) -> str:
    """``--preset`` with ``auto`` resolved for ``backend`` ('paper' on a GPU, else 'quick'), said when ``say``."""
    preset = preset or DEFAULT_PRESET
    if preset == "auto":
        preset = "paper" if backend == "gpu" else "quick"
        if say:
            print(f"[shed_jax] backend={backend}: using the '{preset}' preset "
                  f"({'GPU budgets from docs/design.md §10.3' if preset == 'paper' else 'a CPU-sized smoke run; pass --preset paper for the real budget'})")
    return preset


def experiment_from_args(args, backend: str):
    """The Experiment the run flags ask for (``--preset auto`` resolved for ``backend``, and said).

    ``args`` has the run command's flags as attributes (``env``, ``method``, ``preset``, ``episodes``,
    ``steps_per_episode``, ``test_episode_every``, ``set``, ``ppo``). Bad values (an unknown
    ``--set``/``--ppo`` field, a value a config refuses) raise UsageError.
    """
    from shed_jax.presets import build_experiment

    preset = resolve_preset(args.preset, backend)
    method = args.method or DEFAULT_METHOD
    overrides = route_method_overrides(method, parse_overrides(args.set))
    check_method_overrides(method, overrides)
    try:
        return build_experiment(args.env or DEFAULT_ENV, method, preset, episodes=args.episodes,
                                steps_per_episode=args.steps_per_episode, test_episode_every=args.test_episode_every,
                                method_overrides=overrides, ppo_overrides=parse_ppo_overrides(args.ppo))
    except ValueError as err:
        raise UsageError(str(err)) from err


def experiment_from_dict(d: dict):
    """Rebuild an Experiment from ``Experiment.to_dict()`` (as saved in config.json / a checkpoint).
    Fields missing from an older save take the values that save ran with where those differ from
    today's defaults (``SAVED_BEFORE`` of the method's config, LoopSpec.max_recorded_levels), else
    the defaults."""
    from shed_jax import configs
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.loop import LoopSpec
    from shed_jax.presets import Experiment
    from shed_jax.student import PPOConfig

    try:
        return Experiment(
            env=d["env"], method=d["method"], preset=d["preset"], ppo=configs.from_dict(PPOConfig, d["ppo"]),
            method_config=_with_saved_defaults(d["method"], d["method_config"]),
            # runs saved before LoopSpec.max_recorded_levels existed recorded every level
            loop=LoopSpec(**{"max_recorded_levels": None, **d["loop"]}), test_set=d["test_set"],
        )
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"cannot rebuild the experiment from the saved configuration: {type(err).__name__}: {err}") from err


def _with_saved_defaults(method: str, saved: dict) -> dict:
    """A saved method config with the fields it predates at the values it ran with (the config
    class's ``SAVED_BEFORE``), not at today's defaults."""
    from shed_jax.methods.registry import config_class

    cls = config_class(method)
    return {**getattr(cls, "SAVED_BEFORE", {}), **saved}


EXPERIMENT_FLAGS = ("env", "method", "preset", "episodes", "steps_per_episode", "test_episode_every")


def experiment_flags_given(args) -> bool:
    """Whether ``args`` sets any flag that shapes the experiment."""
    return any(getattr(args, k) is not None for k in EXPERIMENT_FLAGS) or bool(args.set) or bool(args.ppo)


def check_resume_flags(args, config: dict, saved, backend: str, out) -> None:
    """ConfigMismatchError naming each flag given with --resume whose value differs from the SAVED run's.

    Flags are applied to the saved experiment (``--set`` as for a fresh run, routed and merged), and
    both sides are compared as the method builds them (its config's defaults filled in), so a flag
    equal to the saved value, or to a default the saved run used, is no difference.
    """
    from shed_jax.checkpoint import ConfigMismatchError, config_differences, describe_differences

    diffs = []
    preset = resolve_preset(args.preset, backend, say=False) if args.preset is not None else None
    for name, given in (("env", args.env), ("method", args.method), ("preset", preset)):
        if given is not None and given != getattr(saved, name):
            diffs.append((f"experiment.{name}", getattr(saved, name), given))
    if not diffs:  # the same env and method: their fields can be compared one by one
        current = _apply_resume_flags(args, saved)
        diffs = config_differences({"experiment": saved.to_dict()}, {"experiment": current.to_dict()}, ["experiment"])
    for key, given in (("seeds", args.seeds), ("root_seed", args.seed)):
        if given is not None and given != int(config[key]):
            diffs.append((key, int(config[key]), given))
    if diffs:
        raise ConfigMismatchError(f"--resume {out}: flag(s) given that differ from the saved run: "
                                  f"{describe_differences(diffs)}; drop them to continue with the saved configuration", diffs)


def _apply_resume_flags(args, exp):
    """The saved Experiment with the experiment flags of ``args`` applied (as a fresh run applies them to a preset)."""
    from shed_jax import configs
    from shed_jax.presets import episodic

    mc = exp.method_config
    changes = {}
    for flag, field in (("episodes", "num_episodes"), ("steps_per_episode", "steps_per_episode"),
                        ("test_episode_every", "test_episode_every")):
        if getattr(args, flag) is not None:
            changes[field] = getattr(args, flag)
    try:
        if args.steps_per_episode is not None and episodic(mc):
            mc = configs.with_overrides(mc, {"budget_steps": args.steps_per_episode})
        if args.set:
            overrides = route_method_overrides(exp.method, parse_overrides(args.set))
            check_method_overrides(exp.method, overrides)
            mc = configs.with_overrides(mc, overrides, "--set ")
        loop = dataclasses.replace(exp.loop, **changes)
        ppo = exp.ppo.with_overrides(parse_ppo_overrides(args.ppo)) if args.ppo else exp.ppo
    except ValueError as err:
        raise UsageError(str(err)) from err
    return dataclasses.replace(exp, method_config=mc, loop=loop, ppo=ppo)
