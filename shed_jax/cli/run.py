"""``python -m shed_jax run``: one UED method on one environment, seeds vmapped, end to end.

The compiled outer loop (``shed_jax.loop``) runs in chunks of budget steps; between chunks the
host checks the chunk for non-finite values (``shed_jax.checkpoint.find_nonfinite``), writes the
per-step metrics (``metrics.jsonl``), saves a checkpoint of the whole run state
(``DIR/checkpoints/<step>``, the last ``--keep``), prints a one-line summary and updates a progress
bar. At the end it writes ``summary.json`` and plots (mean test return with standard error over
seeds against student env steps; per-test-level curves; the generated level parameters).

Every flag is checked before the run directory is made: a mistake is one line on stderr and exit
code 2 (``shed_jax/cli/errors.py``), and leaves nothing behind. The program is compiled ahead of
the first chunk (a "compiling" line, then its duration), so the progress bar's rate and ETA count
training only.

``--resume DIR`` continues a run from its latest checkpoint (or ``--from-step N``), bitwise as if it
had not stopped; ``--out DIR --restart`` starts over a run that never saved a checkpoint.
SIGINT/SIGTERM finish the current chunk, save and exit with 130/143 (during start-up: at once,
keeping nothing); ``--stop-after`` and ``--time-limit`` stop the same way with exit code 75. See
docs/running.md.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import pathlib
import shutil
import signal
import sys
import threading
import time

import numpy as np

from shed_jax.cli import errors
from shed_jax.cli import eval as eval_cli
from shed_jax.cli.errors import UsageError

ENVS = ("lander", "lander-continuous", "walker")  # the environments with UED presets (shed_jax/presets.py)

EXIT_CHECKPOINT = 2  # a checkpoint could not be used (missing, damaged, other configuration)
EXIT_NONFINITE = 3  # the non-finite guard stopped the run
EXIT_IO = errors.EXIT_IO  # a write failed (disk full, ...); the message names what is safe on disk
EXIT_STOPPED = 75  # --stop-after / --time-limit reached; resumable (EX_TEMPFAIL)

DEFAULT_ENV = "lander"
DEFAULT_METHOD = "shed"
DEFAULT_PRESET = "auto"
DEFAULT_ROOT_SEED = 0
# --final-eval when not given: the walker's named levels (DCD's six of docs/design.md §9.2 set A first) with solved rates
DEFAULT_FINAL_EVAL = {"walker": "named"}
#: what a run writes into its directory; ``--restart`` removes these (and nothing else)
RUN_FILES = ("config.json", "metrics.jsonl", "metrics.jsonl.tmp", "nonfinite_chunk.jsonl", "checkpoints")
DISCARDED_DIR = "discarded_checkpoints"  # where --from-step moves the checkpoints newer than its step


def add_arguments(p) -> None:
    from shed_jax.methods.registry import METHODS
    from shed_jax.presets import PRESETS

    count = errors.positive_int
    p.add_argument("--env", default=None, choices=ENVS, help=f"{' | '.join(ENVS)} (default {DEFAULT_ENV})")
    p.add_argument("--method", default=None, choices=METHODS,
                   help=f"shed | hmdp | dr | paired | accel | accel-norevisit | plr (default {DEFAULT_METHOD})")
    p.add_argument("--preset", default=None, choices=("auto",) + PRESETS,
                   help="auto (default): 'paper' on a GPU, 'quick' on a CPU (the choice is printed)")
    p.add_argument("--seeds", type=count, default=None, help="number of vmapped seeds (default: quick 2, paper 5; the walker on a CPU 1)")
    p.add_argument("--seed", type=int, default=None,
                   help=f"root seed (default {DEFAULT_ROOT_SEED}); seed i of the batch uses fold_in(root, i)")
    p.add_argument("--episodes", type=count, default=None, help="override the number of teacher episodes N_ep")
    p.add_argument("--steps-per-episode", type=count, default=None, help="override the budget steps per episode T")
    p.add_argument("--test-episode-every", type=count, default=None, metavar="K",
                   help="run the test set only in teacher episodes 0, K, 2K, ... and the last "
                        "(default: paper preset 10 for shed/hmdp, else 1 = every episode)")
    p.add_argument("--chunk", type=count, default=None,
                   help="budget steps per compiled call, i.e. between checkpoints (default: T)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the method's config (repeatable), e.g. --set num_eval_levels=20; "
                        "SHED/h-MDP: a field of the teacher reward goes into its 'reward' config, e.g. --set eta=10 "
                        "or --set form=signed_sum")
    p.add_argument("--ppo", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the student's PPOConfig or PPOHyperparams (repeatable), "
                        "e.g. --ppo num_envs=8 --ppo num_steps=640")
    p.add_argument("--out", default=None, help="run directory (default runs/<env>-<method>-<preset>-<time>)")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF of the final student")
    p.add_argument("--final-eval", default=None, metavar="LEVELS",
                   help="after the last budget step, evaluate the final students on level sets as `eval --levels` "
                        "does (test | named | FILE.json, comma-separated, or none) and write final_eval_<set>.json; "
                        f"default: {', '.join(f'{e} {v}' for e, v in DEFAULT_FINAL_EVAL.items())}, other envs none")
    p.add_argument("--final-eval-episodes", type=count, default=10, metavar="N",
                   help="episodes per level and seed of --final-eval (default 10); the episode cap is the test set's")
    g = p.add_argument_group("checkpoints and stopping")
    g.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the run in DIR from its latest checkpoint (its saved configuration is used; "
                        "experiment flags given as well must agree with it)")
    g.add_argument("--from-step", type=count, default=None, metavar="N",
                   help="with --resume: continue from checkpoint N instead of the latest (e.g. when the latest is "
                        f"damaged); the newer ones are moved to DIR/{DISCARDED_DIR}/")
    g.add_argument("--restart", action="store_true",
                   help="with --out DIR: clear a run in DIR that stopped before its first checkpoint and start it "
                        "over (refused when DIR holds a checkpoint or a finished run)")
    g.add_argument("--keep", type=count, default=3, metavar="K", help="keep the last K checkpoints (default 3)")
    g.add_argument("--no-checkpoint", action="store_true", help="do not save checkpoints (the run cannot be resumed)")
    g.add_argument("--stop-after", type=count, default=None, metavar="STEPS",
                   help="stop at the first chunk boundary at or after this many budget steps, save, exit 75")
    g.add_argument("--time-limit", type=errors.non_negative_float, default=None, metavar="SECONDS",
                   help="stop at the first chunk boundary after this much wall time in this process, save, exit 75")


def _parse_overrides(items: list[str]) -> dict:
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
    cls = _method_config_class(method)
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
    cls = _method_config_class(method)
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
    from shed_jax import levels

    return levels.test_set(env, name)[0]  # the env's own test set (env.ued.test_sets)


def _method_config_class(name: str):
    """The method's config dataclass (None for an unknown method: make_method reports it)."""
    if name in ("shed", "hmdp"):
        from shed_jax.methods.registry import config_class

        return config_class(name)
    import importlib

    from shed_jax.methods import registry

    entry = registry._BASELINES.get(name)  # no public accessor yet
    return None if entry is None else getattr(importlib.import_module(entry[0]), entry[2])


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
    return _restore_nested(_method_config_class(name), dict(config))


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
    """The Experiment the command line asks for (``--preset auto`` resolved for ``backend``, and said).

    Bad values (an unknown ``--set``/``--ppo`` field, a value a config refuses) raise UsageError.
    """
    from shed_jax.presets import build_experiment

    preset = resolve_preset(args.preset, backend)
    method = args.method or DEFAULT_METHOD
    overrides = route_method_overrides(method, _parse_overrides(args.set))
    check_method_overrides(method, overrides)
    try:
        return build_experiment(args.env or DEFAULT_ENV, method, preset, episodes=args.episodes,
                                steps_per_episode=args.steps_per_episode, test_episode_every=args.test_episode_every,
                                method_overrides=overrides, ppo_overrides=_parse_ppo(args.ppo))
    except ValueError as err:
        raise UsageError(str(err)) from err


