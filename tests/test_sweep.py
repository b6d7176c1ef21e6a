"""Sweeps: grid parsing and grouping (pure functions on hand cases), SHED's dynamic hyperparameters
(vmapping over eta equals separate runs; psi's mixed-batch split), and a tiny end-to-end sweep that
writes the run CLI's files.

The SHED runs here use a stub student (no networks: training pulls a skill vector toward the levels,
returns measure the distance to the evaluation levels) so that what compiles is the teacher -- the
part these hyperparameters act on -- and each test stays well under a minute on two shared CPU
cores. SHED with the real PPO student is tests/test_shed_method.py; the real student under the
vmapped, sharded loop is tests/test_sharding.py.
"""
import dataclasses
import json
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

import envs
from shed_jax import driver, sharding, sweep
from shed_jax.cli import sweep as sweep_cli
from shed_jax.loop import LoopSpec
from shed_jax.methods.hierarchical import HMDPConfig, TeacherHyperparams, make_hmdp
from shed_jax.methods.shed import SHEDConfig, SHEDHyperparams, make_shed
from shed_jax.presets import Experiment
from shed_jax.runtime import source_commit
from shed_jax.student.config import PPOConfig, PPOHyperparams
from shed_jax.teacher.buffers import Transition, buffer_add_many, buffer_init, make_transition, sample_mixed
from shed_jax.teacher.reward import coefficient_of_variation, zscore_mixed

TINY_TEACHER = dict(updates_per_step=1, num_eval_episodes=1, eval_max_steps=8, budget_steps=3, ddpg_batch=4, real_capacity=16,
                    ddpg_threshold=1)
TINY = dict(**TINY_TEACHER, syn_capacity=16, diffusion_threshold=1, diffusion_steps=2, num_syn=2, syn_threshold=2)
SHED_SPACE = sweep.KeySpace(
    method="shed", method_hparams=("eta", "psi", "actor_lr"), student_hparams=("lr", "ent_coef"),
    method_config=("num_eval_levels", "psi", "updates_per_step"), student_config=("num_envs",),
)
HMDP_SPACE = dataclasses.replace(SHED_SPACE, method="hmdp", method_hparams=("eta", "actor_lr"),
                                 method_config=("num_eval_levels", "updates_per_step"))
DR_SPACE = sweep.KeySpace(method="dr", student_hparams=("lr",), method_config=("num_levels",), student_config=("num_envs",))


# ---- parsing and planning ------------------------------------------------------------------

def test_parse_grid_values_and_errors():
    grid = sweep.parse_grid(["eta=0,10", "psi=0.25, 0.5", "low=[1,2],[3,4]", "sampler=ddim,ancestral", "ppo.lr=1e-4"])
    assert grid == {"eta": [0, 10], "psi": [0.25, 0.5], "low": [[1, 2], [3, 4]], "sampler": ["ddim", "ancestral"],
                    "ppo.lr": [1e-4]}
    assert list(grid) == ["eta", "psi", "low", "sampler", "ppo.lr"]  # order kept: first key slowest
    with pytest.raises(ValueError, match="KEY=V1"):
        sweep.parse_grid(["eta"])
    with pytest.raises(ValueError, match="given twice"):
        sweep.parse_grid(["eta=0", "eta=1"])
    with pytest.raises(ValueError, match="lists 0 twice"):
        sweep.parse_grid(["eta=0,0"])
    with pytest.raises(ValueError, match="empty value"):
        sweep.parse_grid(["eta=0,,1"])
    assert sweep.split_top_level('0,[1,2],"a,b",{"x":1,"y":2}') == ["0", "[1,2]", '"a,b"', '{"x":1,"y":2}']


def test_expand_and_names():
    pts = sweep.expand_grid({"a": [1, 2], "b": [3, 4]})
    assert pts == [{"a": 1, "b": 3}, {"a": 1, "b": 4}, {"a": 2, "b": 3}, {"a": 2, "b": 4}]
    assert sweep.expand_grid({}) == [{}]
    assert sweep.point_name({"eta": 0, "psi": 0.25}) == "eta=0,psi=0.25"
    assert sweep.point_name({}) == "default"
    assert sweep.dir_name('low=[1, 2],s="a/b"') == "low=_1,_2_,s=_a_b_"


