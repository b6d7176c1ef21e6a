"""Checkpoints of a whole UED run (orbax), and the non-finite guard that decides what may be saved.

A run directory holds ``checkpoints/<step>/`` (``step`` = budget steps done), written by an orbax
``CheckpointManager`` (each save goes to a temporary directory that is renamed when complete, so a
kill during a save leaves the previous checkpoint intact; the last ``keep`` are kept). Each
checkpoint has three items:

* ``state``: the full vmapped :class:`shed_jax.loop.RunState` (student params, optimiser and
  normaliser states, env states, method state with its networks, optimisers and buffers, RNG keys,
  the step counter);
* ``history``: the per-step metrics so far (flattened keys ``info/levels``..., leaves
  ``[seeds, steps, ...]``), so summaries and plots of a resumed run equal those of a straight one;
* ``meta`` (JSON): the step, the run configuration (``config.json``'s dict: experiment, seeds, root
  seed, ...), SHA-256 digests of ``state`` and ``history`` and caller extras (e.g. wall time).

Size: orbax writes every array zstd-compressed (its default), into OCDBT data files of about
``DATA_FILE_BYTES`` each (orbax's ``ocdbt_target_data_file_size``), so that no file of a checkpoint
exceeds what a transfer with a per-file limit takes (16 MiB on the device machines). A leaf of the
state whose bytes equal those of an earlier leaf (same dtype and shape) is stored once: the copy is
saved as a scalar placeholder, and the state item's own metadata (orbax's ``custom_metadata``,
``saved_aliases``) maps its name to the leaf it equals (SHED's diffusion sampling
parameters are its training parameters when ``diffusion_ema`` is 0; Adam moments and target
networks equal each other or their online networks before the first update). Restoring fills the
copies back before the digest check, so the state read back is bitwise the one saved.
``docs/running.md`` has the sizes (``python -m experiments.checkpoint_size``).

The layout is versioned (``FORMAT``): checkpoints of every format in ``READABLE_FORMATS`` restore
(format 1, before aliases and the data file size, has no aliases); a newer format is refused with a
one-line :class:`CheckpointError` that says to update shed_jax.

Restoring needs a *target*: the state a fresh ``init`` would build (``jax.eval_shape`` of it is
enough). The checkpoint's tree paths, shapes and dtypes are checked against it before anything is
read, and the digests after, so a restore is either bitwise exact or a :class:`CheckpointError`
that says what is wrong, never a silent restart:

* :class:`CheckpointNotFoundError`: no run directory / no complete checkpoint in it;
* :class:`CheckpointCorruptError`: a damaged checkpoint (unreadable or missing files, a wrong digest,
  array metadata that is not what was saved, an unfinished newer step directory) or a state of
  another structure;
* :class:`ConfigMismatchError`: the checkpoint belongs to another configuration (names the keys).

Messages are one line (library errors quoted inside them are shortened: TensorStore's specs run to
kilobytes); the full error stays in ``__cause__``. ``verify`` says whether one checkpoint is intact,
so a caller can list the intact ones when the newest is damaged.

``find_nonfinite`` is the guard the run CLI applies after every chunk, before saving.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
from typing import Any, Iterable

import jax
import numpy as np

CHECKPOINT_SUBDIR = "checkpoints"
FORMAT = 2  # bump when the layout of a checkpoint changes (2: state aliases, data files of DATA_FILE_BYTES)
READABLE_FORMATS = (1, 2)  # formats this version restores
#: target size of each OCDBT data file of an item (orbax ``ocdbt_target_data_file_size``)
DATA_FILE_BYTES = 8 * 2**20
#: configuration keys a resumed run must share with its checkpoint
COMPARED_KEYS = ("experiment", "seeds", "root_seed")


class CheckpointError(RuntimeError):
    """A checkpoint cannot be used (missing, damaged or from another configuration)."""


class CheckpointNotFoundError(CheckpointError):
    """No run directory, or no complete checkpoint in it."""


class CheckpointCorruptError(CheckpointError):
    """A checkpoint exists but cannot be read back exactly."""


class ConfigMismatchError(CheckpointError):
    """The checkpoint was written by a run with another configuration.

    ``differences`` lists ``(dotted key, saved value, current value)``.
    """

    def __init__(self, message: str, differences: list[tuple[str, Any, Any]]):
        super().__init__(message)
        self.differences = differences

    @property
    def keys(self) -> list[str]:
        return [k for k, _, _ in self.differences]


# --------------------------------------------------------------------------------------------
# configuration comparison
# --------------------------------------------------------------------------------------------


def jsonable(obj: Any) -> Any:
    """``obj`` as it reads back from strict JSON: tuples become lists, unknown objects strings, and
    non-finite floats their names (``configs.finite_json``), so a saved ``-Infinity`` and a saved
    ``"-inf"`` compare equal."""
    from shed_jax.configs import finite_json

    return finite_json(json.loads(json.dumps(obj, default=str)))


def _flat_items(obj: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(obj, dict):
        out: dict[str, Any] = {}
        if not obj and prefix:
            out[prefix] = {}
        for k, v in obj.items():
            out.update(_flat_items(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: obj}


#: how ``config_differences`` shows a key that one side lacks
MISSING = "<missing>"


def config_differences(saved: dict, current: dict, keys: Iterable[str] = COMPARED_KEYS) -> list[tuple[str, Any, Any]]:
    """``(dotted key, saved, current)`` for every leaf that differs under ``keys`` (after a JSON round trip).

    A key missing on one side shows as ``MISSING``.
    """
    diffs = []
    for top in keys:
        a = _flat_items(jsonable(saved.get(top, MISSING)), top)
        b = _flat_items(jsonable(current.get(top, MISSING)), top)
        for k in sorted(set(a) | set(b)):
            va, vb = a.get(k, MISSING), b.get(k, MISSING)
            if va != vb:
                diffs.append((k, va, vb))
    return diffs


def describe_differences(diffs: list[tuple[str, Any, Any]], limit: int = 20) -> str:
    """``'seeds: saved 2, now 3; root_seed: saved 0, now 1'`` (one line; at most ``limit`` keys)."""
    text = "; ".join(f"{k}: saved {a!r}, now {b!r}" for k, a, b in diffs[:limit])
    return text + (f"; ... and {len(diffs) - limit} more" if len(diffs) > limit else "")


def check_config(saved: dict, current: dict, keys: Iterable[str] = COMPARED_KEYS, where: str = "checkpoint") -> None:
    """Raise :class:`ConfigMismatchError` naming every differing key (one line)."""
    diffs = config_differences(saved, current, keys)
    if diffs:
        raise ConfigMismatchError(f"the {where} was written with another configuration: {describe_differences(diffs)}", diffs)


# --------------------------------------------------------------------------------------------
# tree helpers
# --------------------------------------------------------------------------------------------


def brief(err: BaseException, limit: int = 300) -> str:
    """``'Type: message'`` on one line, without TensorStore's spec dump, at most ``limit`` characters."""
    text = " ".join(str(err).split("[tensorstore_spec=")[0].split())
    text = f"{type(err).__name__}: {text}" if text else type(err).__name__
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _is_closed_loop_callback(unraisable) -> bool:
    exc = unraisable.exc_value
    return isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed"