def _parse_ppo(items: list[str]) -> dict:
    from shed_jax.student.config import parse_overrides

    try:
        return parse_overrides(items)
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


def final_eval_specs(arg: str | None, env: str) -> list[str]:
    """``--final-eval`` -> the level-set specs to evaluate after the run (``eval --levels`` values)."""
    text = DEFAULT_FINAL_EVAL.get(env, "none") if arg is None else arg
    specs = [t.strip() for t in text.split(",") if t.strip()]
    if "none" in specs:
        if len(specs) > 1:
            raise UsageError(f"--final-eval: 'none' cannot be combined with level sets, got {arg!r}")
        return []
    if len(set(specs)) != len(specs):
        raise UsageError(f"--final-eval names a level set twice: {arg!r}")
    return specs


def default_seeds(exp) -> int:
    """Seeds when --seeds is not given: paper 5, quick 2 (on any backend: the walker's CPU deadlock
    with two seeds was the batched-LAPACK one of shed_jax/xla_cpu.py, which the student init avoids)."""
    return 5 if exp.preset == "paper" else 2


def seed_keys(root_seed: int, num_seeds: int):
    import jax

    root = jax.random.PRNGKey(root_seed)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(np.arange(num_seeds))


class StartupInterrupted(Exception):
    """SIGINT/SIGTERM before the first chunk ran: the run stops at once (nothing to save yet)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopRequest:
    """SIGINT/SIGTERM set ``signum``; the loop finishes its chunk, saves and exits 128 + signum.

    While ``startup`` is true (validation, building, compiling: before the first chunk runs) a
    signal raises :class:`StartupInterrupted` in the main thread instead; the compile runs in a
    worker thread meanwhile (``_in_worker``), so this happens at once. A second signal aborts at
    once (the last complete checkpoint stays). Handlers are installed only in the main thread and
    restored on exit.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum: int | None = None
        self.startup = True
        self._previous: dict = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()
        return False

    def _handle(self, signum, frame):
        if self.signum is not None:
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise SystemExit(128 + signum)
        self.signum = signum
        if self.startup:
            raise StartupInterrupted(signum)
        print(f"\n[shed_jax] {signal.Signals(signum).name}: finishing the current chunk, then saving "
              f"(send it again to stop at once without saving)", file=sys.stderr, flush=True)

    def poll(self) -> int | None:
        """The signal received so far (checked once per chunk)."""
        return self.signum