def test_classify():
    assert sweep.classify("eta", SHED_SPACE) == ("method_hparam", "eta")
    assert sweep.classify("psi", SHED_SPACE) == ("method_hparam", "psi")  # dynamic wins over the config field
    assert sweep.classify("num_eval_levels", SHED_SPACE) == ("method_config", "num_eval_levels")
    assert sweep.classify("ppo.lr", SHED_SPACE) == ("student_hparam", "lr")
    assert sweep.classify("ppo.num_envs", SHED_SPACE) == ("student_config", "num_envs")
    # h-MDP has no psi (no synthesiser): an unknown key like any other, one line naming the method
    with pytest.raises(ValueError, match=r"^method 'hmdp' has no hyperparameter or config field 'psi'; known keys: actor_lr, eta, "):
        sweep.classify("psi", HMDP_SPACE)
    with pytest.raises(ValueError, match=r"method 'dr' has no hyperparameter or config field 'eta'.*known keys: num_levels, ppo.lr"):
        sweep.classify("eta", DR_SPACE)
    with pytest.raises(ValueError, match=r"write ppo.lr"):
        sweep.classify("lr", SHED_SPACE)
    with pytest.raises(ValueError, match="student has no hyperparameter or config field 'bogus'"):
        sweep.classify("ppo.bogus", SHED_SPACE)


def test_plan_groups_dynamic_points_and_splits_static():
    grid = {"eta": [0, 10], "num_eval_levels": [5, 10], "ppo.lr": [1e-4]}
    groups, notes = sweep.plan(SHED_SPACE, grid, {"psi": 0.5, "ppo.num_envs": 8})
    assert notes == []
    assert len(groups) == 2  # one per static value of num_eval_levels
    g5, g10 = groups
    assert g5.method_config == {"num_eval_levels": 5} and g10.method_config == {"num_eval_levels": 10}
    assert g5.student_config == {"num_envs": 8}  # --set statics reach every group
    assert [p.name for p in g5.points] == ["eta=0,num_eval_levels=5,ppo.lr=0.0001", "eta=10,num_eval_levels=5,ppo.lr=0.0001"]
    assert [p.method_hparams for p in g5.points] == [{"psi": 0.5, "eta": 0}, {"psi": 0.5, "eta": 10}]
    assert [p.student_hparams for p in g10.points] == [{"lr": 1e-4}, {"lr": 1e-4}]
    assert g5.label == "shed[num_eval_levels=5,ppo.num_envs=8]"


def test_the_table_names_dynamic_set_values_that_neither_label_nor_point_shows():
    groups, _ = sweep.plan(SHED_SPACE, {"eta": [0, 10]}, {"psi": 0.5, "ppo.lr": 1e-4, "num_eval_levels": 5})
    (g,) = groups
    assert [sweep.fixed_values(p) for p in g.points] == [{"psi": 0.5, "ppo.lr": 1e-4}] * 2  # not eta: the point's name
    rows = [{"group": g.label, "point": p.name, "final_test_return_mean": 1.0, "final_test_return_se": 0.5,
             "seeds": 2, "set": sweep.fixed_values(p)} for p in g.points]
    lines = sweep.table(rows).splitlines()
    assert lines[0].endswith("| seeds | also set |")
    assert lines[2] == "| shed[num_eval_levels=5] | eta=0 | 1.00 ± 0.50 | 2 | psi=0.5,ppo.lr=0.0001 |"
    assert "also set" not in sweep.table([dict(rows[0], set={})])  # without --set values: the old table


def test_plan_refuses_a_key_the_method_lacks():
    with pytest.raises(ValueError, match="method 'hmdp' has no hyperparameter or config field 'psi'"):
        sweep.plan(HMDP_SPACE, {"eta": [0, 10], "psi": [0.25, 0.5]})
    groups, notes = sweep.plan(HMDP_SPACE, {"eta": [0, 10]})
    assert notes == [] and len(groups) == 1
    assert [p.name for p in groups[0].points] == ["eta=0", "eta=10"]
    assert [p.method_hparams for p in groups[0].points] == [{"eta": 0}, {"eta": 10}]
    groups, _ = sweep.plan(SHED_SPACE, {"eta": [0, 10], "psi": [0.25, 0.5]})
    assert len(groups) == 1 and len(groups[0].points) == 4
    # no grid at all: one default point
    groups, _ = sweep.plan(DR_SPACE, {})
    assert [p.name for p in groups[0].points] == ["default"] and groups[0].method_config == {}
    with pytest.raises(ValueError, match="method 'dr'"):
        sweep.plan(DR_SPACE, {"ppo.lr": [1e-3]}, {"eta": 1})


