"""How many bytes a run checkpoint takes, per subtree of the run state, and on disk.

    python -m experiments.checkpoint_size [--env walker] [--method shed] [--preset paper] [--seeds 5]
                                          [--label after] [--out docs/results/checkpoint_size.json]

1. **Shapes** (nothing computed): ``jax.eval_shape`` of the vmapped ``init`` (the restore target a
   resumed run builds) and of one budget step's metrics. It prints the raw bytes (elements x item
   size) of every subtree of the ``RunState`` and of the ``history`` item, which grows by one
   budget step's metrics per step (``loop.total_steps`` steps at the end of a run).
2. **On disk**: a state of exactly those shapes and dtypes with values like those of a late run,
   saved with :class:`shed_jax.checkpoint.RunCheckpointer` as ``run`` saves it, and the bytes of
   each item on disk. The walker's physics is never compiled. The values (``late_run_state``): the
   student's networks, optimiser and normalisers from its real ``init``, its slots reset onto four
   levels from the teacher's box (real terrain profiles, the largest leaf); the method's real
   ``init`` (episodic methods: DDPG and diffusion nets), then its replay buffer filled with
   ``--fill`` random transitions, ``--updates`` DDPG updates and diffusion training steps on it
   (trained weights and non-zero Adam moments), and the synthetic buffer filled; finally what the
   method does at the end of a budget step to the student's slots (``release_student_slots``,
   where it has one). The history holds ``--history-steps`` budget steps of random metrics.

The record (``--out``, merged by ``--label``: one entry per label, e.g. ``before`` and ``after`` a
change) holds the device, date, command, commit, the per-subtree MB and the totals.
"""
from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import pathlib
import platform
import sys
import tempfile
import time

import numpy as np

from shed_jax.runtime import source_commit


def _mb(n: int | float) -> float:
    return round(n / 1e6, 3)


def leaf_bytes(tree) -> dict[str, int]:
    """``{dotted path: raw bytes}`` of every leaf of a tree of arrays or ShapeDtypeStructs (key arrays as key data)."""
    import jax

    from shed_jax.checkpoint import _storable_target, path_name

    return {path_name(p): int(np.prod(x.shape)) * np.dtype(x.dtype).itemsize
            for p, x in jax.tree_util.tree_flatten_with_path(_storable_target(tree))[0]}


def subtree_bytes(leaves: dict[str, int], depth: int) -> dict[str, int]:
    """Raw bytes summed over the first ``depth`` parts of each dotted name."""
    out: dict[str, int] = collections.defaultdict(int)
    for name, n in leaves.items():
        out[".".join(name.split(".")[:depth])] += n
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def compressed_bytes(state) -> dict[str, int]:
    """``{dotted path: bytes}`` of every leaf as the checkpoint stores it: zarr with zstd level 1
    (orbax's default codec), one chunk per array, and 0 for a copy of another leaf where the
    checkpoint stores copies once (``checkpoint.find_aliases``)."""
    import jax
    import tensorstore as ts

    from shed_jax import checkpoint as ck

    host = {ck.path_name(p): np.asarray(x) for p, x in jax.tree_util.tree_flatten_with_path(jax.device_get(ck._storable(state)))[0]}
    aliases = ck.find_aliases(host) if hasattr(ck, "find_aliases") else {}
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, x) in enumerate(sorted(host.items())):
            if name in aliases:
                out[name] = 0
                continue
            x = x.reshape(1) if x.ndim == 0 else x
            d = pathlib.Path(tmp) / str(i)
            spec = {"driver": "zarr", "kvstore": {"driver": "file", "path": str(d)},
                    "metadata": {"shape": list(x.shape), "chunks": list(x.shape), "dtype": x.dtype.str,
                                 "compressor": {"id": "zstd", "level": 1}}}
            ts.open(spec, create=True).result().write(x).result()
            out[name] = sum(f.stat().st_size for f in d.rglob("*") if f.is_file() and f.name != ".zarray")
    return out


