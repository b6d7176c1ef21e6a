"""The checkpoint's storage: copies stored once, data files below the size target, zstd on disk,
format 1 checkpoints still restore and newer formats are refused in one line.

Small hand-made states saved with :class:`shed_jax.checkpoint.RunCheckpointer` (no run, nothing
compiled); the resume of real runs is tests/test_checkpoint.py's and tests/test_run_cli.py's.
"""
import json
import pathlib
import shutil

import jax
import numpy as np
import pytest
from flax import struct

from shed_jax import checkpoint as ck


@struct.dataclass
class Nets:
    params: dict
    ema_params: dict
    mu: dict
    nu: dict
    key: jax.Array
    step: jax.Array


def make_state(seed: int = 0, width: int = 64) -> Nets:
    rng = np.random.default_rng(seed)
    params = {"kernel": rng.normal(size=(3, width, width)).astype(np.float32),
              "bias": np.array([[0.0, -0.0, np.nan]] * 3, np.float32)}
    zeros = jax.tree_util.tree_map(np.zeros_like, params)
    return Nets(
        params=params,
        ema_params=jax.tree_util.tree_map(np.copy, params),  # equal bytes: stored once
        mu=zeros,
        nu=jax.tree_util.tree_map(np.copy, zeros),  # equal to mu
        key=jax.random.split(jax.random.PRNGKey(seed), 3),  # raw uint32 keys, as the run state holds them
        step=np.int32(7),
    )


def target_of(state):
    return jax.eval_shape(lambda s: s, state)


def save(run_dir, state, step: int = 1, history=None, **kw):
    history = {"loss": np.arange(6, dtype=np.float32).reshape(3, 2)} if history is None else history
    with ck.RunCheckpointer(run_dir, keep=1, async_save=False, **kw) as writer:
        writer.save(step, state, history, {"experiment": {"x": 1}, "seeds": 3, "root_seed": 0})
    return pathlib.Path(run_dir) / ck.CHECKPOINT_SUBDIR / str(step)


def disk_bytes(path) -> int:
    return sum(f.stat().st_size for f in pathlib.Path(path).rglob("*") if f.is_file())


def assert_bitwise(a, b):
    la, lb = jax.tree_util.tree_flatten_with_path(ck._storable(a))[0], jax.tree_util.tree_leaves(ck._storable(b))
    assert len(la) == len(lb)
    for (path, x), y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, ck.path_name(path)
        assert x.tobytes() == y.tobytes(), ck.path_name(path)


def test_find_aliases_is_bitwise_and_skips_scalars():
    z = np.zeros(4, np.float32)
    leaves = {"a": z, "b": z.copy(), "c": -z, "d": z.astype(np.float64), "e": z.reshape(2, 2),
              "f": np.array([np.nan, 1.0], np.float32), "g": np.array([np.nan, 1.0], np.float32),
              "s": np.float32(0.0), "t": np.float32(0.0)}
    # -0.0 differs from 0.0 in its bytes, float64 zeros and another shape are other leaves, NaNs of
    # equal bytes are copies, one-element leaves never alias (their placeholder is a scalar)
    assert ck.find_aliases(leaves) == {"b": "a", "g": "f"}


def test_copies_are_stored_once_and_restore_bitwise(tmp_path):
    state = make_state()
    step_dir = save(tmp_path / "run", state)
    assert json.loads((step_dir / "meta" / "metadata").read_text())["format"] == ck.FORMAT == 2
    with ck.RunCheckpointer(tmp_path / "run", create=False) as reader:
        item = reader.manager.item_metadata(1)["state"]
        saved = ck._metadata_leaves(item)
        restored = reader.restore(target_of(state))
    # the first leaf in name order is stored, the later equal ones point to it
    assert ck.saved_aliases(item) == {"params.bias": "ema_params.bias", "params.kernel": "ema_params.kernel",
                                      "nu.bias": "mu.bias", "nu.kernel": "mu.kernel"}
    assert tuple(saved["params.kernel"].shape) == () and tuple(saved["ema_params.kernel"].shape) == (3, 64, 64)
    assert_bitwise(restored.state, state)
    assert restored.state.params["kernel"] is not restored.state.ema_params["kernel"]
    np.testing.assert_array_equal(restored.history["loss"], np.arange(6, dtype=np.float32).reshape(3, 2))