# ---- SHED's dynamic hyperparameters ----------------------------------------------------------

@struct.dataclass
class _StubState:
    skill: jax.Array  # [d] in the box's unit coordinates
    hparams: Any  # PPOHyperparams (the loop re-initialises students with their hyperparameters)


@dataclasses.dataclass(frozen=True)
class _StubConfig:
    num_envs: int = 5


@dataclasses.dataclass(frozen=True)
class _StubStudent:
    """The student interface SHED and the loop use, without networks.

    Each update moves the skill 20 % toward the mean of the trained levels (unit coordinates) plus
    noise; the return of an episode on a level is 100 - 30 * |skill - level|_1 plus noise.
    """

    env: Any
    config: _StubConfig = _StubConfig()
    env_steps_per_update: int = 20
    train_envs: int = 4  # the driver pads GPU kernels to it (no kernels here)

    def init(self, key, hparams=None):
        hp = PPOHyperparams().as_arrays() if hparams is None else jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), hparams)
        return _StubState(skill=jax.random.uniform(key, (self.env.param_space.dim,), minval=-1.0, maxval=1.0), hparams=hp)

    def _unit(self, levels):
        space = self.env.param_space
        return space.to_unit(space.to_vector(levels))

    def train(self, state, key, levels, num_updates):
        def one(skill, k):
            skill = skill + 0.2 * (jnp.mean(self._unit(levels), axis=0) - skill) + 0.05 * jax.random.normal(k, skill.shape)
            return skill, jnp.sum(skill)

        skill, loss = jax.lax.scan(one, state.skill, jax.random.split(key, num_updates))
        return state.replace(skill=skill), {"loss": loss}

    def evaluate_with_info(self, state, key, levels, num_episodes, max_steps=None, deterministic=False):
        dist = jnp.sum(jnp.abs(self._unit(levels) - state.skill), axis=-1)  # [n]
        rets = 100.0 - 30.0 * dist[:, None] + jax.random.normal(key, (dist.shape[0], num_episodes))
        return rets, {"env_steps": dist.shape[0] * num_episodes * 8, "lengths": jnp.full(rets.shape, 8, jnp.int32)}

    def evaluate(self, state, key, levels, num_episodes, max_steps=None, deterministic=False):
        return self.evaluate_with_info(state, key, levels, num_episodes, max_steps, deterministic)[0]


def _cartpole(num_envs=5):
    env = envs.make("cartpole")
    return env, _StubStudent(env, _StubConfig(num_envs)), env.param_space.sample(jax.random.PRNGKey(42), (10,))


def test_hparams_defaults_validation_and_init():
    env, student, ev = _cartpole()
    cfg = SHEDConfig(**TINY, psi=0.5, explore_sigma=0.2, actor_lr=3e-4)
    method = make_shed(env, student, cfg, eval_levels=ev)
    assert method.default_hparams == SHEDHyperparams(eta=0.05, psi=0.5, actor_lr=3e-4, critic_lr=1e-3, explore_sigma=0.2)
    hp = SHEDHyperparams(eta=10.0, psi=0.25, actor_lr=2e-4)
    m = jax.jit(method.init)(jax.random.PRNGKey(0), hp)
    assert float(m.hparams.eta) == 10.0 and float(m.hparams.psi) == 0.25
    assert float(m.ddpg.actor_opt_state.hyperparams["learning_rate"]) == pytest.approx(2e-4)
    assert float(m.ddpg.critic_opt_state.hyperparams["learning_rate"]) == pytest.approx(1e-3)
    m2 = jax.jit(lambda k, h: method.with_hparams(method.init(k), h))(jax.random.PRNGKey(0), hp)
    for a, b in zip(jax.tree_util.tree_leaves(m), jax.tree_util.tree_leaves(m2)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match=r"SHEDHyperparams.psi must be a finite value in \[0.0, 1.0\]"):
        method.init(jax.random.PRNGKey(0), SHEDHyperparams(psi=1.5))
    with pytest.raises(ValueError, match="actor_lr"):
        SHEDHyperparams.stack([SHEDHyperparams(actor_lr=0.0)])
    with pytest.raises(ValueError, match="SHEDConfig.critic_lr"):
        SHEDConfig(critic_lr=-1.0)
    hmdp = make_hmdp(env, student, HMDPConfig(**TINY_TEACHER), eval_levels=ev)
    assert hmdp.hparam_names == ("eta", "actor_lr", "critic_lr", "explore_sigma")
    assert hmdp.default_hparams == TeacherHyperparams(eta=0.05, actor_lr=1e-3, critic_lr=1e-3, explore_sigma=0.1)


