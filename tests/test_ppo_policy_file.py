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


def test_a_policy_is_read_with_the_student_config_saved_beside_it(tmp_path):
    import json

    import pytest

    from shed_jax.training import policy_student, save_policy

    env = envs.make("cartpole")
    wide = PPOConfig.for_env("cartpole").replace(actor_hidden=(32,))
    student = make_student(env, wide)
    states = jax.vmap(student.init_policy)(jax.random.split(jax.random.PRNGKey(1), 2))
    path = tmp_path / "policy.msgpack"
    save_policy(path, states)
    # alone, the file is read with the preset's student, whose actor it does not fit
    with pytest.raises(ValueError, match=r"is not a policy of this student"):
        load_policy(policy_student(env, "cartpole", path), path)
    # beside the summary 'python -m shed_jax ppo' writes (its config without hparams), it is read as saved
    config = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(wide).items() if k != "hparams"}
    (tmp_path / "summary.json").write_text(json.dumps({"config": config}))
    reader = policy_student(env, "cartpole", path)
    assert reader.config.actor_hidden == (32,) and reader.config.num_envs == 1
    loaded = load_policy(reader, path)
    np.testing.assert_array_equal(loaded.params["actor"]["MLP_0"]["Dense_0"]["kernel"],
                                  states.params["actor"]["MLP_0"]["Dense_0"]["kernel"])
    (tmp_path / "summary.json").write_text(json.dumps({"config": {**config, "hidden": [8]}}))
    with pytest.raises(ValueError, match=r"summary.json: .*hidden"):
        policy_student(env, "cartpole", path)
