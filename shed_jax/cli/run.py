"""``python -m shed_jax run``: one UED method on one environment, seeds vmapped, end to end.

The compiled outer loop (``shed_jax.loop``) runs in chunks of budget steps; between chunks the
host checks the chunk for non-finite values (``shed_jax.checkpoint.find_nonfinite``), writes the
per-step metrics (``metrics.jsonl``), saves a checkpoint of the whole run state
(``DIR/checkpoints/<step>``, the last ``--keep``), prints a one-line summary and updates a progress
bar. At the end it writes ``summary.json`` and plots (mean test return with standard error over
seeds against student env steps; per-test-level curves; the generated level parameters).

``--resume DIR`` continues a run from its latest checkpoint, bitwise as if it had not stopped.
SIGINT/SIGTERM finish the current chunk, save and exit with 130/143; ``--stop-after`` and
``--time-limit`` stop the same way with exit code 75. See docs/running.md.
"""
from __future__ import annotations

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

from shed_jax.cli import eval as eval_cli

TEST_SETS = ("lander-test", "walker-test-a", "walker-test-b")

EXIT_CHECKPOINT = 2  # a checkpoint could not be used (missing, damaged, other configuration)
EXIT_NONFINITE = 3  # the non-finite guard stopped the run
EXIT_STOPPED = 75  # --stop-after / --time-limit reached; resumable (EX_TEMPFAIL)

DEFAULT_ENV = "lander"
DEFAULT_METHOD = "shed"
DEFAULT_PRESET = "auto"
DEFAULT_ROOT_SEED = 0
# --final-eval when not given: the walker's named levels (DCD's six of SPEC 3.2 set A first) with solved rates
DEFAULT_FINAL_EVAL = {"walker": "named"}


def add_arguments(p) -> None:
    from shed_jax.presets import PRESETS

    p.add_argument("--env", default=None, help=f"lander | lander-continuous | walker (default {DEFAULT_ENV})")
    p.add_argument("--method", default=None,
                   help=f"shed | hmdp | dr | paired | accel | accel-norevisit | plr (default {DEFAULT_METHOD})")
    p.add_argument("--preset", default=None, choices=("auto",) + PRESETS,
                   help="auto (default): 'paper' on a GPU, 'quick' on a CPU (the choice is printed)")
    p.add_argument("--seeds", type=int, default=None, help="number of vmapped seeds (default: quick 2, paper 5; the walker on a CPU 1)")
    p.add_argument("--seed", type=int, default=None,
                   help=f"root seed (default {DEFAULT_ROOT_SEED}); seed i of the batch uses fold_in(root, i)")
    p.add_argument("--episodes", type=int, default=None, help="override the number of teacher episodes N_ep")
    p.add_argument("--steps-per-episode", type=int, default=None, help="override the budget steps per episode T")
    p.add_argument("--test-episode-every", type=int, default=None, metavar="K",
                   help="run the test set only in teacher episodes 0, K, 2K, ... and the last "
                        "(default: paper preset 10 for shed/hmdp, else 1 = every episode)")
    p.add_argument("--chunk", type=int, default=None,
                   help="budget steps per compiled call, i.e. between checkpoints (default: T)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the method's config (repeatable), e.g. --set num_eval_levels=20 "
                        "or --set 'reward={\"eta\": 10}'")
    p.add_argument("--ppo", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the student's PPOConfig or PPOHyperparams (repeatable), "
                        "e.g. --ppo num_envs=8 --ppo num_steps=640")
    p.add_argument("--out", default=None, help="run directory (default runs/<env>-<method>-<preset>-<time>)")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF of the final student")
    p.add_argument("--final-eval", default=None, metavar="LEVELS",
                   help="after the last budget step, evaluate the final students on level sets as `eval --levels` "
                        "does (test | named | FILE.json, comma-separated, or none) and write final_eval_<set>.json; "
                        f"default: {', '.join(f'{e} {v}' for e, v in DEFAULT_FINAL_EVAL.items())}, other envs none")
    p.add_argument("--final-eval-episodes", type=int, default=10, metavar="N",
                   help="episodes per level and seed of --final-eval (default 10); the episode cap is the test set's")
    g = p.add_argument_group("checkpoints and stopping")
    g.add_argument("--resume", default=None, metavar="DIR",
                   help="continue the run in DIR from its latest checkpoint (its saved configuration is used; "
                        "experiment flags given as well must agree with it)")
    g.add_argument("--keep", type=int, default=3, metavar="K", help="keep the last K checkpoints (default 3)")
    g.add_argument("--no-checkpoint", action="store_true", help="do not save checkpoints (the run cannot be resumed)")
    g.add_argument("--stop-after", type=int, default=None, metavar="STEPS",
                   help="stop at the first chunk boundary at or after this many budget steps, save, exit 75")
    g.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                   help="stop at the first chunk boundary after this much wall time in this process, save, exit 75")


