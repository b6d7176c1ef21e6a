"""A run directory: what a run will do in it, decided and checked before anything is written.

``plan_fresh`` and ``plan_resume`` turn a run's options into a :class:`RunPlan`: the experiment,
seeds, chunk and configuration of a new run (refusing a directory that holds another run, or
clearing a run that stopped before its first checkpoint with ``--restart``), or the checkpoint a
resumed run continues from (the latest complete one, or ``--from-step N``; flags given with
``--resume`` must agree with the saved run). A damaged checkpoint is one
:class:`shed_jax.checkpoint.CheckpointCorruptError` naming the intact older ones.
``reconcile_metrics_jsonl`` cuts a resumed run's ``metrics.jsonl`` back to its checkpoint.

Layout (docs/running.md): ``config.json``, ``metrics.jsonl``, ``checkpoints/<step>/``,
``summary.json`` (written last: a run with it is finished), plots, ``final_eval_<set>.json``,
``discarded_checkpoints/`` (what ``--from-step`` moved away).
"""
from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import shutil
import time

import numpy as np

from shed_jax import experiment as xp
from shed_jax.errors import UsageError
from shed_jax.runtime import source_commit

#: what a run writes into its directory; ``--restart`` removes these (and nothing else)
RUN_FILES = ("config.json", "metrics.jsonl", "metrics.jsonl.tmp", "nonfinite_chunk.jsonl", "checkpoints")
DISCARDED_DIR = "discarded_checkpoints"  # where --from-step moves the checkpoints newer than its step


def resume_command(out: pathlib.Path) -> str:
    return f"python -m shed_jax run --resume {out}"


@dataclasses.dataclass
class RunPlan:
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


def write_atomic(path: pathlib.Path, text: str) -> None:
    """``path`` holds all of ``text`` or what it held before, never a part: a finished run's
    ``summary.json`` marks it finished, so a kill mid-write must not leave half of one."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def plan_fresh(opts, backend: str) -> RunPlan:
    """The plan of a new run from ``opts`` (the run flags as attributes)."""
    import jax

    from shed_jax.presets import default_chunk

    exp = xp.experiment_from_args(opts, backend)
    num_seeds = opts.seeds or xp.default_seeds(exp)
    root_seed = xp.DEFAULT_ROOT_SEED if opts.seed is None else opts.seed
    out = pathlib.Path(opts.out or f"runs/{exp.env}-{exp.method}-{exp.preset}-{time.strftime('%Y%m%d-%H%M%S')}")
    clear = check_out(out, opts.restart)
    chunk = opts.chunk or default_chunk(exp)
    config = run_config(exp, num_seeds, root_seed, backend, jax.devices(), chunk)
    return RunPlan(out, exp, num_seeds, root_seed, chunk, config, clear=clear)


def run_config(exp, seeds: int, root_seed: int, backend: str, devices, chunk: int) -> dict:
    """A run's configuration as config.json and its checkpoints hold it (a sweep point's adds ``sweep_point``)."""
    import jax

    return {"experiment": exp.to_dict(), "seeds": seeds, "root_seed": root_seed, "backend": backend,
            "devices": [str(d) for d in devices], "chunk": chunk, "jax": jax.__version__, "commit": source_commit()}


def commit_note(config: dict) -> str | None:
    """One line when a resumed run continues at another commit than the one it started at (None if the
    same, or either is unknown): its numbers then come from two versions of the code."""
    started, now = config.get("commit"), source_commit()
    if started and now and started != now:
        return f"this run started at commit {started} and continues at {now}"
    return None


def check_out(out: pathlib.Path, restart: bool) -> bool:
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


def clear_run(out: pathlib.Path) -> list[str]:
    """--restart: remove the files a run writes (``RUN_FILES``, metrics backups) from ``out``; returns their names."""
    removed = []
    for path in sorted(out.iterdir()):
        if path.name in RUN_FILES or path.name.startswith("metrics.jsonl.bak-"):
            removed.append(path.name + ("/" if path.is_dir() else ""))
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    return removed


def plan_resume(opts, backend: str) -> RunPlan:
    """The plan of ``--resume DIR``."""
    from shed_jax.checkpoint import (COMPARED_KEYS, CheckpointCorruptError, CheckpointNotFoundError, RunCheckpointer,
                                     check_config, complete_steps)

    out = pathlib.Path(opts.resume)
    from_step = opts.from_step
    if opts.out is not None and pathlib.Path(opts.out).resolve() != out.resolve():
        raise UsageError(f"--resume continues the run in its own directory {out}; drop --out {opts.out}")
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
    exp = xp.experiment_from_dict(config["experiment"])
    xp.check_resume_flags(opts, config, exp, backend, out)
    num_seeds, root_seed = int(config["seeds"]), int(config["root_seed"])
    chunk = opts.chunk or int(config.get("chunk") or exp.loop.steps_per_episode)
    total = exp.loop.total_steps
    if step > total:
        raise CheckpointNotFoundError(f"checkpoint step {step} is beyond the run's {total} budget steps")
    finished = damaged is None and from_step is None and step == total and (out / "summary.json").exists()
    return RunPlan(out, exp, num_seeds, root_seed, chunk, config, resume_step=step, complete=tuple(complete),
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


def restore(plan: RunPlan, target):
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
                f"{resume_command(plan.out)} --from-step {intact[0]}")
    else:
        hint = f"no older checkpoint is intact; delete {plan.out} to start over"
    raise CheckpointCorruptError(f"{err}; {hint}") from err


def discard_newer(plan: RunPlan) -> None:
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


def config_json(config: dict) -> str:
    """A run configuration as ``config.json`` holds it: strict JSON (a non-finite float by its name,
    ``configs.finite_json``), so that any JSON reader takes it."""
    from shed_jax.checkpoint import jsonable

    return json.dumps(jsonable(config), indent=2, allow_nan=False)


def create_run_dir(plan: RunPlan, made: list) -> None:
    """Clear (--restart), make ``out`` and write config.json; ``made`` collects what is new (removed if start-up is cut)."""
    out = plan.out
    if plan.clear:
        removed = clear_run(out)
        print(f"[shed_jax] --restart: removed {', '.join(removed) or 'nothing'} from {out}")
    try:
        if not out.exists():
            out.mkdir(parents=True)
            made.append(out)
        (out / "config.json").write_text(config_json(plan.config))
    except OSError as err:
        raise UsageError(f"--out {out}: cannot write there ({err.strerror or err})") from err
    made.append(out / "config.json")


def remove_made(made: list) -> str:
    """Undo what start-up made (files, and directories if empty), newest first; returns what was removed."""
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
    tmp.write_bytes(reporting.jsonl_bytes(reporting.step_records(flat, range(num_seeds))))
    os.replace(tmp, path)
    if backup is None:  # e.g. a carried piece packed without it (experiments/run_piece.sh): expected
        return f"metrics.jsonl: none beside the checkpoint; wrote its {len(expected)} record(s) from the checkpoint's history"
    return (f"metrics.jsonl did not hold exactly the records of steps < {step} "
            f"({len(seen & expected)}/{len(expected)} present{', duplicates' if dup else ''}); "
            f"rewrote it from the checkpoint's history "
            f"(old file kept as {backup.name})")