def test_mixed_batch_real_part_follows_dynamic_psi():
    env, student, ev = _cartpole()
    ex = make_transition(3, 2)
    items = lambda r: Transition(s=jnp.zeros((4, 3)), u=jnp.zeros((4, 2)), r=jnp.full((4,), r), s_next=jnp.zeros((4, 3)), done=jnp.zeros(4))
    real = buffer_add_many(buffer_init(ex, 8), items(1.0))
    syn = buffer_add_many(buffer_init(ex, 8), items(2.0))
    psis = jnp.asarray([0.0, 0.25, 0.75, 0.3, 1.0])
    batch, mask = jax.jit(jax.vmap(lambda p: sample_mixed(real, syn, jax.random.PRNGKey(0), 32, p)))(psis)
    expect = [0, 8, 24, 9, 32]  # floor(psi * 32): the official 24 + 8 at psi = 0.75
    np.testing.assert_array_equal(np.asarray(mask).sum(axis=1), expect)
    for i, n in enumerate(expect):  # real items first, then synthetic ones
        np.testing.assert_array_equal(np.asarray(batch.r[i]), [1.0] * n + [2.0] * (32 - n))
    # per-part z-scoring: each part has mean 0 (a constant part maps to 0)
    r = jnp.asarray([1.0, 2.0, 3.0, 10.0, 30.0])
    z = np.asarray(zscore_mixed(r, jnp.asarray([True, True, True, False, False])))
    np.testing.assert_allclose(z, [-1.2247, 0.0, 1.2247, -1.0, 1.0], atol=1e-4)


def _method_run(method, student, steps):
    def run(key, hp):
        k_m, k_s, k_b, k_run = jax.random.split(key, 4)
        m = method.init(k_m, hp)
        m, s = method.begin_episode(k_b, m, student.init(k_s))
        s0 = m.s

        def body(carry, k):
            m, s = carry
            m, s, info = method.step(k, m, s)
            return (m, s), info

        (m, s), infos = jax.lax.scan(body, (m, s), jax.random.split(k_run, steps))
        return m, s0, infos

    return run


def test_vmap_over_eta_equals_separate_runs():
    # h-MDP: the same teacher code path as SHED minus the diffusion model (which compiles slowly on
    # CPU); SHED's dynamic psi is checked above and SHED runs vmapped in the end-to-end test
    env, student, ev = _cartpole()
    method = make_hmdp(env, student, HMDPConfig(**TINY_TEACHER), eval_levels=ev)
    run = _method_run(method, student, 3)
    etas = [0.0, 10.0]
    key = jax.random.PRNGKey(5)
    hps = TeacherHyperparams.stack([method.default_hparams.replace(eta=e) for e in etas])
    m_b, s0_b, info_b = jax.jit(jax.vmap(run, in_axes=(None, 0)))(key, hps)
    single = jax.jit(run)
    for i, eta in enumerate(etas):
        m_i, s0_i, info_i = single(key, method.default_hparams.replace(eta=eta).as_arrays())
        np.testing.assert_allclose(np.asarray(info_b.teacher_reward[i]), np.asarray(info_i.teacher_reward), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.asarray(info_b.levels[i]), np.asarray(info_i.levels), rtol=1e-5, atol=1e-5)
        for a, b in zip(jax.tree_util.tree_leaves(m_b.ddpg.actor_params), jax.tree_util.tree_leaves(m_i.ddpg.actor_params)):
            np.testing.assert_allclose(np.asarray(a)[i], np.asarray(b), rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(info_b.extras["ddpg_branch"][i]), [0, 1, 1])  # DDPG updates ran
    assert single._cache_size() == 1  # both eta values through one compiled program
    # eta enters as R = gain - eta * cv: the first step (same s, u and s' for both) differs by exactly 10 * cv
    s1 = np.asarray(info_b.extras["teacher_state"][0, 0])
    np.testing.assert_allclose(np.asarray(info_b.extras["teacher_state"][1, 0]), s1, rtol=1e-6)
    cv = float(coefficient_of_variation(np.asarray(s0_b[0]), s1))
    r0, r10 = np.asarray(info_b.teacher_reward[:, 0])
    assert cv > 0
    np.testing.assert_allclose(r0 - r10, 10.0 * cv, rtol=1e-4)
    np.testing.assert_allclose(r0, np.abs(s1 - np.asarray(s0_b[0])).sum(), rtol=1e-5)