def _parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"--set expects KEY=VALUE, got {item!r}")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def test_levels(name: str, env):
    from shed_jax import eval_sets

    if name == "lander-test":
        return eval_sets.lander_test_set().to_params(env.default_params)
    if name == "walker-test-b":
        return eval_sets.walker_test_set_b().to_params(env.default_params)
    if name == "walker-test-a":
        return eval_sets.walker_test_set_a()
    raise ValueError(f"unknown test set {name!r}; known: {', '.join(TEST_SETS)}")


def _method_config_class(name: str):
    """The method's config dataclass (None for an unknown method: make_method reports it)."""
    if name in ("shed", "hmdp"):
        from shed_jax.methods.shed import SHEDConfig

        return SHEDConfig
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
    student = make_student(env, exp.ppo)
    method = make_method(exp.method, env, student, method_config(exp.method, exp.method_config))
    return env, student, method, test_levels(exp.test_set, env)


def experiment_from_args(args, backend: str):
    """The Experiment the command line asks for (``--preset auto`` resolved for ``backend``, and said)."""
    from shed_jax.presets import build_experiment

    preset = args.preset or DEFAULT_PRESET
    if preset == "auto":
        preset = "paper" if backend == "gpu" else "quick"
        print(f"[shed_jax] backend={backend}: using the '{preset}' preset "
              f"({'GPU budgets from SPEC 6.3' if preset == 'paper' else 'a CPU-sized smoke run; pass --preset paper for the real budget'})")
    return build_experiment(args.env or DEFAULT_ENV, args.method or DEFAULT_METHOD, preset, episodes=args.episodes,
                            steps_per_episode=args.steps_per_episode, test_episode_every=args.test_episode_every,
                            method_overrides=_parse_overrides(args.set), ppo_overrides=_parse_ppo(args.ppo))


def _parse_ppo(items: list[str]) -> dict:
    from shed_jax.student.config import parse_overrides

    try:
        return parse_overrides(items)
    except ValueError as err:
        raise SystemExit(str(err)) from None


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
            raise SystemExit(f"--final-eval: 'none' cannot be combined with level sets, got {arg!r}")
        return []
    if len(set(specs)) != len(specs):
        raise SystemExit(f"--final-eval names a level set twice: {arg!r}")
    return specs


def default_seeds(exp) -> int:
    """Seeds when --seeds is not given: paper 5, quick 2 (on any backend: the walker's CPU deadlock
    with two seeds was the batched-LAPACK one of shed_jax/xla_cpu.py, which the student init avoids)."""
    return 5 if exp.preset == "paper" else 2


def seed_keys(root_seed: int, num_seeds: int):
    import jax

    root = jax.random.PRNGKey(root_seed)
    return jax.vmap(lambda i: jax.random.fold_in(root, i))(np.arange(num_seeds))


