"""experiments.profile_lander: the per-kernel sums from a Perfetto trace, and the variants' programs
(the GPU timings themselves are benchmarks, docs/log/benchmarks.md "Exact contact selection and a free-flight reset")."""
import gzip
import json

import jax
import numpy as np
import pytest

import envs
from experiments import profile_lander


def _write_trace(path, events):
    path.mkdir(parents=True)
    with gzip.open(path / "perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)


def test_kernel_summary_sums_device_time_per_kernel_on_gpu_processes_only(tmp_path):
    events = [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "name": "process_name", "pid": 2, "args": {"name": "/host:CPU"}},
        {"ph": "X", "pid": 1, "name": "kernel", "dur": 10.0},
        {"ph": "X", "pid": 1, "name": "kernel", "dur": 5.5},
        {"ph": "X", "pid": 1, "name": "pad", "dur": 7.0},
        {"ph": "X", "pid": 2, "name": "host_work", "dur": 1000.0},  # host time is not device time
        {"ph": "i", "pid": 1, "name": "marker"},  # instants carry no duration
    ]
    _write_trace(tmp_path / "plugins" / "profile" / "run", events)
    rows = profile_lander.kernel_summary(str(tmp_path))
    assert rows == [dict(name="kernel", total_us=15.5, count=2), dict(name="pad", total_us=7.0, count=1)]
    assert profile_lander.kernel_summary(str(tmp_path / "nothing")) == []


def test_reset_env_variant_starts_a_fresh_episode_in_every_slot():
    env = envs.make("lander")
    batch, steps = 4, 3
    levels = env.param_space.sample(jax.random.PRNGKey(1), (batch,))
    obs, state = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch), levels)
    run, _ = profile_lander.make_variant(env, "reset_env", batch, steps)
    o, s, total = run(jax.random.PRNGKey(2), obs, state)
    # every slot holds a fresh episode at step 0, whatever state came before
    np.testing.assert_array_equal(np.asarray(s.time), 0)
    assert np.isfinite(float(total))
    with pytest.raises(ValueError, match="unknown variant"):
        profile_lander.make_variant(env, "nope", batch, steps)


def test_tf32_check_reports_equal_rollouts_where_float32_matmuls_are_exact():
    from experiments import tf32_check

    row = tf32_check.check("cartpole", batch=4, steps=5)
    if jax.default_backend() == "cpu":  # CPU float32 products are float32 at every precision
        assert row["bitwise_equal"] and row["max_abs_obs_diff"] == 0.0 and row["first_step_over_tol"] is None
    assert row["steps"] == 5 and row["s_per_step_default"] > 0 and row["s_per_step_highest"] > 0