def test_a_copy_costs_nothing_on_disk_and_zeros_compress(tmp_path):
    rng = np.random.default_rng(1)
    w = rng.normal(size=(4, 256, 256)).astype(np.float32)  # 1 MiB of incompressible floats
    alone = disk_bytes(save(tmp_path / "alone", {"w": w}))
    twice = disk_bytes(save(tmp_path / "twice", {"w": w, "w_copy": w.copy()}))
    zeros = disk_bytes(save(tmp_path / "zeros", {"w": w, "z": np.zeros_like(w)}))
    other = disk_bytes(save(tmp_path / "other", {"w": w, "v": rng.normal(size=w.shape).astype(np.float32)}))
    assert alone > 0.8 * w.nbytes  # random floats: zstd saves little
    assert twice - alone < 4096  # the copy is a placeholder and a name
    assert zeros - alone < 0.02 * w.nbytes  # zstd (orbax's default) stores zeros in almost nothing
    assert other - alone > 0.8 * w.nbytes  # a leaf that is no copy is stored in full


def test_data_files_stay_near_the_target_size(tmp_path):
    rng = np.random.default_rng(2)
    state = {f"layer{i}": rng.normal(size=(4, 128, 128)).astype(np.float32) for i in range(8)}  # 8 x 256 KiB
    target = 512 * 1024
    step_dir = save(tmp_path / "run", state, data_file_bytes=target)
    data = [f.stat().st_size for f in (step_dir / "state").rglob("d/*") if f.is_file()]
    assert sum(data) > 1.8 * 2**20 and len(data) >= 4
    assert max(data) <= 2 * target  # at most one chunk over the target
    # the default keeps every file of a checkpoint well under a 16 MiB per-file transfer limit
    assert 2 * ck.DATA_FILE_BYTES <= 16 * 2**20
    with ck.RunCheckpointer(tmp_path / "run", create=False) as reader:
        assert_bitwise(reader.restore(target_of(state)).state, state)
    with pytest.raises(ValueError, match="data_file_bytes must be a positive int"):
        ck.RunCheckpointer(tmp_path / "x", data_file_bytes=0)


def save_format_1(run_dir, state, history, config, step: int = 1):
    """A checkpoint as format 1 wrote it: the state through orbax's StandardCheckpointHandler, every
    leaf stored, no aliases."""
    import orbax.checkpoint as ocp

    storable = ck._storable(state)
    meta = {"format": 1, "step": step, "config": ck.jsonable(config), "state_sha256": ck.tree_digest(storable),
            "state_structure_sha256": ck.structure_digest(ck._leaf_dict(storable)),
            "history_sha256": ck.tree_digest(dict(sorted(history.items()))), "extra": {"wall_s": 3.0}}
    handlers = {"state": ocp.StandardCheckpointHandler(), "history": ocp.StandardCheckpointHandler(),
                "meta": ocp.JsonCheckpointHandler()}
    options = ocp.CheckpointManagerOptions(max_to_keep=3, create=True, enable_async_checkpointing=False)
    with ocp.CheckpointManager((pathlib.Path(run_dir) / ck.CHECKPOINT_SUBDIR).absolute(), options=options,
                               item_handlers=handlers) as manager:
        manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(storable),
                                                   history=ocp.args.StandardSave(ck.nest(history)),
                                                   meta=ocp.args.JsonSave(meta)))
        manager.wait_until_finished()


