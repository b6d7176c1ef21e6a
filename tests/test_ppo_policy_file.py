"""``python -m shed_jax ppo`` writes policy.msgpack; ``load_policy`` gives back the same actions."""
import argparse

import jax
import jax.numpy as jnp
import numpy as np

import envs
from shed_jax.student import PPOConfig, make_student
from shed_jax.training import load_policy, train_fixed_level


def test_ppo_command_policy_file_round_trips(tmp_path):
    args = argparse.Namespace(env="cartpole", level=None, total_steps=2_000, seeds=2, seed=3, chunks=2,
                              eval_episodes=2, lr=None, num_envs=None, out=str(tmp_path))
    summary = train_fixed_level(args)
    # the summary is a record: where, how and when it was measured
    assert summary["command"].startswith("python -m shed_jax ") and summary["date"].endswith(" UTC")
    assert summary["device"].startswith("cpu: ")
    path = tmp_path / "policy.msgpack"
    assert path.is_file()
    env = envs.make("cartpole")
    student = make_student(env, PPOConfig.for_env("cartpole"))
    loaded = load_policy(student, path, seeds=2)
    fresh = jax.vmap(student.init_policy)(jax.random.split(jax.random.PRNGKey(0), 2))
    # training moved the parameters and the observation statistics away from a fresh init ...
    moved = jax.tree_util.tree_map(lambda a, b: float(jnp.abs(a - b).max()), loaded.params, fresh.params)
    assert max(jax.tree_util.tree_leaves(moved)) > 0
    # ... and the loaded policies score what the command's own final evaluation scored (same keys)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), args.seeds)
    eval_keys = jax.vmap(lambda k: jax.random.fold_in(k, 2))(keys)
    levels = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], env.default_params)
    ret = jax.vmap(lambda s, k: student.evaluate(s, k, levels, args.eval_episodes))(loaded, eval_keys)
    np.testing.assert_allclose(np.asarray(ret)[:, 0, :].mean(axis=1), summary["final_return_mean"], rtol=1e-6)
    # another seed count or another student's networks: refused by name, not restored at the wrong shape
    import pytest

    with pytest.raises(ValueError, match=r"\['obs_norm'\]\['count'\] has shape \(2,\), expected \(3,\) \(3 seed\(s\)\)"):
        load_policy(student, path, seeds=3)
    wide = make_student(env, PPOConfig.for_env("cartpole").replace(actor_hidden=(32,)))
    with pytest.raises(ValueError, match=r"is not a policy of this student: \['params'\]"):
        load_policy(wide, path)