class _AbandonedReadFilter:
    """Drops asyncio's "Task exception was never retrieved" records of TensorStore reads."""

    def filter(self, record) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        exc = exc or (record.args.get("exception") if isinstance(record.args, dict) else None)
        text = f"{record.getMessage()} {exc}"
        return not ("exception was never retrieved" in text and "tensorstore_spec" in text)


def quiet_closed_loop_callbacks() -> None:
    """Silence the late echoes of a failed orbax read (the checkpoint error itself says what failed).

    When one array of a restore cannot be read, orbax returns the error and closes its event loop
    while TensorStore still completes the other reads: each completion posts to the closed loop
    (Python prints the RuntimeError as unraisable) and the abandoned tasks' errors are logged by
    asyncio when collected, dozens of tracebacks in all, nothing lost. Installed once, after a
    failed read; every other unraisable error goes to the previous hook, other records through.
    """
    import logging
    import sys

    previous = sys.unraisablehook
    if getattr(previous, "_shed_jax_quiet", False):
        return

    def hook(unraisable):
        if not _is_closed_loop_callback(unraisable):
            previous(unraisable)

    hook._shed_jax_quiet = True
    sys.unraisablehook = hook
    logging.getLogger("asyncio").addFilter(_AbandonedReadFilter())


def structure_digest(leaves: dict[str, Any]) -> str:
    """SHA-256 over ``{dotted name: array-like}`` names, dtypes and shapes (no values)."""
    h = hashlib.sha256()
    for name in sorted(leaves):
        x = leaves[name]
        h.update(f"{name}|{np.dtype(x.dtype).str}|{tuple(x.shape)}\n".encode())
    return h.hexdigest()