def reconcile_metrics_jsonl(path: pathlib.Path, hist: dict, step: int, num_seeds: int) -> str:
    """Make ``metrics.jsonl`` hold exactly the records of budget steps ``< step`` (a checkpoint's).

    Records at or beyond ``step`` (written before a crash that came before the checkpoint) and a
    final line cut by a kill are dropped; earlier lines are kept byte for byte. If records before
    ``step`` are missing or duplicated, the file is copied to ``metrics.jsonl.bak-<step>`` and
    rewritten from the checkpoint's metrics history. Returns a one-line note.
    """
    from shed_jax import reporting
    from shed_jax.checkpoint import CheckpointCorruptError

    expected = {(s, t) for t in range(step) for s in range(num_seeds)}
    lines = path.read_text().splitlines(keepends=True) if path.exists() else []
    kept, seen, dropped, dup = [], set(), 0, False
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError as err:
            if i == len(lines) - 1:  # the last line, cut by a kill
                dropped += 1
                continue
            raise CheckpointCorruptError(f"{path}: line {i + 1} is not JSON ({err}); repair or remove it") from err
        key = (rec.get("seed"), rec.get("step"))
        if not isinstance(key[1], int) or key[1] >= step:
            dropped += 1
            continue
        dup |= key in seen
        seen.add(key)
        kept.append(line if line.endswith("\n") else line + "\n")
    tmp = path.with_name(path.name + ".tmp")
    if seen == expected and not dup:
        tmp.write_text("".join(kept))
        os.replace(tmp, path)
        return f"metrics.jsonl: kept {len(kept)} record(s) before step {step}, dropped {dropped} after it"
    backup = path.with_name(f"{path.name}.bak-{step}") if path.exists() else None
    if backup is not None:
        shutil.copyfile(path, backup)
    flat = {k: np.asarray(v)[:, :step] for k, v in hist.items()}
    with open(tmp, "w") as f:
        for r in reporting.step_records(flat, range(num_seeds)):
            f.write(json.dumps(r) + "\n")
    os.replace(tmp, path)
    return (f"metrics.jsonl did not hold exactly the records of steps < {step} "
            f"({len(seen & expected)}/{len(expected)} present{', duplicates' if dup else ''}); "
            f"rewrote it from the checkpoint's history "
            f"({f'old file kept as {backup.name}' if backup is not None else 'there was no metrics.jsonl'})")


def _experiment_flags_given(args) -> bool:
    return any(getattr(args, k) is not None for k in ("env", "method", "preset", "episodes", "steps_per_episode",
                                                  "test_episode_every")) or bool(args.set) or bool(args.ppo)


def _resume_command(out: pathlib.Path) -> str:
    return f"python -m shed_jax run --resume {out}"


def main(args) -> int:
    from shed_jax.checkpoint import CheckpointError

    try:
        return _main(args)
    except CheckpointError as err:
        errors.report(err, args)
        return EXIT_CHECKPOINT


@dataclasses.dataclass
class _Plan:
    """What a run will do, decided (and every input checked) before anything is written."""

    out: pathlib.Path
    exp: object  # presets.Experiment
    num_seeds: int
    root_seed: int
    chunk: int
    config: dict  # the run configuration (config.json; saved in every checkpoint)
    resume_step: int | None = None  # the checkpoint a resumed run continues from
    complete: tuple = ()  # a resumed run's complete checkpoints
    damaged: Exception | None = None  # why ``resume_step`` cannot be used (found before building), if so
    newer: tuple = ()  # step directories newer than ``resume_step`` (--from-step moves them away)
    clear: bool = False  # --restart: remove the run files in ``out`` first
    finished: bool = False  # a resumed run that already wrote its summary: nothing to do once its checkpoint reads back


#: the counts argparse checks (``errors.positive_int``); checked again for callers that build ``args`` themselves
_COUNTS = ("seeds", "episodes", "steps_per_episode", "test_episode_every", "chunk", "keep", "final_eval_episodes",
           "stop_after", "from_step")


def _check_flags(args) -> None:
    for name in _COUNTS:
        value = getattr(args, name, None)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise UsageError(f"--{name.replace('_', '-')} must be an integer >= 1, got {value!r}")
    if args.time_limit is not None and not 0 <= args.time_limit < math.inf:
        raise UsageError(f"--time-limit must be a finite number of seconds >= 0, got {args.time_limit!r}")
    if getattr(args, "from_step", None) is not None and not args.resume:
        raise UsageError("--from-step N chooses the checkpoint that --resume DIR continues from; give --resume DIR as well")
    if getattr(args, "restart", False):
        if args.resume:
            raise UsageError("--restart starts the run in --out DIR over, --resume DIR continues it: give one of them")
        if args.out is None:
            raise UsageError("--restart clears the run directory given with --out DIR: give --out")


def _plan_fresh(args, backend: str) -> _Plan:
    import jax

    exp = experiment_from_args(args, backend)
    num_seeds = args.seeds or default_seeds(exp)
    root_seed = DEFAULT_ROOT_SEED if args.seed is None else args.seed
    out = pathlib.Path(args.out or f"runs/{exp.env}-{exp.method}-{exp.preset}-{time.strftime('%Y%m%d-%H%M%S')}")
    clear = _check_out(out, getattr(args, "restart", False))
    from shed_jax.presets import default_chunk

    chunk = args.chunk or default_chunk(exp)
    config = {"experiment": exp.to_dict(), "seeds": num_seeds, "root_seed": root_seed, "backend": backend,
              "devices": [str(d) for d in jax.devices()], "chunk": chunk, "jax": jax.__version__}
    return _Plan(out, exp, num_seeds, root_seed, chunk, config, clear=clear)