# ---- end to end --------------------------------------------------------------------------------

def _tiny_experiment(method, method_overrides, ppo_overrides):
    ppo = PPOConfig.for_env("cartpole", num_envs=5, num_steps=4, num_minibatches=1, update_epochs=1).replace(**ppo_overrides)
    own = TINY if method == "shed" else TINY_TEACHER
    return Experiment(env="cartpole", method=method, preset="tiny", ppo=ppo, method_config={**own, **method_overrides},
                      loop=LoopSpec(steps_per_episode=3, num_episodes=1, test_episodes=1, test_max_steps=8),
                      test_set="cartpole-test")


def _tiny_build(exp):
    env = envs.make("cartpole")
    student = _StubStudent(env, _StubConfig(exp.ppo.num_envs))
    make = make_shed if exp.method == "shed" else make_hmdp
    method = make(env, student, exp.method_config, eval_levels=env.param_space.sample(jax.random.PRNGKey(42), (10,)))
    return env, student, method, env.param_space.sample(jax.random.PRNGKey(7), (2,))


def test_end_to_end_sweep_writes_run_files(tmp_path):
    exp = _tiny_experiment("shed", {}, {})
    _, student, method, _ = _tiny_build(exp)
    space = sweep.key_space("shed", method, exp.ppo)
    groups, notes = sweep.plan(space, sweep.parse_grid(["eta=0,10"]))
    assert len(groups) == 1 and not notes
    rows = sweep.run_sweep(groups, out=tmp_path, make_experiment=_tiny_experiment, build=_tiny_build, num_seeds=1,
                           root_seed=3, chunk=1, mesh=sharding.batch_mesh(), plots=True, progress=False,
                           final_eval="test", final_eval_episodes=64)
    assert [r["point"] for r in rows] == ["eta=0", "eta=10"]
    assert (tmp_path / "sweep.md").read_text().count("| shed |") == 2
    result = json.loads((tmp_path / "sweep.json").read_text())
    assert result["rows"] == rows and result["groups"] == ["shed"]
    assert result["device"].startswith("cpu: ") and result["date"].endswith(" UTC") and result["command"].startswith("python -m shed_jax")
    recs = {}
    for r in rows:
        d = tmp_path / r["dir"]
        assert d == tmp_path / "shed" / r["point"]
        for f in ("config.json", "metrics.jsonl", "summary.json", "test_return.png", "test_return_per_level.png"):
            assert (d / f).exists(), f
        records = [json.loads(line) for line in (d / "metrics.jsonl").read_text().splitlines()]
        assert [x["step"] for x in records] == [0, 1, 2] and all(x["seed"] == 0 for x in records)
        summary = json.loads((d / "summary.json").read_text())
        # the run CLI's summary fields, plus the point
        hist = {k: np.asarray([[x[k] for x in records]]) for k in ("test_return", "test_return_per_level", "episode", "step",
                                                                    "info/env_steps_train", "info/env_steps_eval")}
        expect = driver.summarize(_tiny_experiment("shed", {}, {}), hist, summary["wall_time_s"], 1)
        assert set(expect) <= set(summary)
        for k in ("final_test_return_mean", "student_env_steps_total", "eval_env_steps_total", "budget_steps"):
            assert summary[k] == pytest.approx(expect[k]), k
        assert summary["values"] == {"eta": json.loads(r["point"].split("=")[1])}
        assert r["final_test_return_mean"] == pytest.approx(records[-1]["test_return"])
        config = json.loads((d / "config.json").read_text())
        assert config["sweep_point"]["method_hparams"] == summary["values"] and config["root_seed"] == 3
        assert config["commit"] == source_commit() and summary["commit"] == source_commit()
        recs[r["point"]] = records
        # --final-eval: this point's final student on the test set. The stub's return is
        # 100 - 30 |level - skill|_1 + N(0, 1), and the last budget step tested the same student with
        # one episode per level, so 64 episodes must land within a few noise SDs of that record.
        final = json.loads((d / "final_eval_test.json").read_text())
        returns = np.asarray(final["returns"])
        assert returns.shape == (1, 2, 64) and final["budget_step"] == 3 and final["labels"] == ["test-0", "test-1"]
        np.testing.assert_allclose(returns.mean(axis=(0, 2)), records[-1]["test_return_per_level"], atol=3.0)
        assert [row["mean"] for row in final["per_level"]] == pytest.approx(returns.mean(axis=(0, 2)).tolist())
    # eta acts on the stored rewards: at step 1 (states s1 -> s2 of each run) R = L1 gain - eta * cv
    for name, eta in (("eta=0", 0.0), ("eta=10", 10.0)):
        s1, s2 = (np.asarray(recs[name][t]["info/extras/teacher_state"]) for t in (0, 1))
        expect = np.abs(s2 - s1).sum() - eta * float(coefficient_of_variation(s1, s2))
        assert recs[name][1]["info/teacher_reward"] == pytest.approx(expect, rel=1e-4)
    # same seeds at both points: step 0 trains on the same levels (the teacher has not learned yet)
    np.testing.assert_allclose(recs["eta=0"][0]["info/levels"], recs["eta=10"][0]["info/levels"], rtol=1e-6)
    # a second sweep into the same directory refuses to overwrite
    with pytest.raises(ValueError, match="already holds a run"):
        sweep.run_sweep(groups, out=tmp_path, make_experiment=_tiny_experiment, build=_tiny_build, num_seeds=1, progress=False)