def _key_name(k) -> str:
    for attr in ("name", "key", "idx"):
        if hasattr(k, attr):
            return str(getattr(k, attr))
    return str(k)


def path_name(path) -> str:
    """A pytree key path as a dotted name (``student.params.actor.MLP_0.Dense_0.kernel``), as orbax names leaves."""
    return ".".join(_key_name(k) for k in path)


def _is_key_array(x) -> bool:
    dtype = getattr(x, "dtype", None)
    return dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)


def _storable(tree):
    """Typed PRNG key arrays -> their uint32 key data (orbax stores plain arrays)."""
    return jax.tree_util.tree_map(lambda x: jax.random.key_data(x) if _is_key_array(x) else x, tree)


def _storable_target(tree):
    def conv(x):
        if _is_key_array(x):
            return jax.eval_shape(jax.random.key_data, x)
        return jax.ShapeDtypeStruct(np.shape(x), x.dtype)

    return jax.tree_util.tree_map(conv, tree)


def _unstorable(restored, target):
    return jax.tree_util.tree_map(
        lambda r, t: jax.random.wrap_key_data(r, impl=jax.random.key_impl(t)) if _is_key_array(t) else r, restored, target
    )


def find_aliases(leaves: dict[str, Any]) -> dict[str, str]:
    """``{name: earlier name}`` for every leaf whose dtype, shape and bytes equal those of an earlier
    leaf (in sorted name order); leaves of one element are never aliased (the placeholder is one).

    ``leaves``: ``{dotted name: host array}``. Equality is of the raw bytes (NaNs included), found by
    SHA-256 and confirmed byte for byte.
    """
    first: dict[tuple, str] = {}
    aliases: dict[str, str] = {}
    for name in sorted(leaves):
        x = np.ascontiguousarray(np.asarray(leaves[name]))
        if x.size < 2:
            continue
        key = (x.dtype.str, x.shape, hashlib.sha256(x.tobytes()).digest())
        source = first.setdefault(key, name)
        if source != name and np.asarray(leaves[source]).tobytes() == x.tobytes():
            aliases[name] = source
    return aliases


def saved_aliases(state_metadata) -> dict[str, str]:
    """The aliases a state item was saved with (its orbax custom metadata; none in format 1)."""
    custom = getattr(state_metadata, "custom_metadata", None) or {}
    aliases = custom.get("aliases", {}) if isinstance(custom, dict) else None
    if not isinstance(aliases, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in aliases.items()):
        raise ValueError(f"malformed aliases in the state's metadata: {str(custom)[:100]}")
    return aliases


def _placeholder(dtype) -> np.ndarray:
    return np.zeros((), dtype)