def disk_bytes(path: pathlib.Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def largest_file(path: pathlib.Path) -> int:
    return max((p.stat().st_size for p in path.rglob("*") if p.is_file()), default=0)


def build_batch(env: str, method: str, preset: str, seeds: int):
    from shed_jax import driver
    from shed_jax.experiment import build
    from shed_jax.presets import build_experiment

    exp = build_experiment(env, method, preset)
    batch = driver.make_batch(exp, build(exp), [({}, {})], num_seeds=seeds, root_seed=0)
    return exp, batch


def shapes(batch):
    """(state target, one budget step's metrics) as ShapeDtypeStructs, nothing computed."""
    import jax

    from shed_jax import driver

    keys, shp, mhp = driver.batch_inputs(batch)
    target = jax.eval_shape(jax.vmap(driver.batch_init(batch.init, batch.method)), keys, shp, mhp)
    metrics = jax.eval_shape(jax.vmap(lambda s: batch.run(s, 1, 0)), target)[1]
    return target, metrics


def late_run_state(batch, fill: int, updates: int):
    """A vmapped RunState of the batch's shapes with values like a late run's (module docstring)."""
    import jax
    import jax.numpy as jnp

    from shed_jax import driver
    from shed_jax.teacher.buffers import Transition, buffer_add_many

    keys, shp, mhp = driver.batch_inputs(batch)
    student, method = batch.student, batch.method

    def one(key, student_hp, method_hp):
        k_student, k_method, k_run, k_levels, k_seeds, k_assign, k_fill, k_ddpg, k_diff, k_syn = jax.random.split(key, 10)
        sstate = student.init(k_student, student_hp)
        mstate = method.init(k_method)
        if method_hp is not None:
            mstate = method.with_hparams(mstate, method_hp)
        codec = getattr(method, "codec", None)
        if codec is not None:  # the slots on fresh levels from the teacher's box
            from shed_jax.levels import new_seeds

            n = getattr(method.config, "num_levels", 4)
            vecs = codec.space.from_unit(jax.random.uniform(k_levels, (n, codec.dim), minval=-1.0, maxval=1.0))
            sstate = student.assign_levels(sstate, k_assign, codec.to_params(vecs, new_seeds(k_seeds, n)))
        teacher = getattr(method, "teacher", None)
        real = getattr(mstate, "real", None)
        if teacher is not None and real is not None:
            ks = jax.random.split(k_fill, 4)
            sd, ad = teacher.state_dim, teacher.action_dim
            done = (jnp.arange(fill) % 50 == 49).astype(jnp.float32)
            s = jax.random.normal(ks[0], (fill, sd)) * 50.0
            items = Transition(s=s, u=jax.random.uniform(ks[1], (fill, ad), minval=-1.0, maxval=1.0),
                               r=jax.random.normal(ks[2], (fill,)), s_next=s + jax.random.normal(ks[3], (fill, sd)),
                               done=done)
            real = buffer_add_many(real, items)
            ddpg = teacher.real_updates(k_ddpg, mstate.ddpg, real, updates)
            mstate = mstate.replace(ddpg=ddpg, real=real)
            synth = getattr(mstate, "synth", None)
            if synth is not None:
                syn_model = method.synthesiser.model
                d = syn_model.refresh_norm(synth.diffusion, real) if hasattr(syn_model, "refresh_norm") else synth.diffusion
                d, _ = syn_model.train_steps(d, k_diff, real, updates)
                cap = synth.syn.capacity
                idx = jax.random.randint(k_syn, (cap,), 0, fill)
                syn_items = jax.tree_util.tree_map(lambda x: x[idx], items)
                mstate = mstate.replace(synth=synth.replace(diffusion=d, syn=buffer_add_many(synth.syn, syn_items)))
        release = getattr(method, "release_student_slots", None)
        if release is not None:
            sstate = release(sstate)
        from shed_jax.loop import RunState

        return RunState(student=sstate, method=mstate, key=k_run, step=jnp.int32(fill))

    return jax.jit(jax.vmap(one))(keys, shp, mhp)


def random_history(metrics, steps: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``steps`` budget steps of metrics with the shapes of ``metrics`` (one step), random values."""
    import jax

    from shed_jax.reporting import flatten_tree

    rng = np.random.default_rng(seed)
    out = {}
    for k, v in flatten_tree(jax.tree_util.tree_map(lambda x: np.zeros(x.shape, x.dtype), metrics)).items():
        shape = (v.shape[0], steps) + v.shape[2:]
        if np.issubdtype(v.dtype, np.floating):
            out[k] = rng.normal(size=shape).astype(v.dtype)
        else:
            out[k] = rng.integers(0, 1000, size=shape).astype(v.dtype)
    return out


def measure_disk(state, history: dict, config: dict) -> dict:
    """Bytes on disk of one checkpoint per item, the largest file, and save/restore times (s)."""
    import jax

    from shed_jax.checkpoint import RunCheckpointer

    target = jax.eval_shape(lambda s: s, state)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.time()
        with RunCheckpointer(tmp, keep=1, async_save=False) as ck:
            ck.save(1, state, history, config)
        t_save = time.time() - t0
        step_dir = pathlib.Path(tmp) / "checkpoints" / "1"
        items = {p.name: disk_bytes(p) for p in step_dir.iterdir() if p.is_dir()}
        total, biggest = disk_bytes(step_dir), largest_file(step_dir)
        t0 = time.time()
        with RunCheckpointer(tmp, create=False) as ck:
            restored = ck.restore(target)
        t_restore = time.time() - t0
    from shed_jax.checkpoint import tree_digest

    same = tree_digest(restored.state) == tree_digest(state)
    return {"total_mb": _mb(total), "items_mb": {k: _mb(v) for k, v in sorted(items.items())},
            "largest_file_mb": _mb(biggest), "save_s": round(t_save, 2), "restore_s": round(t_restore, 2),
            "restored_bitwise": bool(same)}


def device_line() -> str:
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return f"{jax.default_backend()} ({os.cpu_count()} cores, {cpu})"


def record_header(module: str, argv) -> dict:
    """A measurement record's provenance: device, UTC date, the command (``python -m module ...``), commit, jax."""
    import jax

    return {"device": device_line(), "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "command": f"python -m {module} " + " ".join(argv if argv is not None else sys.argv[1:]),
            "commit": source_commit() or "unknown", "jax": jax.__version__}


def merge_labelled(path: str, label: str, record: dict) -> None:
    """Write ``record`` under ``label`` into the JSON file at ``path``, keeping its other labels."""
    out = pathlib.Path(path)
    doc = json.loads(out.read_text()) if out.exists() else {}
    doc[label] = record
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out} [{label}]")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="walker")
    ap.add_argument("--method", default="shed")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--fill", type=int, default=1000, help="real transitions in the teacher's buffer (one per budget step)")
    ap.add_argument("--updates", type=int, default=1000, help="DDPG updates and diffusion steps on them")
    ap.add_argument("--history-steps", type=int, default=None, help="budget steps in the history (default: the run's total)")
    ap.add_argument("--no-disk", action="store_true", help="shapes only")
    ap.add_argument("--label", default="after", help="key of this measurement in the record")
    ap.add_argument("--out", default=None, help="JSON record to merge this measurement into")
    args = ap.parse_args(argv)

    import jax

    t0 = time.time()
    exp, batch = build_batch(args.env, args.method, args.preset, args.seeds)
    target, metrics = shapes(batch)
    state_leaves = leaf_bytes(target)
    step_leaves = leaf_bytes(metrics)
    steps = exp.loop.total_steps if args.history_steps is None else args.history_steps
    per_step = sum(step_leaves.values())
    print(f"{args.env} {args.method} {args.preset}, {args.seeds} seeds: run state {_mb(sum(state_leaves.values()))} MB raw "
          f"in {len(state_leaves)} leaves; history {per_step} B per budget step, {_mb(per_step * steps)} MB after "
          f"{steps} steps (shapes in {time.time() - t0:.1f} s)")
    state = history = None
    packed: dict[str, int] = {}
    if not args.no_disk:
        t1 = time.time()
        state = jax.block_until_ready(late_run_state(batch, args.fill, args.updates))
        history = random_history(metrics, steps)
        packed = compressed_bytes(state)
        print(f"late-run values built and compressed per leaf in {time.time() - t1:.1f} s")
    table, packed_table = {}, {}
    for depth in (1, 2, 3):
        packed_sums = subtree_bytes(packed, depth)
        for name, n in subtree_bytes(state_leaves, depth).items():
            if n >= 1e4 and name not in table:
                table[name] = _mb(n)
                if packed:
                    packed_table[name] = _mb(packed_sums.get(name, 0))
    print(f"{'MB raw':>9} {'MB zstd':>9}  subtree")
    for name in sorted(table):
        print(f"{table[name]:9.3f} {packed_table.get(name, float('nan')):9.3f}  {name}")
    print(f"{_mb(per_step * steps):9.3f} {'':9}  history ({steps} budget steps; largest per step: "
          + ", ".join(f"{k} {v} B" for k, v in sorted(step_leaves.items(), key=lambda kv: -kv[1])[:3]) + ")")
    record = {
        **record_header("experiments.checkpoint_size", argv),
        "experiment": {"env": args.env, "method": args.method, "preset": args.preset, "seeds": args.seeds},
        "state_raw_mb": _mb(sum(state_leaves.values())), "subtree_raw_mb": table,
        "history_bytes_per_step": per_step, "history_steps": steps, "history_raw_mb": _mb(per_step * steps),
    }
    if state is not None:
        config = {"experiment": exp.to_dict(), "seeds": args.seeds, "root_seed": 0}
        disk = measure_disk(state, history, config)
        disk["values"] = (f"late_run_state: real inits, {args.fill} random real transitions, {args.updates} DDPG updates "
                          f"and diffusion steps on them, synthetic buffer full; {steps} steps of random metrics")
        disk["subtree_zstd_mb"] = packed_table
        disk["state_zstd_mb"] = _mb(sum(packed.values()))
        record["disk"] = disk
        print(f"on disk: {disk['total_mb']} MB ({', '.join(f'{k} {v} MB' for k, v in disk['items_mb'].items())}); "
              f"largest file {disk['largest_file_mb']} MB; save {disk['save_s']} s, restore {disk['restore_s']} s; "
              f"restored bitwise: {disk['restored_bitwise']}")
    if args.out:
        merge_labelled(args.out, args.label, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