def test_stop_and_resume_equals_an_uninterrupted_sweep(tmp_path, capsys, monkeypatch):
    from shed_jax.checkpoint import ConfigMismatchError

    exp = _tiny_experiment("hmdp", {}, {})
    _, student, method, _ = _tiny_build(exp)
    groups, _ = sweep.plan(sweep.key_space("hmdp", method, exp.ppo), sweep.parse_grid(["eta=0,10"]))
    kw = dict(make_experiment=_tiny_experiment, build=_tiny_build, num_seeds=2, root_seed=1, chunk=1,
              mesh=sharding.batch_mesh(), plots=False, progress=False)
    straight, split = tmp_path / "straight", tmp_path / "split"
    rows = sweep.run_sweep(groups, out=straight, **kw)
    # a time limit of 0 stops after the first chunk of 3, with a checkpoint at budget step 1
    assert sweep.run_sweep(groups, out=split, time_limit=0.0, **kw) is None
    ckpt_dir = sweep.group_checkpoint_dir(split, groups[0])
    assert sorted(p.name for p in (ckpt_dir / "checkpoints").iterdir() if p.name.isdigit()) == ["1"]
    first = split / "hmdp" / "eta=0" / "metrics.jsonl"
    assert [json.loads(x)["step"] for x in first.read_text().splitlines()] == [0, 0]  # two seeds, step 0
    assert not (split / "hmdp" / "eta=0" / "summary.json").exists()
    # records written after the checkpoint (a chunk that ran but was not saved) are cut on resume
    with first.open("a") as f:
        f.write(json.dumps({"seed": 0, "step": 1, "test_return": 0.0}) + "\n")
    with pytest.raises(ValueError, match="already holds a run.*--resume"):
        sweep.run_sweep(groups, out=split, **kw)
    with pytest.raises(ConfigMismatchError, match="root_seed"):
        sweep.run_sweep(groups, out=split, resume=True, **{**kw, "root_seed": 2})
    capsys.readouterr()
    resumed = sweep.run_sweep(groups, out=split, resume=True, **kw)
    log = capsys.readouterr().out
    assert "resumed at budget step 1/3" in log and "step 1/3 " not in log  # it ran steps 2 and 3 only
    for r, q in zip(rows, resumed):
        assert r["final_test_return_mean"] == q["final_test_return_mean"] and r["point"] == q["point"]
    for point in ("eta=0", "eta=10"):
        a = (straight / "hmdp" / point / "metrics.jsonl").read_text()
        b = (split / "hmdp" / point / "metrics.jsonl").read_text()
        assert len(a.splitlines()) == 6 and a == b  # 2 seeds x 3 steps, every metric in the same digits
    # resuming a finished sweep keeps its groups without running them
    monkeypatch.setattr(sweep, "run_group", lambda *a, **k: pytest.fail("a finished group ran again"))
    kept = sweep.run_sweep(groups, out=split, resume=True, **kw)
    assert kept == resumed
    # sweep.json: this process trained nothing, but the groups' wall time covers both earlier processes
    result = json.loads((split / "sweep.json").read_text())
    group_wall = json.loads((split / "hmdp" / "eta=0" / "summary.json").read_text())["wall_time_s"]
    assert result["groups_wall_time_s"] == group_wall == kept[0]["group_wall_time_s"] > result["wall_time_s"]


