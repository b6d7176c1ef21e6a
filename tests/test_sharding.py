"""Sharding a vmapped batch of runs over devices: padding helpers, and a tiny vmapped loop on 4
virtual CPU devices (a subprocess, since the device count is fixed when JAX starts) that must give
the same numbers sharded and unsharded, with its outputs spread over the 4 devices."""
import json
import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from shed_jax import sharding
from shed_jax.xla_cpu import with_flag

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_padding_helpers():
    assert [sharding.padded_size(n, 4) for n in (1, 4, 5, 8)] == [4, 4, 8, 8]
    tree = {"a": np.arange(6).reshape(3, 2), "b": jnp.asarray([1.0, 2.0, 3.0])}
    padded, n = sharding.pad_batch(tree, 4)
    assert n == 3
    np.testing.assert_array_equal(padded["a"], [[0, 1], [2, 3], [4, 5], [4, 5]])  # the last run repeated
    np.testing.assert_array_equal(padded["b"], [1.0, 2.0, 3.0, 3.0])
    assert isinstance(padded["a"], np.ndarray) and isinstance(padded["b"], jax.Array)
    back = sharding.unpad(padded, n)
    np.testing.assert_array_equal(back["a"], tree["a"])
    same, n = sharding.pad_batch(tree, 3)
    assert n == 3 and same is tree  # divisible: untouched
    with pytest.raises(ValueError, match=r"a batch of 3 runs does not divide over 4 devices; use a multiple of 4 \(e.g. 4\)"):
        sharding.pad_batch(tree, 4, pad=False)
    with pytest.raises(ValueError, match="disagree on the leading axis: sizes \\[2, 3\\]"):
        sharding.batch_size({"a": np.zeros(3), "b": np.zeros(2)})
    with pytest.raises(ValueError, match=r"batch leaf \['s'\] is a scalar"):
        sharding.batch_size({"s": np.float32(1.0)})


def test_one_device_mesh_is_the_plain_vmap():
    mesh = sharding.batch_mesh(jax.devices()[:1])
    assert mesh.axis_names == ("batch",) and mesh.size == 1
    x = sharding.put_batch(np.arange(6.0).reshape(3, 2), mesh)
    y = sharding.sharded_init(lambda v: v * 2.0, mesh)(x)
    np.testing.assert_array_equal(sharding.to_host(y), np.arange(6.0).reshape(3, 2) * 2.0)
    assert sharding.devices_of(y) == {jax.devices()[0]}