def _check_out(out: pathlib.Path, restart: bool) -> bool:
    """UsageError unless a fresh run may write to ``out``; True if ``--restart`` must clear it first."""
    from shed_jax.checkpoint import CheckpointError, complete_steps

    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file, not a directory; choose another --out")
    held = [name for name in ("metrics.jsonl", "checkpoints", "summary.json") if (out / name).exists()]
    if not held:
        return restart and out.exists()  # nothing of a run (a config.json alone is overwritten)
    try:
        steps = complete_steps(out)
    except CheckpointError:
        steps = []
    if steps:
        raise UsageError(f"{out} already holds a run with checkpoint(s) at budget step(s) {', '.join(map(str, steps))}; "
                         f"continue it with --resume {out} (--from-step N for an older checkpoint) or choose another --out"
                         + ("; --restart only clears a run that saved no checkpoint" if restart else ""))
    if (out / "summary.json").exists():
        raise UsageError(f"{out} already holds a finished run (summary.json); choose another --out")
    if not restart:
        raise UsageError(f"{out} already holds a run that stopped before its first checkpoint ({', '.join(held)}); "
                         f"start it over with --restart (which clears it) or choose another --out")
    return True


def _clear_run(out: pathlib.Path) -> list[str]:
    """--restart: remove the files a run writes (``RUN_FILES``, metrics backups) from ``out``; returns their names."""
    removed = []
    for path in sorted(out.iterdir()):
        if path.name in RUN_FILES or path.name.startswith("metrics.jsonl.bak-"):
            removed.append(path.name + ("/" if path.is_dir() else ""))
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    return removed


def _plan_resume(args, backend: str) -> _Plan:
    """The plan of ``--resume DIR``."""
    from shed_jax.checkpoint import (COMPARED_KEYS, CheckpointCorruptError, CheckpointNotFoundError, RunCheckpointer,
                                     check_config, complete_steps)

    out = pathlib.Path(args.resume)
    from_step = getattr(args, "from_step", None)
    if args.out is not None and pathlib.Path(args.out).resolve() != out.resolve():
        raise UsageError(f"--resume continues the run in its own directory {out}; drop --out {args.out}")
    if not out.is_dir():
        raise CheckpointNotFoundError(f"--resume {out}: " + ("not a directory" if out.exists() else f"no run directory {out}"))
    complete = complete_steps(out)
    ck_dir = out / "checkpoints"
    on_disk = sorted(int(p.name) for p in ck_dir.iterdir() if p.is_dir() and p.name.isdigit()) if ck_dir.is_dir() else []
    if not complete and not on_disk:
        raise CheckpointNotFoundError(
            f"{out} holds no complete checkpoint: the run stopped before its first one was saved, or ran with "
            f"--no-checkpoint; start it over with: python -m shed_jax run --out {out} --restart (and its flags)")
    if from_step is not None:
        if from_step not in complete:
            raise CheckpointNotFoundError(f"--from-step {from_step}: {ck_dir} has no complete checkpoint "
                                          f"{from_step}; complete: {', '.join(map(str, complete)) or 'none'}")
        step = from_step
    else:
        step = max(complete + on_disk)
    damaged = None
    with RunCheckpointer(out, create=False) as reader:
        try:
            if step not in complete:
                raise CheckpointCorruptError(f"checkpoint {ck_dir / str(step)} is damaged (not a complete checkpoint)")
            config = reader.read_config(step)
        except CheckpointCorruptError as err:
            damaged, config = err, _readable_config(reader, out, [s for s in complete if s < step])
            if config is None:
                raise CheckpointCorruptError(f"{err}; no older checkpoint and no config.json is readable: "
                                             f"delete {out} to start over") from err
    cfg_file = out / "config.json"
    if damaged is None and cfg_file.exists():
        check_config(config, json.loads(cfg_file.read_text()), COMPARED_KEYS, where=f"checkpoint (vs {cfg_file})")
    exp = experiment_from_dict(config["experiment"])
    _check_resume_flags(args, config, exp, backend, out)
    num_seeds, root_seed = int(config["seeds"]), int(config["root_seed"])
    chunk = args.chunk or int(config.get("chunk") or exp.loop.steps_per_episode)
    total = exp.loop.total_steps
    if step > total:
        raise CheckpointNotFoundError(f"checkpoint step {step} is beyond the run's {total} budget steps")
    finished = damaged is None and from_step is None and step == total and (out / "summary.json").exists()
    return _Plan(out, exp, num_seeds, root_seed, chunk, config, resume_step=step, complete=tuple(complete),
                 damaged=damaged, newer=tuple(s for s in on_disk if s > step), finished=finished)


def _readable_config(reader, out: pathlib.Path, older: list[int]) -> dict | None:
    """A run configuration to check older checkpoints with: config.json's, else the newest readable checkpoint's."""
    from shed_jax.checkpoint import CheckpointError

    cfg_file = out / "config.json"
    try:
        return json.loads(cfg_file.read_text())
    except (OSError, ValueError):
        pass
    for s in sorted(older, reverse=True):
        try:
            return reader.read_config(s)
        except CheckpointError:
            continue
    return None


def _check_resume_flags(args, config: dict, saved, backend: str, out: pathlib.Path) -> None:
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
        mc = route_method_overrides(exp.method, _parse_overrides(args.set), base=mc)
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
        ppo = exp.ppo.with_overrides(_parse_ppo(args.ppo)) if args.ppo else exp.ppo
    except ValueError as err:
        raise UsageError(str(err)) from err
    return dataclasses.replace(exp, method_config=mc, loop=loop, ppo=ppo)


def _effective(exp) -> dict:
    """``exp.to_dict()`` with the method config as the method builds it (every field, defaults included)."""
    d = exp.to_dict()
    cls = _method_config_class(exp.method)
    if cls is not None:
        try:
            d["method_config"] = dataclasses.asdict(cls(**method_config(exp.method, exp.method_config)))
        except (TypeError, ValueError) as err:
            raise UsageError(f"--set: {err}") from err
    return d


