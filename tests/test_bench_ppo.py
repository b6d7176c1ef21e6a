"""experiments/bench_ppo.py: config overrides, early stop, and the per-chunk checkpoint that lets a
long GPU run (the walker) go on across 10-minute device calls."""
from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from experiments import bench_ppo

TINY = ["num_envs=4", "num_steps=16", "update_epochs=1", "num_minibatches=2"]


def test_parse_overrides_types_and_errors():
    o = bench_ppo.parse_overrides(["num_envs=2048", "ent_coef=0", "init_log_std=-0.5", "actor_hidden=128,128",
                                   "anneal_lr=false"])
    assert o == {"num_envs": 2048, "ent_coef": 0.0, "init_log_std": -0.5, "actor_hidden": (128, 128), "anneal_lr": False}
    cfg = bench_ppo.make_config("walker", o)
    assert (cfg.num_envs, cfg.hparams.ent_coef, cfg.init_log_std, cfg.actor_hidden) == (2048, 0.0, -0.5, (128, 128))
    assert cfg.hparams.lr == bench_ppo.make_config("walker").hparams.lr  # untouched fields keep the preset
    with pytest.raises(ValueError, match="unknown field 'foo'"):
        bench_ppo.parse_overrides(["foo=1"])
    with pytest.raises(ValueError, match="KEY=VALUE"):
        bench_ppo.parse_overrides(["num_envs"])
    with pytest.raises(ValueError, match="true or false"):
        bench_ppo.parse_overrides(["anneal_lr=maybe"])
    for item, kind in (("num_envs=abc", "an int"), ("lr=fast", "a float"), ("actor_hidden=64,x", "comma-separated ints")):
        with pytest.raises(ValueError, match=f"--ppo {item.split('=')[0]} takes {kind}, got"):  # names field and type
            bench_ppo.parse_overrides([item])


def _run(tmp_path, name, **kw):
    return bench_ppo.bench_student("cartpole", 4 * 64, 2, tmp_path, chunks=4, eval_episodes=1,
                                   overrides=bench_ppo.parse_overrides(TINY), **kw)


def test_checkpoint_resume_and_eval_only(tmp_path):
    ck = tmp_path / "ck"
    log = tmp_path / "log.jsonl"
    # stop after the first chunk (a time limit of 0 s leaves room for no second chunk)
    first = _run(tmp_path, "a", ckpt=ck, time_limit=0.0, log_path=log)
    assert first["stop_reason"].startswith("time limit") and first["env_steps_per_seed"] == 64
    from shed_jax.checkpoint import RunCheckpointer
    reader = RunCheckpointer(ck, create=False, async_save=False)
    meta = reader.read_meta()
    assert meta["step"] == 1 and reader.steps() == [1]  # chunks done; only the latest is kept

    # the restore puts exactly the saved learning state into fresh states
    _, restore, history = bench_ppo.load_checkpoint(ck, meta["config"])
    assert history[0]["episode_return"].shape[1] == 1  # one update per chunk here
    import envs
    from shed_jax.student import make_student
    student = make_student(envs.make("cartpole"), bench_ppo.make_config("cartpole", bench_ppo.parse_overrides(TINY)))
    fresh = jax.vmap(student.init)(jax.random.split(jax.random.PRNGKey(5), 2))
    restored = bench_ppo._learning_state(restore(fresh))
    saved = reader.restore(bench_ppo._learning_state(fresh), with_history=False).state
    reader.close()
    assert np.any(np.asarray(saved.ret_norm.ret) != 0)  # running returns of the cut episodes ...
    saved = saved.replace(ret_norm=saved.ret_norm.reset())  # ... restart with the freshly reset envs
    jax.tree_util.tree_map(np.testing.assert_array_equal, jax.device_get(restored), jax.device_get(saved))
    assert not np.array_equal(np.asarray(jax.tree_util.tree_leaves(fresh.params)[0]),
                              np.asarray(jax.tree_util.tree_leaves(restored.params)[0]))

    # the rest of the run continues from chunk 1 and ends with the whole curve
    rest = _run(tmp_path, "b", ckpt=ck, log_path=log)
    assert rest["resumed_from_chunk"] == 1 and rest["stop_reason"] is None
    assert rest["env_steps_per_seed"] == 4 * 64 and len(rest["curve_env_steps"]) == 4
    assert [json.loads(line)["chunk"] for line in log.read_text().splitlines()] == [0, 1, 2, 3]
    # evaluation only: nothing more is trained
    ev = _run(tmp_path, "c", ckpt=ck, eval_only=True)
    assert ev["resumed_from_chunk"] == 4 and ev["env_steps_per_seed"] == 4 * 64
    assert len(ev["final_eval_stochastic"]) == 2

    # a checkpoint of another configuration is refused, not silently restarted
    with pytest.raises(ValueError, match="another run configuration"):
        bench_ppo.bench_student("cartpole", 4 * 64, 3, tmp_path, chunks=4, eval_episodes=1,
                                overrides=bench_ppo.parse_overrides(TINY), ckpt=ck)


def test_stop_at_ends_the_run_early(tmp_path):
    r = _run(tmp_path, "s", stop_at=-1e9)  # any return passes: stop after the first chunk
    assert r["stop_reason"].startswith("median training return") and r["env_steps_per_seed"] == 64
    with pytest.raises(ValueError, match="needs a checkpoint"):
        _run(tmp_path, "e", ckpt=tmp_path / "none", eval_only=True)


def test_brax_needs_whole_rollout_minibatches():
    # the tuned continuous-lander preset: 40 envs in 32 minibatches cannot be brax minibatches
    with pytest.raises(ValueError, match="num_minibatches=8"):
        bench_ppo.bench_brax("lander-continuous", 1000, 1, None)


def test_brax_adapter_follows_our_env():
    """Brax's PPO sees our env through the adapter: same observations, rewards and done flags as
    our own step with the key the adapter carries, and the episode bookkeeping brax reads."""
    import envs

    env = envs.make("lander-continuous")
    level = env.default_params
    adapter = bench_ppo.make_brax_adapter(env, level)
    assert (adapter.observation_size, adapter.action_size) == (8, 2)
    action = jax.numpy.array([1.0, 0.0])  # main engine on

    @jax.jit
    def both(key):  # one compile for both paths (XLA shares their identical work)
        state = adapter.reset(key)
        obs0, ours = env.reset(jax.random.split(key)[0], level)

        def body(carry, _):
            state, ours = carry
            obs, ours, r, done, _ = env.step(jax.random.split(state.info["rng"])[0], ours, action, level)
            state = adapter.step(state, action)
            return (state, ours), (state.obs, obs, state.reward, r, state.done, done.astype(jax.numpy.float32))

        first_obs = state.obs
        (state, _), per_step = jax.lax.scan(body, (state, ours), None, length=5)
        return (first_obs, obs0), state, per_step

    (a_obs0, obs0), state, (a_obs, obs, a_rew, rew, a_done, done) = both(jax.random.PRNGKey(3))
    np.testing.assert_allclose(a_obs0, obs0, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(a_obs, obs, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(a_rew, rew, atol=1e-4)
    assert np.all(np.asarray(a_done) == 0.0) and np.all(np.asarray(done) == 0.0)
    assert float(state.info["episode_metrics"]["sum_reward"]) == pytest.approx(float(np.sum(rew)), abs=1e-3)
    assert float(state.info["steps"]) == 5.0 and float(state.info["truncation"]) == 0.0