def test_preset_experiment_passes_the_episode_overrides():
    make = sweep.preset_experiment("lander", "paper", episodes=12, steps_per_episode=60, test_episode_every=4)
    exp = make("shed", {"num_eval_levels": 5}, {})
    assert (exp.loop.num_episodes, exp.loop.steps_per_episode, exp.loop.test_episode_every) == (12, 60, 4)
    assert exp.method_config.num_eval_levels == 5 and exp.method_config.budget_steps == 60
    default = sweep.preset_experiment("lander", "paper")
    assert default("shed", {}, {}).loop.test_episode_every == 10  # the paper preset tests every 10th episode
    assert default("dr", {}, {}).loop.test_episode_every == 1


def test_resume_reads_the_saved_arguments(tmp_path):
    import argparse

    p = argparse.ArgumentParser()
    sweep_cli.add_arguments(p)
    start = p.parse_args(["--env", "lander", "--methods", "shed", "--seeds", "3", "--grid", "eta=0,10",
                          "--test-episode-every", "4", "--out", str(tmp_path)])
    (tmp_path / sweep.ARGS_FILE).write_text(json.dumps({k: getattr(start, k) for k in sweep.SAVED_ARGS}))
    later = sweep.resumed_args(p.parse_args(["--resume", str(tmp_path), "--time-limit", "60"]))
    assert (later.env, later.methods, later.seeds, later.grid, later.test_episode_every, later.out, later.time_limit) == (
        "lander", "shed", 3, ["eta=0,10"], 4, str(tmp_path), 60.0)
    # a sweep saved before --test-episode-every existed resumes with the preset's default (None)
    (tmp_path / sweep.ARGS_FILE).write_text(json.dumps({k: getattr(start, k) for k in sweep.SAVED_ARGS
                                                        if k != "test_episode_every"}))
    assert sweep.resumed_args(p.parse_args(["--resume", str(tmp_path)])).test_episode_every is None
    with pytest.raises(SystemExit, match="drop --out"):
        sweep.resumed_args(p.parse_args(["--resume", str(tmp_path), "--out", str(tmp_path / "other")]))
    with pytest.raises(SystemExit, match="no sweep_args.json"):
        sweep.resumed_args(p.parse_args(["--resume", str(tmp_path / "nowhere")]))


def test_bad_final_eval_set_fails_before_any_compile(tmp_path):
    exp = _tiny_experiment("shed", {}, {})
    _, student, method, _ = _tiny_build(exp)
    groups, _ = sweep.plan(sweep.key_space("shed", method, exp.ppo), sweep.parse_grid(["eta=0,10"]))
    with pytest.raises(ValueError, match="--final-eval: .*'hard' is none of these"):
        sweep.run_sweep(groups, out=tmp_path, make_experiment=_tiny_experiment, build=_tiny_build, num_seeds=1,
                        progress=False, final_eval="hard")
    assert not list(tmp_path.iterdir())  # nothing written


def test_cli_rejects_unknown_keys(capsys, tmp_path):
    from shed_jax.__main__ import main

    # one line on stderr, exit 2 (a usage error), nothing written
    out = tmp_path / "sweep"
    assert main(["sweep", "--env", "lander", "--methods", "shed,dr", "--preset", "quick", "--grid", "eta=0,10",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("shed_jax: error: sweep: method 'dr' has no hyperparameter or config field 'eta'")
    assert main(["sweep", "--env", "lander", "--methods", "shed", "--grid", "eta=0", "--grid", "eta=1",
                 "--out", str(out)]) == 2
    assert "--grid key 'eta' given twice" in capsys.readouterr().err
    assert main(["sweep", "--methods", "shed,bogus", "--out", str(out)]) == 2
    assert "--methods: unknown method(s) 'bogus'; known: dr, plr" in capsys.readouterr().err
    assert not out.exists()