def _build_checked(exp, fresh: bool):
    """``build(exp)``; a value the configs refuse is a UsageError (fresh run) or a CheckpointError (saved run)."""
    from shed_jax.checkpoint import CheckpointError

    try:
        return build(exp)
    except (ValueError, TypeError) as err:
        if not fresh:
            raise CheckpointError(f"the saved configuration cannot be built: {errors.one_line(str(err), 300)}") from err
        hint = " (a --set/--ppo value of the wrong type?)" if isinstance(err, TypeError) else ""
        raise UsageError(f"{err}{hint}") from err


def _final_sets(args, exp, env, tests) -> list:
    try:
        return [eval_cli.resolve_levels(spec, env, exp, tests) for spec in final_eval_specs(args.final_eval, exp.env)]
    except eval_cli.LevelFileError as err:
        raise UsageError(f"--final-eval: {err}") from err


def _restore(plan: _Plan, target):
    """Restore ``plan.resume_step``; a damaged checkpoint is one CheckpointCorruptError listing the intact older ones."""
    from shed_jax.checkpoint import CheckpointCorruptError, RunCheckpointer

    with RunCheckpointer(plan.out, create=False) as reader:
        err = plan.damaged
        if err is None:
            try:
                return reader.restore(target, step=plan.resume_step)
            except CheckpointCorruptError as e:
                err = e
        intact = [s for s in sorted(plan.complete, reverse=True) if s < plan.resume_step and reader.verify(target, s) is None]
    if intact:
        hint = (f"intact older checkpoint(s): {', '.join(map(str, intact))}; continue from the newest with: "
                f"{_resume_command(plan.out)} --from-step {intact[0]}")
    else:
        hint = f"no older checkpoint is intact; delete {plan.out} to start over"
    raise CheckpointCorruptError(f"{err}; {hint}") from err


def _discard_newer(plan: _Plan) -> None:
    """--from-step N: move the step directories newer than N out of ``checkpoints/`` (kept, not deleted)."""
    if not plan.newer:
        return
    dest = plan.out / DISCARDED_DIR
    dest.mkdir(exist_ok=True)
    for s in plan.newer:
        target = dest / str(s)
        k = 1
        while target.exists():
            target, k = dest / f"{s}-{k}", k + 1
        shutil.move(str(plan.out / "checkpoints" / str(s)), str(target))
    print(f"[shed_jax] --from-step {plan.resume_step}: moved checkpoint(s) {', '.join(map(str, plan.newer))} "
          f"to {dest} (delete them when no longer needed)")


def _create_run_dir(plan: _Plan, made: list) -> None:
    """Clear (--restart), make ``out`` and write config.json; ``made`` collects what is new (removed if start-up is cut)."""
    out = plan.out
    if plan.clear:
        removed = _clear_run(out)
        print(f"[shed_jax] --restart: removed {', '.join(removed) or 'nothing'} from {out}")
    try:
        if not out.exists():
            out.mkdir(parents=True)
            made.append(out)
        (out / "config.json").write_text(json.dumps(plan.config, indent=2, default=str))
    except OSError as err:
        raise UsageError(f"--out {out}: cannot write there ({err.strerror or err})") from err
    made.append(out / "config.json")


def _remove_made(made: list) -> str:
    """Undo ``_create_run_dir``: remove config.json and the directory if this process made it (and it is empty)."""
    removed = []
    for path in reversed(made):
        try:
            if path.is_dir():
                path.rmdir()
            else:
                path.unlink()
            removed.append(str(path))
        except OSError:
            pass
    return ", ".join(removed)


def _in_worker(fn, name: str = "compile", heartbeat: float | None = None, what: str = "compiling"):
    """``fn()`` in a worker thread while the main thread waits, so that SIGINT/SIGTERM are handled at
    once (a compile inside XLA would hold off the Python handlers until it returns). With
    ``heartbeat`` (seconds), a "still <what>" line every so often, so the run is never silent longer."""
    box: dict = {}

    def work():
        try:
            box["value"] = fn()
        except BaseException as err:  # noqa: BLE001 - re-raised in the main thread
            box["error"] = err

    worker = threading.Thread(target=work, name=f"shed_jax-{name}", daemon=True)
    worker.start()
    start = time.time()
    beat = start + heartbeat if heartbeat else float("inf")
    while worker.is_alive():
        worker.join(0.1)
        if time.time() >= beat and worker.is_alive():
            print(f"[shed_jax] still {what} ({time.time() - start:.0f} s)...", flush=True)
            beat += heartbeat
    if "error" in box:
        raise box["error"]
    return box["value"]


def chunk_sizes(chunk: int, done: int, total: int) -> list[int]:
    """The distinct chunk lengths a run from ``done`` to ``total`` calls: full chunks, then a shorter last one."""
    left = total - done
    if left <= 0:
        return []
    sizes = [min(chunk, left)]
    if left > chunk and left % chunk:
        sizes.append(left % chunk)
    return sizes


def _startup_interrupted(signum: int, plan: _Plan | None, made: list) -> int:
    name = signal.Signals(signum).name
    if plan is not None and plan.resume_step is not None:
        what = f"continue it with: {_resume_command(plan.out)}"
    else:
        removed = _remove_made(made)
        what = f"nothing was kept (removed {removed})" if removed else "nothing was written"
    print(f"[shed_jax] {name} during start-up, before the first budget step: stopped; {what}", file=sys.stderr, flush=True)
    return 128 + signum


