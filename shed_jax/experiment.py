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

import copy
import dataclasses
import json

import numpy as np

from shed_jax.errors import UsageError

ENVS = ("lander", "lander-continuous", "walker")  # the environments with UED presets (shed_jax/presets.py)

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


def route_method_overrides(method: str, overrides: dict, base: dict | None = None) -> dict:
    """``--set`` items -> method-config overrides, on top of ``base`` (a method config dict).

    SHED and h-MDP keep the teacher reward's options (``eta``, ``form``, ... of
    ``shed_jax.teacher.reward.RewardConfig``) in their ``reward`` field: a key that is one of those
    and no field of the method's own config is set inside ``reward`` (merged with what is there),
    so ``--set eta=10`` means ``--set 'reward={"eta": 10}'``. A ``reward`` dict is merged the same
    way. Other keys replace the value in ``base``.
    """
    out = copy.deepcopy(dict(base or {}))
    cls = method_config_class(method)
    own = {f.name for f in dataclasses.fields(cls)} if cls is not None else set()
    nested = "reward" in own
    for key, value in overrides.items():
        if nested and key not in own and key in _reward_fields():
            out["reward"] = {**_as_dict(out.get("reward")), key: value}
        elif nested and key == "reward" and isinstance(value, dict):
            out["reward"] = {**_as_dict(out.get("reward")), **value}
        else:
            out[key] = value
    return out


def _as_dict(value) -> dict:
    if value is None:
        return {}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return dict(value)


def check_method_overrides(method: str, overrides: dict) -> None:
    """UsageError for a ``--set`` key the method's config does not have (naming the known ones), or a
    value of the wrong kind for its field (judged by the field's default: a number, a string, ...)."""
    cls = method_config_class(method)
    if cls is None:
        return
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        reward = f"; the teacher reward's: {', '.join(_reward_fields())}" if "reward" in fields else ""
        raise UsageError(f"--set: method {method!r} has no config field(s) {', '.join(map(repr, unknown))}; "
                         f"known: {', '.join(sorted(fields))}{reward}")
    _check_kinds(cls, overrides, "")


def _check_kinds(cls, values: dict, prefix: str) -> None:
    for f in dataclasses.fields(cls):
        if f.name not in values:
            continue
        value, default, key = values[f.name], f.default, f"{prefix}{f.name}"
        if value is None or default is None or default is dataclasses.MISSING:
            continue
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            if isinstance(value, dict):
                sub = type(default)
                known = {g.name for g in dataclasses.fields(sub)}
                unknown = sorted(set(value) - known)
                if unknown:
                    raise UsageError(f"--set {key}: {sub.__name__} has no field(s) {', '.join(map(repr, unknown))}; "
                                     f"known: {', '.join(sorted(known))}")
                _check_kinds(sub, value, f"{key}.")
            elif not isinstance(value, type(default)):
                raise UsageError(f"--set {key}: expected a JSON object of {type(default).__name__} fields, got {value!r}")
            continue
        if isinstance(default, bool):
            ok, kind = isinstance(value, bool), "true or false"
        elif isinstance(default, (int, float)):
            ok, kind = isinstance(value, (int, float)) and not isinstance(value, bool), "a number"
        elif isinstance(default, str):
            ok, kind = isinstance(value, str), "a string"
        else:
            continue
        if not ok:
            raise UsageError(f"--set {key}: expected {kind}, got {json.dumps(value, default=str)}")


def method_config_class(name: str):
    """The method's config dataclass (None for an unknown method: make_method reports it)."""
    from shed_jax.methods.registry import config_class

    return config_class(name)


def _restore_nested(cls, values: dict) -> dict:
    """Dict values of fields whose default is a config dataclass (e.g. PLR's ``sampler``) -> that class.

    A saved experiment holds nested configs as dicts (JSON); the methods want the dataclass.
    """
    if cls is None or not dataclasses.is_dataclass(cls):
        return values
    out = dict(values)
    for f in dataclasses.fields(cls):
        v = out.get(f.name)
        if isinstance(v, dict) and dataclasses.is_dataclass(f.default) and not isinstance(f.default, type):
            sub = type(f.default)
            out[f.name] = sub(**_restore_nested(sub, v))
    return out


def method_config(name: str, config: dict) -> dict:
    """An experiment's method config with nested config dicts turned back into their dataclasses."""
    return _restore_nested(method_config_class(name), dict(config))


# ---------------------------------------------------------------------------------------------
# building
# ---------------------------------------------------------------------------------------------