def tree_digest(tree) -> str:
    """SHA-256 over every leaf's path, dtype, shape and bytes (host copies)."""
    h = hashlib.sha256()
    for path, leaf in jax.tree_util.tree_flatten_with_path(_storable(tree))[0]:
        x = np.ascontiguousarray(np.asarray(leaf))
        h.update(f"{path_name(path)}|{x.dtype.str}|{x.shape}\n".encode())
        h.update(x.tobytes())
    return h.hexdigest()


def nest(flat: dict[str, Any]) -> dict:
    """``{'a/b': x}`` -> ``{'a': {'b': x}}`` (orbax stores nested dicts; keys with '/' are paths)."""
    out: dict = {}
    for key, value in flat.items():
        parts = key.split("/")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"metric key {key!r} collides with a leaf at {p!r}")
        node[parts[-1]] = value
    return out


def unnest(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(unnest(v, f"{prefix}{k}/"))
        else:
            out[f"{prefix}{k}"] = np.asarray(v)
    return out


def _metadata_leaves(tree) -> dict[str, Any]:
    """orbax's TreeMetadata (or its ``.tree``) -> {dotted name: ArrayMetadata-like}."""
    tree = getattr(tree, "tree", tree)
    out = {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree, is_leaf=lambda x: hasattr(x, "shape") and hasattr(x, "dtype"))[0]:
        if leaf is None:
            continue
        out[path_name(path)] = leaf
    return out


# --------------------------------------------------------------------------------------------
# the checkpointer
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Restored:
    step: int  # budget steps done
    state: Any  # the RunState, in the target's structure
    history: dict[str, np.ndarray] | None  # flattened metrics [seeds, step, ...]
    config: dict  # the run configuration saved with it
    extra: dict  # caller extras saved with it (e.g. wall time)


class RunCheckpointer:
    """Save and restore checkpoints of one run directory (``DIR/checkpoints``).

    ``keep``: how many of the most recent checkpoints to keep. ``create=False`` opens an existing
    run read-only (raises :class:`CheckpointNotFoundError` if there is none). ``data_file_bytes``:
    the target size of each data file a save writes (orbax's ``ocdbt_target_data_file_size``).
    """

    def __init__(self, run_dir, keep: int = 3, create: bool = True, async_save: bool = True,
                 data_file_bytes: int = DATA_FILE_BYTES):
        import orbax.checkpoint as ocp

        if not isinstance(keep, int) or keep < 1:
            raise ValueError(f"keep must be a positive int, got {keep!r}")
        if isinstance(data_file_bytes, bool) or not isinstance(data_file_bytes, int) or data_file_bytes < 1:
            raise ValueError(f"data_file_bytes must be a positive int, got {data_file_bytes!r}")
        self.data_file_bytes = data_file_bytes
        self.run_dir = pathlib.Path(run_dir)
        self.directory = self.run_dir / CHECKPOINT_SUBDIR
        if not create:
            if not self.run_dir.is_dir():
                raise CheckpointNotFoundError(f"no run directory {self.run_dir}")
            if not self.directory.is_dir():
                raise CheckpointNotFoundError(f"{self.run_dir} has no {CHECKPOINT_SUBDIR}/ directory (was it run with --no-checkpoint?)")
        self._ocp = ocp
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=create, enable_async_checkpointing=async_save)
        handlers = {
            # the PyTree handler (StandardCheckpointHandler's base) takes the data file size on save
            "state": ocp.PyTreeCheckpointHandler(),
            "history": ocp.StandardCheckpointHandler(),
            "meta": ocp.JsonCheckpointHandler(),
        }
        self.manager = ocp.CheckpointManager(self.directory.absolute(), options=options, item_handlers=handlers)

    # ---------------------------------------------------------------- queries
    def steps(self) -> list[int]:
        return sorted(int(s) for s in self.manager.all_steps())

    def latest_step(self) -> int | None:
        steps = self.steps()
        return steps[-1] if steps else None

    def _resolve_step(self, step: int | None) -> int:
        steps = self.steps()
        # a digits-only directory orbax does not list is a finished rename whose contents are damaged
        # (interrupted saves live in '<step>.orbax-checkpoint-tmp-*' and are ignored)
        on_disk = sorted(int(p.name) for p in self.directory.iterdir() if p.is_dir() and p.name.isdigit())
        unlisted = [s for s in on_disk if s not in steps]
        if not steps:
            if unlisted:
                raise CheckpointCorruptError(
                    f"{self.directory}: step director{'y' if len(unlisted) == 1 else 'ies'} {unlisted} "
                    f"{'is' if len(unlisted) == 1 else 'are'} damaged (not a complete checkpoint)"
                )
            raise CheckpointNotFoundError(f"no complete checkpoint in {self.directory}")
        if step is None:
            newer = [s for s in unlisted if s > steps[-1]]
            if newer:
                raise CheckpointCorruptError(
                    f"checkpoint {self.directory / str(newer[-1])} is damaged (not a complete checkpoint; "
                    f"the last complete one is step {steps[-1]})"
                )
            return steps[-1]
        if step not in steps:
            raise CheckpointNotFoundError(f"no checkpoint for step {step} in {self.directory}; available: {steps}")
        return step

    def step_directories(self) -> list[int]:
        """Steps with a ``<step>/`` directory, complete or not (interrupted saves' temporary ones excluded)."""
        return sorted(int(p.name) for p in self.directory.iterdir() if p.is_dir() and p.name.isdigit())

    def verify(self, target, step: int) -> str | None:
        """None if checkpoint ``step`` restores exactly into ``target`` (a full read), else why not (one line)."""
        try:
            self.restore(target, step=step)
        except CheckpointError as err:
            return str(err)
        return None

    def read_meta(self, step: int | None = None) -> dict:
        """The JSON item of a checkpoint (step, config, digests, extras) without reading any array."""
        step = self._resolve_step(step)
        try:
            meta = self.manager.restore(step, args=self._ocp.args.Composite(meta=self._ocp.args.JsonRestore())).meta
        except Exception as err:  # noqa: BLE001 - any failure to read is a damaged checkpoint
            quiet_closed_loop_callbacks()
            raise CheckpointCorruptError(f"checkpoint {self.directory / str(step)} is damaged: cannot read its metadata "
                                         f"({brief(err)})") from err
        fmt = meta.get("format") if isinstance(meta, dict) else None
        if isinstance(fmt, int) and not isinstance(fmt, bool) and fmt > FORMAT and meta.get("step") == step:
            raise CheckpointError(
                f"checkpoint {self.directory / str(step)} was written by a newer shed_jax (checkpoint format {fmt}; "
                f"this version reads formats {', '.join(map(str, READABLE_FORMATS))}): update shed_jax to use it"
            )
        if not isinstance(meta, dict) or fmt not in READABLE_FORMATS or meta.get("step") != step:
            raise CheckpointCorruptError(
                f"checkpoint {self.directory / str(step)} is damaged: unexpected metadata (format "
                f"{'/'.join(map(str, READABLE_FORMATS))} and step {step} expected): {' '.join(str(meta)[:200].split())}"
            )
        return meta

    def read_config(self, step: int | None = None) -> dict:
        return self.read_meta(step)["config"]

    def read_history(self, step: int | None = None) -> dict[str, np.ndarray]:
        """The metrics history of a checkpoint (digest-checked), without reading the state."""
        step = self._resolve_step(step)
        meta = self.read_meta(step)
        where = self.directory / str(step)
        try:
            out = self.manager.restore(step, args=self._ocp.args.Composite(history=self._ocp.args.StandardRestore()))
        except Exception as err:  # noqa: BLE001
            quiet_closed_loop_callbacks()
            raise CheckpointCorruptError(f"checkpoint {where} is damaged: cannot read its metrics history ({brief(err)})") from err
        return _checked_history(out.history, meta, where)

    # ---------------------------------------------------------------- save
    def save(self, step: int, state, history: dict[str, np.ndarray], config: dict, extra: dict | None = None) -> None:
        """Save ``state`` (device arrays, not copied), ``history`` (flat ``[seeds, step, ...]``) and
        ``config`` as checkpoint ``step``. Older checkpoints beyond ``keep`` are deleted once it is
        complete. Waits for a previous asynchronous save first."""
        ocp = self._ocp
        if not isinstance(step, int) or step < 1:
            raise ValueError(f"checkpoint step must be a positive int, got {step!r}")
        storable = _storable(state)
        host = jax.device_get(storable)
        history = {k: np.asarray(v) for k, v in history.items()}
        aliases = find_aliases(_leaf_dict(host))
        meta = {
            "format": FORMAT,
            "step": step,
            "config": jsonable(config),
            "state_sha256": tree_digest(host),
            # names, dtypes and shapes (copies as the leaves they equal): tells a damaged array
            # metadata from a state of another structure
            "state_structure_sha256": structure_digest(_leaf_dict(storable)),
            "history_sha256": tree_digest(dict(sorted(history.items()))),
            "extra": jsonable(extra or {}),
        }
        self.manager.save(
            step,
            args=ocp.args.Composite(
                # the aliases travel with the arrays they describe (the state item's own metadata)
                state=ocp.args.PyTreeSave(_with_placeholders(storable, aliases), custom_metadata={"aliases": aliases},
                                          ocdbt_target_data_file_size=self.data_file_bytes),
                history=ocp.args.StandardSave(nest(history)),
                meta=ocp.args.JsonSave(meta),
            ),
            force=True,
        )

    def wait(self) -> None:
        self.manager.wait_until_finished()

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()

    def __enter__(self) -> "RunCheckpointer":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    # ---------------------------------------------------------------- restore
    def restore(self, target, step: int | None = None, config: dict | None = None, keys: Iterable[str] = COMPARED_KEYS,
                with_history: bool = True) -> Restored:
        """Restore checkpoint ``step`` (default: the latest) into the structure of ``target``.

        ``target``: a freshly built state (concrete or from ``jax.eval_shape``); its key paths,
        shapes and dtypes must equal the saved ones. ``config``: if given, the saved configuration
        must agree with it on ``keys`` (else :class:`ConfigMismatchError`).
        """
        ocp = self._ocp
        step = self._resolve_step(step)
        meta = self.read_meta(step)
        if config is not None:
            check_config(meta["config"], config, keys)
        where = self.directory / str(step)
        storable_target = _storable_target(target)
        try:
            saved_meta = self.manager.item_metadata(step)
            saved_leaves = _metadata_leaves(saved_meta["state"])
            aliases = saved_aliases(saved_meta["state"])
        except Exception as err:  # noqa: BLE001
            quiet_closed_loop_callbacks()
            raise CheckpointCorruptError(f"checkpoint {where} is damaged: cannot read the array metadata of its state "
                                         f"({brief(err)})") from err
        # a copy is described by the leaf it equals (its own entry is a scalar placeholder)
        consistent = all(n in saved_leaves and src in saved_leaves and src not in aliases and tuple(saved_leaves[n].shape) == ()
                         for n, src in aliases.items())
        if consistent:
            saved_leaves = {n: saved_leaves[aliases.get(n, n)] for n in saved_leaves}
        recorded = meta.get("state_structure_sha256")  # absent in checkpoints written before it existed
        if not saved_leaves or not consistent or (recorded is not None and structure_digest(saved_leaves) != recorded):
            raise CheckpointCorruptError(
                f"checkpoint {where} is damaged: the array metadata of its state "
                f"{'is missing or unreadable' if not saved_leaves else 'is not what was saved'} (state/_METADATA)"
            )
        target_leaves = _leaf_dict(storable_target)
        problems = []
        for name in sorted(set(saved_leaves) | set(target_leaves)):
            if name not in saved_leaves:
                problems.append(f"{name}: missing in the checkpoint")
            elif name not in target_leaves:
                problems.append(f"{name}: in the checkpoint but not in the current state")
            else:
                s, t = saved_leaves[name], target_leaves[name]
                if tuple(s.shape) != tuple(t.shape) or np.dtype(s.dtype) != np.dtype(t.dtype):
                    problems.append(f"{name}: saved {np.dtype(s.dtype).name}{list(s.shape)}, expected {np.dtype(t.dtype).name}{list(t.shape)}")
        if problems:
            more = f"; ... and {len(problems) - 20} more" if len(problems) > 20 else ""
            raise CheckpointCorruptError(
                f"checkpoint {where} does not match the run state this configuration builds "
                f"({len(problems)} leaf/leaves): " + "; ".join(problems[:20]) + more
            )
        stored_target = _with_placeholders(storable_target, aliases)
        items = {"state": ocp.args.PyTreeRestore(
            stored_target, restore_args=ocp.checkpoint_utils.construct_restore_args(stored_target))}
        if with_history:
            items["history"] = ocp.args.StandardRestore()
        try:
            out = self.manager.restore(step, args=ocp.args.Composite(**items))
        except Exception as err:  # noqa: BLE001
            quiet_closed_loop_callbacks()
            raise CheckpointCorruptError(f"checkpoint {where} is damaged: cannot read its arrays ({brief(err)})") from err
        # back through the host: orbax's arrays are committed to a device, and a jitted call on
        # committed arguments is a different executable (and persistent-cache entry) than on fresh ones
        host_state = _fill_aliases(jax.device_get(out.state), aliases)
        state = jax.tree_util.tree_map(jax.numpy.asarray, host_state)
        if tree_digest(host_state) != meta["state_sha256"]:
            raise CheckpointCorruptError(f"checkpoint {where} is damaged: the run state read back differs from what was saved "
                                         "(digest mismatch)")
        history = _checked_history(out.history, meta, where) if with_history else None
        state = _unstorable(state, target)
        if jax.tree_util.tree_structure(state) != jax.tree_util.tree_structure(target):
            raise CheckpointCorruptError(f"checkpoint {where}: restored tree structure differs from the target")
        return Restored(step=step, state=state, history=history, config=meta["config"], extra=meta.get("extra", {}))