_SCRIPT = textwrap.dedent(
    """
    import dataclasses, json, time
    t0 = time.time()
    import jax, jax.numpy as jnp, numpy as np
    import envs
    from shed_jax import sharding
    from shed_jax.loop import LoopSpec, make_run
    from shed_jax.methods.base import StepInfo
    from shed_jax.student import PPOConfig, PPOHyperparams, make_student

    assert jax.device_count() == 4, jax.devices()

    @dataclasses.dataclass(frozen=True)
    class Uniform:  # one PPO update per budget step on 2 uniform levels
        env: object
        student: object
        name: str = "uniform"

        def init(self, key):
            return {"calls": jnp.zeros((), jnp.int32)}

        def begin_episode(self, key, m, s):
            return m, s

        def step(self, key, m, s):
            k_lv, k_tr = jax.random.split(key)
            vec = self.env.param_space.sample_vector(k_lv, (2,))
            s, _ = self.student.train(s, k_tr, self.env.param_space.from_vector(vec), 1)
            info = StepInfo(levels=vec, env_steps_train=jnp.int32(32), env_steps_eval=jnp.int32(0),
                            teacher_reward=jnp.float32(jnp.nan), num_new_levels=jnp.int32(2))
            return {"calls": m["calls"] + 1}, s, info

    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole", num_envs=4, num_steps=8, update_epochs=1, num_minibatches=1))
    init, run = make_run(student, Uniform(env, student), env.param_space.sample(jax.random.PRNGKey(7), (2,)),
                         LoopSpec(steps_per_episode=2, num_episodes=1, test_episodes=1, test_max_steps=20))
    keys = np.asarray(jax.random.split(jax.random.PRNGKey(0), 4))
    hps = PPOHyperparams.stack([PPOHyperparams(lr=lr) for lr in (1e-4, 3e-4, 1e-3, 3e-3)])  # a swept hyperparameter
    hps = jax.tree_util.tree_map(np.asarray, hps)

    # unsharded: the run CLI's jit(vmap(...)) on the default device
    t1 = time.time()
    ref_state = jax.jit(jax.vmap(init))(keys, hps)
    ref_state, ref_m = jax.jit(jax.vmap(run, in_axes=(0, None, None)), static_argnums=1)(ref_state, 2, 0)
    jax.block_until_ready(ref_m)
    t2 = time.time()

    mesh = sharding.batch_mesh()
    init_s, run_s = sharding.sharded_init(init, mesh), sharding.sharded_run(run, mesh)
    state = init_s(*sharding.put_batch((keys, hps), mesh))
    state, m = run_s(state, 2, 0)
    jax.block_until_ready(m)
    t3 = time.time()

    # a batch of 3 padded to 4 (the padded run repeats run 2) through the same compiled program
    padded, n = sharding.pad_batch((keys[:3], jax.tree_util.tree_map(lambda x: x[:3], hps)), mesh.size)
    p_state, p_m = run_s(init_s(*sharding.put_batch(padded, mesh)), 2, 0)
    p_m = sharding.unpad(sharding.to_host(p_m), n)

    def maxdiff(a, b):
        la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
        assert len(la) == len(lb)
        return max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)), initial=0.0)) for x, y in zip(la, lb))

    host = lambda t: sharding.to_host(t)
    print(json.dumps({
        "devices": sorted(d.id for d in sharding.devices_of((state, m))),
        "spec_is_batch": all(x.sharding.spec == jax.sharding.PartitionSpec("batch") for x in jax.tree_util.tree_leaves((state, m))),
        "shard_rows": sorted({s.data.shape[0] for s in jax.tree_util.tree_leaves(state)[0].addressable_shards}),
        "state_maxdiff": maxdiff(host(state), host(ref_state)),
        "metrics_maxdiff": maxdiff(host(m), host(ref_m)),
        "padded_maxdiff": maxdiff(p_m, jax.tree_util.tree_map(lambda x: np.asarray(x)[:3], host(ref_m))),
        "padded_n": n,
        "test_return": np.asarray(host(m)["test_return"]).tolist(),
        "compiles": run_s._cache_size(),
        "seconds": {"setup": t1 - t0, "unsharded": t2 - t1, "sharded": t3 - t2},
    }))
    """
)


def test_sharded_loop_on_four_devices_equals_unsharded():
    # the suite's XLA:CPU guard and compile flags (tests/conftest.py), plus four virtual devices
    env = {**os.environ, "XLA_FLAGS": with_flag(os.environ.get("XLA_FLAGS", ""), "--xla_force_host_platform_device_count=4"),
           "JAX_PLATFORMS": "cpu",
           "PYTHONPATH": str(ROOT), "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
           # the suite's persistent compilation cache (tests/conftest.py), so reruns skip the two compiles
           "JAX_COMPILATION_CACHE_DIR": str(ROOT / ".cache" / "jax"), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "1"}
    proc = subprocess.run([sys.executable, "-c", _SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == [0, 1, 2, 3]  # state and metrics live on all 4 devices
    assert out["spec_is_batch"]  # every leaf split along its leading (run) axis
    assert out["shard_rows"] == [1]  # 4 runs -> one per device
    assert out["state_maxdiff"] <= 1e-6 and out["metrics_maxdiff"] <= 1e-6, out
    assert out["padded_n"] == 3 and out["padded_maxdiff"] <= 1e-6, out
    assert out["compiles"] == 1  # the padded batch reused the program
    tr = np.asarray(out["test_return"])  # [4 runs, 2 steps]; CartPole pays 1 per step
    assert tr.shape == (4, 2) and np.all(tr >= 1.0)