def _write_failed(err: BaseException, stage: str, out: pathlib.Path, saved: int | None, checkpointing: bool, args) -> int:
    """A failed write (disk full, ...): one line naming the stage and what is safe on disk; exit 74."""
    if saved is not None:
        safe = (f"safe on disk: checkpoint {saved} in {out / 'checkpoints'} (and metrics.jsonl up to it); "
                f"after freeing space continue with: {_resume_command(out)}")
    elif checkpointing:
        safe = f"no checkpoint was saved yet; after freeing space start over with: python -m shed_jax run --out {out} --restart ..."
    else:
        safe = "nothing resumable (--no-checkpoint)"
    if errors.debug_enabled(args):
        import traceback

        traceback.print_exception(err, file=sys.stderr)
    print(f"{errors.PREFIX} {errors.io_reason(err)} while {stage}; {safe}", file=sys.stderr, flush=True)
    return EXIT_IO


def _is_write_failure(err: BaseException) -> bool:
    return errors.os_error_in(err) is not None or errors.is_disk_full(err)


def _close_quietly(ckpt) -> None:
    try:
        ckpt.close()
    except Exception:  # noqa: BLE001 - the save that failed was reported already
        pass


def _main(args) -> int:
    import jax

    _check_flags(args)
    backend = jax.default_backend()
    plan: _Plan | None = None
    made: list = []  # what this process created before the first chunk (removed if start-up is interrupted)
    with StopRequest() as stop:
        try:
            plan = _plan_resume(args, backend) if args.resume else _plan_fresh(args, backend)
            started = _start(args, plan, made)
            if started is None:
                return 0
        except StartupInterrupted as sig:
            return _startup_interrupted(sig.signum, plan, made)
        stop.startup = False
        return _train_and_report(args, plan, started, stop)


def _start(args, plan: _Plan, made: list) -> dict | None:
    """Everything before the first chunk: build (checked), restore or create the run directory, compile.

    None for a finished run (said): its checkpoint is read back to check it, nothing is written.
    """
    import jax

    exp, out = plan.exp, plan.out
    fresh = plan.resume_step is None
    env, student, method, tests = _build_checked(exp, fresh)
    final_sets = _final_sets(args, exp, env, tests)
    from shed_jax.loop import make_run

    init, run = make_run(student, method, tests, exp.loop)
    total = exp.loop.total_steps
    keys = seed_keys(plan.root_seed, plan.num_seeds)
    metrics_path = out / "metrics.jsonl"
    state, hist, previous_wall, done = None, {}, 0.0, 0
    if not fresh:
        restored = _restore(plan, jax.eval_shape(jax.vmap(init), keys))
        state, done, hist = restored.state, restored.step, restored.history
        previous_wall = float(restored.extra.get("wall_time_s", 0.0))
        if plan.finished:
            print(f"[shed_jax] {out} holds a finished run (budget step {done}/{total}, summary.json written, the last "
                  f"checkpoint intact): nothing to do; `python -m shed_jax eval --run {out}` evaluates its students")
            return None
        _discard_newer(plan)
        print(f"[shed_jax] resuming {out} from budget step {done}/{total}")
        print(f"[shed_jax] {reconcile_metrics_jsonl(metrics_path, hist, done, plan.num_seeds)}")
    else:
        _create_run_dir(plan, made)
    print(f"[shed_jax] {exp.method} on {exp.env}: {exp.loop.num_episodes} episode(s) x {exp.loop.steps_per_episode} "
          f"budget steps, {plan.num_seeds} seed(s), ~{exp.env_steps_per_budget_step:,} student env steps per budget step -> {out}")
    t0 = time.time()  # this session's wall clock, compile included (summary.json's wall_time_s)
    run_chunk = jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)
    sizes = chunk_sizes(plan.chunk, done, total)
    compiled = {}
    if sizes or fresh:
        chunks = (f"a chunk of {sizes[0]} budget step(s)" if len(sizes) == 1 else
                  f"chunks of {sizes[0]} and {sizes[1]} budget steps" if sizes else "")
        what = " and ".join(x for x in ("the initial state" if fresh else "", chunks) if x)
        print(f"[shed_jax] compiling {what} (minutes for a large program on a CPU)...", flush=True)

        def compile_all(state):
            if state is None:
                state = jax.jit(jax.vmap(init))(keys)
            return state, {n: run_chunk.lower(state, n, done).compile() for n in sizes}

        state, compiled = _in_worker(lambda: compile_all(state), heartbeat=45.0)
        print(f"[shed_jax] compiled in {time.time() - t0:.1f} s", flush=True)
    return dict(env=env, student=student, tests=tests, final_sets=final_sets, state=state, hist=hist, done=done,
                previous_wall=previous_wall, t0=t0, compiled=compiled, metrics_path=metrics_path)