def _leaf_dict(tree) -> dict[str, Any]:
    return {path_name(p): x for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _with_placeholders(tree, aliases: dict[str, str]):
    """``tree`` with each aliased leaf replaced by a scalar of its dtype (a ShapeDtypeStruct in a target)."""
    if not aliases:
        return tree

    def sub(path, x):
        if path_name(path) not in aliases:
            return x
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct((), x.dtype)
        return _placeholder(x.dtype)

    return jax.tree_util.tree_map_with_path(sub, tree)


def _fill_aliases(host_tree, aliases: dict[str, str]):
    """A restored host tree with each aliased leaf a copy of the leaf it equals."""
    if not aliases:
        return host_tree
    by_name = _leaf_dict(host_tree)
    return jax.tree_util.tree_map_with_path(
        lambda p, x: np.array(by_name[aliases[path_name(p)]], copy=True) if path_name(p) in aliases else x, host_tree)


def complete_steps(run_dir) -> list[int]:
    """The steps of the complete checkpoints in ``run_dir`` (empty without a ``checkpoints/`` directory)."""
    if not (pathlib.Path(run_dir) / CHECKPOINT_SUBDIR).is_dir():
        return []
    with RunCheckpointer(run_dir, create=False) as reader:
        return reader.steps()


def _checked_history(saved_tree, meta: dict, where) -> dict[str, np.ndarray]:
    """The flat metrics history of a checkpoint item, after checking it against the saved digest."""
    history = unnest(saved_tree)
    if tree_digest(dict(sorted(history.items()))) != meta["history_sha256"]:
        raise CheckpointCorruptError(f"checkpoint {where} is damaged: the metrics history read back differs from what was "
                                     "saved (digest mismatch)")
    return history


# --------------------------------------------------------------------------------------------
# the non-finite guard
# --------------------------------------------------------------------------------------------

#: metrics the loop fills on every test step (NaN on the steps LoopSpec.tests_at skips)
TEST_METRICS = ("test_return", "test_return_per_level")


def is_param_path(path) -> bool:
    """A leaf under a field/key named ``params`` or ``*_params`` (student, antagonist, adversary,
    DDPG actor/critic and targets, diffusion and its EMA); not ``hparams``."""
    names = [_key_name(k) for k in path]
    return any(n == "params" or n.endswith("_params") for n in names)


def _seeds_and_count(bad: np.ndarray) -> tuple[list[int], int]:
    seeds = np.nonzero(bad.reshape(bad.shape[0], -1).any(axis=1))[0].tolist() if bad.ndim else [0]
    return seeds, int(bad.sum())


def find_nonfinite(metrics: dict[str, np.ndarray], state=None, start_step: int = 0, tests_at=None) -> list[str]:
    """Problems that must stop a run, one line each naming the component; empty if healthy.

    ``metrics``: one chunk's flattened metrics, leaves ``[seeds, steps, ...]`` for global budget
    steps ``start_step, start_step + 1, ...``. ``state``: the vmapped state after the chunk.
    ``tests_at``: maps an array of global steps to whether the loop ran the test set there
    (``LoopSpec.tests_at``); None means at every step.

    * every floating leaf of the parameters (``is_param_path``) must be finite (NaN or Inf);
    * floating metrics must not hold +-Inf;
    * NaN in metrics marks "no value" by design (a PPO phase skipped in a PLR explore step, no
      finished training episode, no teacher reward, the test set not run at this step), so it is
      an error only in the test returns on test steps (where the loop always evaluates).
    """
    problems = []
    if state is not None:
        leaves = [(p, x) for p, x in jax.tree_util.tree_flatten_with_path(_storable(state))[0]
                  if is_param_path(p) and np.issubdtype(np.dtype(x.dtype), np.floating)]
        # one reduction per leaf on the device; only a leaf that fails comes to the host whole
        finite = jax.device_get(_all_finite([x for _, x in leaves])) if leaves else []
        for (path, x), ok in zip(leaves, finite):
            if ok:
                continue
            x = np.asarray(jax.device_get(x))
            bad = ~np.isfinite(x)
            if bad.any():
                seeds, count = _seeds_and_count(bad)
                kinds = "/".join(k for k, m in (("NaN", np.isnan(x)), ("Inf", np.isinf(x))) if m.any())
                problems.append(
                    f"{path_name(path)}: {kinds} in {count} of {x.size} values (seed(s) {seeds}) "
                    f"after budget step {start_step + _num_steps(metrics) - 1}"
                )
    for key, value in metrics.items():
        x = np.asarray(value)
        if not np.issubdtype(x.dtype, np.floating) or x.ndim < 2:
            continue
        bad = np.isinf(x)
        what = "Inf"
        if key in TEST_METRICS:
            steps = start_step + np.arange(x.shape[1])
            tested = np.ones(steps.shape, bool) if tests_at is None else np.asarray(tests_at(steps), bool)
            tested = tested.reshape((1, -1) + (1,) * (x.ndim - 2))
            bad = bad | (np.isnan(x) & tested)
            what = "NaN/Inf"
        if bad.any():
            per_step = bad.reshape(bad.shape[0], bad.shape[1], -1).any(axis=(0, 2))
            first = start_step + int(np.argmax(per_step))
            seeds, count = _seeds_and_count(bad)
            problems.append(f"metric {key}: {what} in {count} value(s) (seed(s) {seeds}), first at budget step {first}")
    return problems


@jax.jit
def _all_finite(leaves: list) -> list:
    """Per leaf, whether every value is finite: a scalar each, so a healthy state never leaves the device."""
    return [jax.numpy.isfinite(x).all() for x in leaves]


def _num_steps(metrics: dict) -> int:
    for v in metrics.values():
        v = np.asarray(v)
        if v.ndim >= 2:
            return v.shape[1]
    return 1