def test_format_1_restores_and_a_newer_format_is_refused_in_one_line(tmp_path):
    state = make_state(3)
    history = {"loss": np.ones((3, 2), np.float32), "info/levels": np.zeros((3, 2, 4), np.float32)}
    save_format_1(tmp_path / "old", state, history, {"experiment": {"x": 1}, "seeds": 3, "root_seed": 0})
    with ck.RunCheckpointer(tmp_path / "old", create=False) as reader:
        assert reader.read_meta()["format"] == 1
        restored = reader.restore(target_of(state), config={"experiment": {"x": 1}, "seeds": 3, "root_seed": 0})
        assert reader.verify(target_of(state), 1) is None
    assert_bitwise(restored.state, state)
    assert restored.extra == {"wall_s": 3.0} and set(restored.history) == set(history)
    # a format written by a later version
    step_dir = save(tmp_path / "new", state)
    meta_file = step_dir / "meta" / "metadata"
    meta_file.write_text(json.dumps({**json.loads(meta_file.read_text()), "format": ck.FORMAT + 1}))
    with ck.RunCheckpointer(tmp_path / "new", create=False) as reader:
        with pytest.raises(ck.CheckpointError, match=r"written by a newer shed_jax \(checkpoint format 3; this version "
                                                      r"reads formats 1, 2\): update shed_jax") as info:
            reader.restore(target_of(state))
    assert "\n" not in str(info.value) and not isinstance(info.value, ck.CheckpointCorruptError)


def test_the_aliases_travel_with_their_arrays(tmp_path):
    """Step 1's state item (with copies) under step 2's metadata (another state, no copies) reads as
    the arrays of another save, not as damaged array metadata: the aliases come with the arrays."""
    rng = np.random.default_rng(5)
    with_copies = {"a": rng.normal(size=(8, 8)).astype(np.float32)}
    with_copies["b"] = with_copies["a"].copy()
    other = {"a": rng.normal(size=(8, 8)).astype(np.float32), "b": rng.normal(size=(8, 8)).astype(np.float32)}
    with ck.RunCheckpointer(tmp_path / "run", keep=2, async_save=False) as writer:
        for step, state in ((1, with_copies), (2, other)):
            writer.save(step, state, {"x": np.zeros((1, step), np.float32)}, {})
    directory = tmp_path / "run" / ck.CHECKPOINT_SUBDIR
    shutil.rmtree(directory / "2" / "state")
    shutil.copytree(directory / "1" / "state", directory / "2" / "state")
    with ck.RunCheckpointer(tmp_path / "run", create=False) as reader:
        with pytest.raises(ck.CheckpointCorruptError, match="checkpoints/2 is damaged: the run state read back differs "
                                                           "from what was saved \\(digest mismatch\\)"):
            reader.restore(target_of(other))
        assert_bitwise(reader.restore(target_of(other), step=1).state, with_copies)


def test_a_changed_structure_is_named_through_a_copy(tmp_path):
    state = make_state(4)
    save(tmp_path / "run", state)
    bigger = make_state(4, width=32)
    with ck.RunCheckpointer(tmp_path / "run", create=False) as reader:
        # params.kernel is stored as a copy of ema_params.kernel: the message gives its real shape
        with pytest.raises(ck.CheckpointCorruptError, match=r"params\.kernel: saved float32\[3, 64, 64\], "
                                                              r"expected float32\[3, 32, 32\]"):
            reader.restore(target_of(bigger))


def test_checkpoint_size_counts_bytes_per_subtree():
    from experiments.checkpoint_size import compressed_bytes, leaf_bytes, subtree_bytes

    shapes = {"a": {"x": jax.ShapeDtypeStruct((5, 4), np.float32), "y": jax.ShapeDtypeStruct((3,), np.int8)},
              "b": jax.ShapeDtypeStruct((2,), np.int16)}
    leaves = leaf_bytes(shapes)
    assert leaves == {"a.x": 80, "a.y": 3, "b": 4}
    assert subtree_bytes(leaves, 1) == {"a": 83, "b": 4}
    rng = np.random.default_rng(6)
    w = rng.normal(size=(64, 64)).astype(np.float32)
    packed = compressed_bytes({"w": w, "w_copy": w.copy(), "z": np.zeros((64, 64), np.float32)})
    assert packed["w_copy"] == 0  # stored once, as the checkpoint does
    assert packed["w"] > 0.8 * w.nbytes and packed["z"] < 0.05 * w.nbytes