def _train_and_report(args, plan: _Plan, s: dict, stop) -> int:
    """The chunks (checked, written, saved), then the summary, plots, final evaluation and GIF."""
    import jax
    from tqdm import tqdm

    from shed_jax import reporting
    from shed_jax.checkpoint import RunCheckpointer, find_nonfinite

    exp, out, num_seeds = plan.exp, plan.out, plan.num_seeds
    env, student, tests, state, hist, done = s["env"], s["student"], s["tests"], s["state"], s["hist"], s["done"]
    previous_wall, t0, compiled, metrics_path = s["previous_wall"], s["t0"], s["compiled"], s["metrics_path"]
    total = exp.loop.total_steps
    config = plan.config
    saved = plan.resume_step  # the last checkpoint known to be complete on disk
    stage = "opening the checkpoint directory"
    ckpt = None
    stopped = None  # (exit code, reason)
    failed = None  # a write that failed: (error, stage)
    bar = None
    try:
        if not args.no_checkpoint:
            ckpt = RunCheckpointer(out, keep=args.keep, create=True)
        # created after the compile, so that its rate and ETA count training only
        bar = tqdm(total=total, initial=done, unit="step", desc=f"{exp.method}/{exp.env}", dynamic_ncols=True)
        while done < total:
            n = min(plan.chunk, total - done)
            new_state, metrics = compiled[n](state, done)
            flat = reporting.flatten_tree(jax.device_get(metrics))
            problems = find_nonfinite(flat, new_state, done, exp.loop.tests_at)
            if problems:
                stage = "writing nonfinite_chunk.jsonl"
                bad = out / "nonfinite_chunk.jsonl"
                bad.unlink(missing_ok=True)
                reporting.append_jsonl(bad, reporting.step_records(flat, range(num_seeds)))
                bar.close()
                if ckpt is not None:
                    ckpt.wait()  # the previous chunk's save may still be in flight
                last = ckpt.latest_step() if ckpt is not None else None
                print(f"[shed_jax] non-finite values in budget steps {done}-{done + n - 1}; stopping without saving this chunk:",
                      file=sys.stderr)
                for line in problems:
                    print(f"  {line}", file=sys.stderr)
                print(f"[shed_jax] this chunk's metrics: {bad}; "
                      + (f"the last good checkpoint is step {last} in {ckpt.directory}" if last is not None else "no checkpoint was saved"),
                      file=sys.stderr)
                return EXIT_NONFINITE
            state = new_state
            hist = flat if not hist else {k: np.concatenate([hist[k], v], axis=1) for k, v in flat.items()}
            stage = f"writing the records of budget steps {done}-{done + n - 1} to {metrics_path}"
            reporting.append_jsonl(metrics_path, reporting.step_records(flat, range(num_seeds)))
            done += n
            if ckpt is not None:
                stage = f"saving checkpoint {done} in {ckpt.directory}"
                ckpt.save(done, state, hist, config, extra={"wall_time_s": previous_wall + time.time() - t0})
                ckpt.wait()  # a failed write is reported now, at this chunk, not at the next save
                saved = done
            bar.update(n)
            steps_train = hist["info/env_steps_train"].astype(np.float64).sum(axis=1).mean()
            tr = flat["test_return"][:, -1]
            teacher_r = np.nanmean(flat["info/teacher_reward"]) if np.any(np.isfinite(flat["info/teacher_reward"])) else math.nan
            # the test set runs only in some teacher episodes (--test-episode-every): say so, not "nan"
            test = (f"test return {np.nanmean(tr):8.1f} ± {reporting.mean_se(tr)[1]:.1f}" if np.any(np.isfinite(tr))
                    else "test return  (not run in this episode)")
            bar.write(f"step {done:5d}/{total}  episode {int(flat['episode'][0, -1])}  student env steps/seed {steps_train:,.0f}  "
                      f"{test}  teacher reward {teacher_r:8.3f}  "
                      f"{steps_train * num_seeds / max(time.time() - t0 + previous_wall, 1e-9):,.0f} train steps/s")
            if done >= total:
                break
            if stop.poll() is not None:
                stopped = (128 + stop.signum, f"interrupted by {signal.Signals(stop.signum).name}")
            elif args.stop_after is not None and done >= args.stop_after:
                stopped = (EXIT_STOPPED, f"--stop-after {args.stop_after} reached")
            elif args.time_limit is not None and time.time() - t0 >= args.time_limit:
                stopped = (EXIT_STOPPED, f"--time-limit {args.time_limit:g}s reached")
            if stopped:
                break
    except Exception as err:  # noqa: BLE001 - only failed writes are handled; anything else is re-raised
        if not _is_write_failure(err):
            raise
        failed = (err, stage)
    finally:
        if bar is not None:
            bar.close()
        if ckpt is not None:
            if failed is None:
                ckpt.close()
            else:
                _close_quietly(ckpt)
    if failed is not None:
        return _write_failed(failed[0], failed[1], out, saved, ckpt is not None, args)
    if stopped is not None:
        code, reason = stopped
        print(f"[shed_jax] {reason}: stopped at budget step {done}/{total}")
        if ckpt is not None:
            print(f"[shed_jax] checkpoint saved in {ckpt.directory / str(done)}; resume with:\n  {_resume_command(out)}")
        else:
            print("[shed_jax] no checkpoint was written (--no-checkpoint): this run cannot be resumed")
        return code

    wall = previous_wall + time.time() - t0
    stage = "writing the plots"
    try:
        print(f"[shed_jax] training done ({done}/{total} budget steps); writing the plots and summary.json...", flush=True)
        summary = summarize(exp, hist, wall, num_seeds)
        make_plots(exp, env, hist, out)
        for resolved in s["final_sets"]:
            stage = f"writing the final evaluation on {resolved[2]!r}"
            final_eval(exp, env, student, state.student, num_seeds, resolved, out, done, args.final_eval_episodes)
        # written after the plots and evaluations: a run with summary.json is finished (--resume leaves
        # it alone), one without it gets them all again from --resume
        stage = "writing summary.json"
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        if not args.no_gif:
            stage = "writing final_student.gif"
            _gif(env, student, state, tests, out)
    except Exception as err:  # noqa: BLE001 - as above
        if not _is_write_failure(err):
            raise
        return _write_failed(err, stage, out, saved, not args.no_checkpoint, args)
    print(json.dumps({k: summary[k] for k in ("final_test_return_mean", "final_test_return_se", "wall_time_s")}, indent=2))
    print(f"[shed_jax] results in {out}")
    return 0