class StopRequest:
    """SIGINT/SIGTERM set ``signum``; the loop finishes its chunk, saves and exits 128 + signum.

    A second signal aborts at once (the last complete checkpoint stays). Handlers are installed
    only in the main thread and restored on exit.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.signum: int | None = None
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
    backup = path.with_name(f"{path.name}.bak-{step}")
    if path.exists():
        shutil.copyfile(path, backup)
    flat = {k: np.asarray(v)[:, :step] for k, v in hist.items()}
    with open(tmp, "w") as f:
        for r in reporting.step_records(flat, range(num_seeds)):
            f.write(json.dumps(r) + "\n")
    os.replace(tmp, path)
    return (f"metrics.jsonl did not hold exactly the records of steps < {step} "
            f"({len(seen & expected)}/{len(expected)} present{', duplicates' if dup else ''}); "
            f"rewrote it from the checkpoint's history (old file: {backup.name})")


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
        print(f"[shed_jax] checkpoint error: {err}", file=sys.stderr)
        return EXIT_CHECKPOINT


def _main(args) -> int:
    import jax
    from tqdm import tqdm

    from shed_jax import reporting
    from shed_jax.checkpoint import COMPARED_KEYS, CheckpointNotFoundError, RunCheckpointer, check_config, find_nonfinite
    from shed_jax.loop import make_run

    if args.keep < 1:
        raise SystemExit("--keep must be >= 1")
    if args.final_eval_episodes < 1:
        raise SystemExit("--final-eval-episodes must be >= 1")
    if args.stop_after is not None and args.stop_after < 1:
        raise SystemExit("--stop-after must be >= 1")
    if args.chunk is not None and args.chunk < 1:
        raise SystemExit("--chunk must be >= 1")
    backend = jax.default_backend()
    ckpt = None
    previous_wall = 0.0
    if args.resume:
        out = pathlib.Path(args.resume)
        if args.out is not None and pathlib.Path(args.out).resolve() != out.resolve():
            raise SystemExit(f"--resume continues the run in its own directory {out}; drop --out {args.out}")
        with RunCheckpointer(out, create=False) as reader:
            config = reader.read_config()
        cfg_file = out / "config.json"
        if cfg_file.exists():
            check_config(config, json.loads(cfg_file.read_text()), COMPARED_KEYS, where=f"checkpoint (vs {cfg_file})")
        current = {}
        if _experiment_flags_given(args):
            current["experiment"] = experiment_from_args(args, backend).to_dict()
        if args.seeds is not None:
            current["seeds"] = args.seeds
        if args.seed is not None:
            current["root_seed"] = args.seed
        exp = experiment_from_dict(config["experiment"])
        num_seeds, root_seed = int(config["seeds"]), int(config["root_seed"])
        chunk = args.chunk or int(config.get("chunk") or exp.loop.steps_per_episode)
    else:
        exp = experiment_from_args(args, backend)
        num_seeds = args.seeds or default_seeds(exp)
        root_seed = DEFAULT_ROOT_SEED if args.seed is None else args.seed
        if num_seeds < 1:
            raise SystemExit("--seeds must be >= 1")
        out = pathlib.Path(args.out or f"runs/{exp.env}-{exp.method}-{exp.preset}-{time.strftime('%Y%m%d-%H%M%S')}")
        out.mkdir(parents=True, exist_ok=True)
        for held in ("metrics.jsonl", "checkpoints"):
            if (out / held).exists():
                raise SystemExit(f"{out} already holds a run ({held}); continue it with --resume {out} or choose another --out")
        chunk = args.chunk or exp.loop.steps_per_episode
        config = {"experiment": exp.to_dict(), "seeds": num_seeds, "root_seed": root_seed, "backend": backend,
                  "devices": [str(d) for d in jax.devices()], "chunk": chunk, "jax": jax.__version__}

    env, student, method, tests = build(exp)
    # level sets of --final-eval are resolved now, so that a bad one fails before training, not after
    try:
        final_sets = [eval_cli.resolve_levels(spec, env, exp, tests) for spec in final_eval_specs(args.final_eval, exp.env)]
    except eval_cli.LevelFileError as err:
        raise SystemExit(f"--final-eval: {err}") from err
    init, run = make_run(student, method, tests, exp.loop)
    total = exp.loop.total_steps
    keys = seed_keys(root_seed, num_seeds)
    run_chunk = jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)
    metrics_path = out / "metrics.jsonl"

    if args.resume:
        with RunCheckpointer(out, create=False) as reader:
            restored = reader.restore(jax.eval_shape(jax.vmap(init), keys), config=current or None, keys=tuple(current))
        state, done, hist = restored.state, restored.step, restored.history
        previous_wall = float(restored.extra.get("wall_time_s", 0.0))
        if done > total:
            raise CheckpointNotFoundError(f"checkpoint step {done} is beyond the run's {total} budget steps")
        print(f"[shed_jax] resuming {out} from budget step {done}/{total}")
        print(f"[shed_jax] {reconcile_metrics_jsonl(metrics_path, hist, done, num_seeds)}")
    else:
        (out / "config.json").write_text(json.dumps(config, indent=2, default=str))
        state = jax.jit(jax.vmap(init))(keys)
        done, hist = 0, {}
    if not args.no_checkpoint:
        ckpt = RunCheckpointer(out, keep=args.keep, create=True)
    print(f"[shed_jax] {exp.method} on {exp.env}: {exp.loop.num_episodes} episode(s) x {exp.loop.steps_per_episode} "
          f"budget steps, {num_seeds} seed(s), ~{exp.env_steps_per_budget_step:,} student env steps per budget step -> {out}")

    t0 = time.time()
    stopped = None  # (exit code, reason)
    bar = tqdm(total=total, initial=done, unit="step", desc=f"{exp.method}/{exp.env}", dynamic_ncols=True)
    try:
        with StopRequest() as stop:
            while done < total:
                n = min(chunk, total - done)
                new_state, metrics = run_chunk(state, n, done)
                flat = reporting.flatten_tree(jax.device_get(metrics))
                problems = find_nonfinite(flat, new_state, done, exp.loop.tests_at)
                if problems:
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
                reporting.append_jsonl(metrics_path, reporting.step_records(flat, range(num_seeds)))
                done += n
                if ckpt is not None:
                    ckpt.save(done, state, hist, config, extra={"wall_time_s": previous_wall + time.time() - t0})
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
    finally:
        bar.close()
        if ckpt is not None:
            ckpt.close()
    if stopped is not None:
        code, reason = stopped
        print(f"[shed_jax] {reason}: stopped at budget step {done}/{total}")
        if ckpt is not None:
            print(f"[shed_jax] checkpoint saved in {ckpt.directory / str(done)}; resume with:\n  {_resume_command(out)}")
        else:
            print("[shed_jax] no checkpoint was written (--no-checkpoint): this run cannot be resumed")
        return code

    wall = previous_wall + time.time() - t0
    summary = summarize(exp, hist, wall, num_seeds)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    make_plots(exp, env, hist, out)
    for resolved in final_sets:
        final_eval(exp, env, student, state.student, num_seeds, resolved, out, done, args.final_eval_episodes)
    if not args.no_gif:
        try:
            from shed_jax.visualize import student_gif

            path = student_gif(env, student, state, tests, out / "final_student.gif")
            print(f"[shed_jax] wrote {path}")
        except ImportError as err:  # the visualisation module is optional
            print(f"[shed_jax] no GIF: shed_jax.visualize is not available ({err})")
        except NotImplementedError as err:  # an env without a renderer
            print(f"[shed_jax] no GIF: {err}")
        except Exception as err:  # noqa: BLE001 - the results are written; a GIF failure must not fail the run
            print(f"[shed_jax] no GIF: {type(err).__name__}: {err}")
    print(json.dumps({k: summary[k] for k in ("final_test_return_mean", "final_test_return_se", "wall_time_s")}, indent=2))
    print(f"[shed_jax] results in {out}")
    return 0


def final_eval(exp, env, student, student_state, num_seeds: int, resolved, out: pathlib.Path, step: int,
               episodes: int) -> None:
    """Evaluate the final students on one level set (as ``eval`` does) and write final_eval_<set>.json.

    The episode cap is the test set's (``LoopSpec.test_max_steps``). The run's results are already
    written, so a failure here is reported and does not fail the run. The JSON's ``wall_time_s`` is
    the evaluation's own time, compile included; the run's ``summary.json`` wall time stops before it.
    """
    t0 = time.time()
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
    curves = {f"level {j}": (x, per_level[..., j]) for j in range(per_level.shape[-1])}
    reporting.plot_curves(curves, out / "test_return_per_level.png", xlabel="student env steps", ylabel="test return",
                          title=f"{exp.method} on {exp.env}: per test level")
    levels = hist.get("info/levels")
    if levels is not None and levels.ndim == 4 and levels.shape[-1] == env.param_space.dim:
        xs = np.arange(levels.shape[1])
        reporting.plot_parameters(xs, levels, env.param_space.names, out / "generated_levels.png",
                                  title=f"{exp.method} on {exp.env}: generated level parameters per budget step")