def check_bounds(config: dict, env) -> None:
    """ValueError unless the teacher box's ``low``/``high`` (if set) hold one number per env parameter."""
    space = env.param_space
    for key in ("low", "high"):
        value = config.get(key)
        if value is None:
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        if len(values) != space.dim or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            name = getattr(env, "name", "this environment")
            raise ValueError(f"--set {key}: expected a list of {space.dim} numbers for {name} "
                             f"({', '.join(space.names)}), got {json.dumps(value, default=str)}")


def test_levels(name: str, env):
    """The named test set's levels (a params pytree with a leading axis), from the env (``env.ued.test_sets``)."""
    from shed_jax import levels

    return levels.test_set(env, name)[0]


def build(exp):
    """Environment, student, method and test levels for an Experiment."""
    import envs
    from shed_jax.methods.registry import make_method
    from shed_jax.student import make_student

    env = envs.make(exp.env)
    check_bounds(exp.method_config, env)  # else numpy's broadcast error, far from the flag
    student = make_student(env, exp.ppo)
    method = make_method(exp.method, env, student, method_config(exp.method, exp.method_config))
    return env, student, method, test_levels(exp.test_set, env)


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
    """Seeds when --seeds is not given: paper 5, quick 2 (on any backend: the walker's CPU deadlock
    with two seeds was the batched-LAPACK one of shed_jax/xla_cpu.py, which the student init avoids)."""
    return 5 if exp.preset == "paper" else 2


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


def _tuples(x):
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    if isinstance(x, dict):
        return {k: _tuples(v) for k, v in x.items()}
    return x


def experiment_from_dict(d: dict):
    """Rebuild an Experiment from ``Experiment.to_dict()`` (as saved in config.json / a checkpoint)."""
    from shed_jax.checkpoint import CheckpointError
    from shed_jax.loop import LoopSpec
    from shed_jax.presets import Experiment
    from shed_jax.student import PPOConfig, PPOHyperparams

    try:
        ppo = dict(d["ppo"])
        hp = PPOHyperparams(**ppo.pop("hparams"))
        for k in ("actor_hidden", "critic_hidden"):
            if k in ppo:
                ppo[k] = tuple(ppo[k])
        return Experiment(
            env=d["env"], method=d["method"], preset=d["preset"], ppo=PPOConfig(**ppo, hparams=hp),
            method_config=_tuples(dict(d["method_config"])),
            # runs saved before LoopSpec.max_recorded_levels existed recorded every level
            loop=LoopSpec(**{"max_recorded_levels": None, **d["loop"]}), test_set=d["test_set"],
        )
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"cannot rebuild the experiment from the saved configuration: {type(err).__name__}: {err}") from err


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
        diffs = config_differences({"experiment": _effective(saved)}, {"experiment": _effective(current)}, ["experiment"])
    for key, given in (("seeds", args.seeds), ("root_seed", args.seed)):
        if given is not None and given != int(config[key]):
            diffs.append((key, int(config[key]), given))
    if diffs:
        raise ConfigMismatchError(f"--resume {out}: flag(s) given that differ from the saved run: "
                                  f"{describe_differences(diffs)}; drop them to continue with the saved configuration", diffs)


def _apply_resume_flags(args, exp):
    """The saved Experiment with the experiment flags of ``args`` applied (as a fresh run applies them to a preset)."""
    from shed_jax.presets import EPISODIC_METHODS

    mc = dict(exp.method_config)
    if args.set:
        mc = route_method_overrides(exp.method, parse_overrides(args.set), base=mc)
        check_method_overrides(exp.method, mc)
    changes = {}
    for flag, field in (("episodes", "num_episodes"), ("steps_per_episode", "steps_per_episode"),
                        ("test_episode_every", "test_episode_every")):
        if getattr(args, flag) is not None:
            changes[field] = getattr(args, flag)
    if args.steps_per_episode is not None and exp.method in EPISODIC_METHODS:
        mc["budget_steps"] = args.steps_per_episode
    try:
        loop = dataclasses.replace(exp.loop, **changes)
        ppo = exp.ppo.with_overrides(parse_ppo_overrides(args.ppo)) if args.ppo else exp.ppo
    except ValueError as err:
        raise UsageError(str(err)) from err
    return dataclasses.replace(exp, method_config=mc, loop=loop, ppo=ppo)


def _effective(exp) -> dict:
    """``exp.to_dict()`` with the method config as the method builds it (every field, defaults included)."""
    d = exp.to_dict()
    cls = method_config_class(exp.method)
    if cls is not None:
        try:
            d["method_config"] = dataclasses.asdict(cls(**method_config(exp.method, exp.method_config)))
        except (TypeError, ValueError) as err:
            raise UsageError(f"--set: {err}") from err
    return d