def _gif(env, student, state, tests, out: pathlib.Path) -> None:
    print("[shed_jax] rendering a GIF of seed 0's final student on a test level...", flush=True)
    try:
        from shed_jax.visualize import student_gif

        path = student_gif(env, student, state, tests, out / "final_student.gif")
        print(f"[shed_jax] wrote {path}")
    except ImportError as err:  # the visualisation module is optional
        print(f"[shed_jax] no GIF: shed_jax.visualize is not available ({err})")
    except NotImplementedError as err:  # an env without a renderer
        print(f"[shed_jax] no GIF: {err}")
    except OSError as err:
        if errors.is_disk_full(err):
            raise  # reported by the caller with what is safe on disk
        print(f"[shed_jax] no GIF: {type(err).__name__}: {err}")
    except Exception as err:  # noqa: BLE001 - the results are written; a GIF failure must not fail the run
        print(f"[shed_jax] no GIF: {type(err).__name__}: {err}")


def final_eval(exp, env, student, student_state, num_seeds: int, resolved, out: pathlib.Path, step: int,
               episodes: int) -> None:
    """Evaluate the final students on one level set (as ``eval`` does) and write final_eval_<set>.json.

    The episode cap is the test set's (``LoopSpec.test_max_steps``). The run's results are already
    written, so a failure here is reported and does not fail the run. The JSON's ``wall_time_s`` is
    the evaluation's own time, compile included; the run's ``summary.json`` wall time stops before it.
    """
    t0 = time.time()
    levels = len(resolved[1])
    print(f"[shed_jax] final evaluation on {resolved[2]!r}: {levels} level(s) x {num_seeds} seed(s) x {episodes} "
          f"episode(s) (compiling first)...", flush=True)
    try:
        body, text = eval_cli.evaluate_students(exp, env, student, student_state, num_seeds, resolved,
                                                episodes=episodes, max_steps=exp.loop.test_max_steps)
    except Exception as err:  # noqa: BLE001 - see the docstring
        print(f"[shed_jax] final evaluation on {resolved[2]!r} failed: {type(err).__name__}: {err}", file=sys.stderr)
        return
    path = out / f"final_eval_{body['levels']}.json"
    path.write_text(json.dumps({"run": str(out), "budget_step": step, "wall_time_s": time.time() - t0, **body},
                               indent=2))
    solved = f"solved: return > {body['solved_threshold']:g}" if body["solved_threshold"] is not None else "no solved threshold"
    print(f"[shed_jax] final students on {body['levels']!r} ({num_seeds} seed(s) x {episodes} episode(s) per level, {solved}):")
    print(text)
    print(f"[shed_jax] wrote {path}")


def summarize(exp, hist: dict, wall: float, num_seeds: int) -> dict:
    from shed_jax import reporting

    T = exp.loop.steps_per_episode
    last = hist["test_return"][:, -1]
    m, se = reporting.mean_se(last)
    last_ep = hist["episode"][0] == hist["episode"][0, -1]
    train_steps = hist["info/env_steps_train"].astype(np.float64)
    return {
        "env": exp.env, "method": exp.method, "preset": exp.preset, "seeds": num_seeds,
        "budget_steps": int(hist["step"].shape[1]), "steps_per_episode": T,
        "final_test_return_mean": float(m), "final_test_return_se": float(se),
        "final_test_return_per_seed": [float(x) for x in last],
        "final_test_return_per_level": [float(x) for x in np.nanmean(hist["test_return_per_level"][:, -1], axis=0)],
        "student_env_steps_last_episode": float(train_steps[:, last_ep].sum(axis=1).mean()),
        "student_env_steps_total": float(train_steps.sum(axis=1).mean()),
        "eval_env_steps_total": float(hist["info/env_steps_eval"].astype(np.float64).sum(axis=1).mean()),
        "wall_time_s": wall,
        "wall_time_per_seed_s": wall / num_seeds,
    }


def make_plots(exp, env, hist: dict, out: pathlib.Path) -> None:
    from shed_jax import reporting

    episode = hist["episode"][0]
    last = episode == episode[-1]
    x = np.cumsum(hist["info/env_steps_train"][0, last].astype(np.float64))
    y = hist["test_return"][:, last]
    label = f"{exp.method} (last teacher episode)" if exp.loop.num_episodes > 1 else exp.method
    reporting.plot_curves({label: (x, y)}, out / "test_return.png", xlabel="student env steps", ylabel="mean test return",
                          title=f"{exp.method} on {exp.env}: test return (mean ± SE over seeds)")
    per_level = hist["test_return_per_level"][:, last]  # [S, steps, L]
    # one small panel per level, shared axes (ten overlaid bands could not be told apart)
    reporting.plot_per_level(x, per_level, out / "test_return_per_level.png", xlabel="student env steps",
                             ylabel="test return", title=f"{exp.method} on {exp.env}: per test level (mean ± SE over seeds)")
    levels = hist.get("info/levels")
    if levels is not None and levels.ndim == 4 and levels.shape[-1] == env.param_space.dim:
        xs = np.arange(levels.shape[1])
        reporting.plot_parameters(xs, levels, env.param_space.names, out / "generated_levels.png",
                                  title=f"{exp.method} on {exp.env}: generated level parameters per budget step")
