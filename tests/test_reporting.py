"""Reporting and the results-comparison tool: statistics, records, table text and plots on
hand-computed synthetic runs written the way ``shed_jax/driver.py`` writes them."""
import csv
import json
import math
import pathlib
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from experiments import compare
from shed_jax import driver, reporting
from shed_jax.methods.base import StepInfo
from shed_jax.presets import build_experiment

# --------------------------------------------------------------------------------------------
# statistics and records
# --------------------------------------------------------------------------------------------


def test_mean_se_hand_computed():
    m, se = reporting.mean_se(np.array([[1.0, 2.0], [3.0, 6.0]]))
    np.testing.assert_allclose(m, [2.0, 4.0])
    np.testing.assert_allclose(se, [1.0, 2.0])  # sd([1,3]) = sqrt 2, sd([2,6]) = 2 sqrt 2; / sqrt 2
    m, se = reporting.mean_se(np.array([1.0, np.nan, 3.0]))
    assert (float(m), float(se)) == (2.0, 1.0)  # NaN ignored: n = 2
    m, se = reporting.mean_se(np.array([[5.0, 7.0]]))
    np.testing.assert_array_equal(se, [0.0, 0.0])  # one seed: SE 0, not NaN
    m, se = reporting.mean_se(np.array([-100.0, -110.0, -120.0]))
    assert float(m) == -110.0 and math.isclose(float(se), 10 / math.sqrt(3))
    # seeds without a finished episode (NaN) leave one value or none in a column: no numpy warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        m, se = reporting.mean_se(np.array([[4.0, np.nan], [np.nan, np.nan]]))
    np.testing.assert_array_equal(m, [4.0, np.nan])
    np.testing.assert_array_equal(se, [0.0, 0.0])


def test_final_value_uses_last_evaluated_step():
    y = np.array([[1.0, 2.0, np.nan], [3.0, 4.0, np.nan]])  # last step not evaluated (test_every > 1)
    m, se, t = reporting.final_value(y)
    assert (m, se, t) == (3.0, 1.0, 1)
    assert math.isnan(reporting.final_value(np.full((2, 3), np.nan))[0])


def test_curve_of_the_last_tested_teacher_episode():
    nan = np.nan
    # 2 seeds, 3 teacher episodes of 2 steps; episode 2 (the last) not tested yet, as in a run
    # stopped by --time-limit: the curve is episode 1's, x counted within it
    hist = {"episode": np.array([[0, 0, 1, 1, 2, 2]] * 2),
            "info/env_steps_train": np.full((2, 6), 100),
            "test_return": np.array([[1.0, 2.0, nan, 4.0, nan, nan], [3.0, 4.0, nan, 6.0, nan, nan]])}
    assert reporting.last_tested_episode(hist) == 1
    x, y = reporting.last_episode_curve(hist)
    np.testing.assert_array_equal(x, [200.0])  # episode 1's untested first step dropped
    np.testing.assert_array_equal(y, [[4.0], [6.0]])
    assert reporting.episode_label("shed", hist, 3) == "shed (teacher episode 2)"
    assert reporting.episode_label("dr", hist, 1) == "dr"
    hist["test_return"][:, 5] = [7.0, nan]  # one seed tested in the last episode: that episode
    assert reporting.last_tested_episode(hist) == 2
    np.testing.assert_array_equal(reporting.last_episode_curve(hist)[0], [200.0])
    hist["test_return"][:] = nan  # nothing tested: the last episode, no points
    assert reporting.last_tested_episode(hist) == 2 and reporting.last_episode_curve(hist)[0].size == 0


def test_records_round_trip_with_nan_and_nested_arrays():
    metrics = {
        "step": np.array([[0, 1], [0, 1]], np.int32),
        "test_return": np.array([[1.5, np.nan], [2.5, 3.0]], np.float32),
        "info/levels": np.arange(2 * 2 * 3 * 2, dtype=np.float32).reshape(2, 2, 3, 2),
    }
    lines = reporting.jsonl_bytes(reporting.step_records(metrics, [0, 1])).decode().splitlines()
    records = [json.loads(line) for line in lines]
    assert records[1] == {"seed": 1, "step": 0, "test_return": 2.5, "info/levels": [[12.0, 13.0], [14.0, 15.0], [16.0, 17.0]]}
    assert records[2]["test_return"] is None  # NaN -> null in JSON
    # each float with the shortest digits that read back to it in its own precision
    x = np.float32(0.1)
    line = reporting.jsonl_bytes(reporting.step_records(
        {"v": np.array([[x]]), "d": np.array([[float(x)]]), "h": np.array([[0.1]], jnp.bfloat16),
         "w": np.array([[np.inf]], np.float32)}, [0]))
    assert line == b'{"seed":0,"v":0.1,"d":0.10000000149011612,"h":0.100097656,"w":null}\n'
    assert np.float32(json.loads(line)["v"]) == x  # lossless for float32
    back = reporting.records_to_arrays(records)
    np.testing.assert_array_equal(back["step"], metrics["step"])
    np.testing.assert_array_equal(back["test_return"], metrics["test_return"])  # NaN compares equal here
    np.testing.assert_array_equal(back["info/levels"], metrics["info/levels"])
    np.testing.assert_array_equal(back["seed"], [[0, 0], [1, 1]])
    with pytest.raises(ValueError, match="different numbers of records"):
        reporting.records_to_arrays(records[:-1])
    # a metric logged only from a resume on (a newer version): NaN before, with its shape
    later = [dict(r, extra=[7.0, 8.0]) if r["step"] == 1 else r for r in records]
    back = reporting.records_to_arrays(later)
    assert back["extra"].shape == (2, 2, 2)
    assert np.isnan(back["extra"][:, 0]).all() and (back["extra"][:, 1] == [7.0, 8.0]).all()


def test_text_formatting():
    assert reporting.format_mean_se(-110.0, 10 / math.sqrt(3)) == "-110.0 ± 5.8"
    assert reporting.format_mean_se(float("nan"), 1.0) == "n/a"
    assert reporting.format_mean_se(2.0, 0.25, digits=2) == "2.00 ± 0.25"
    assert [reporting.format_count(n) for n in (950, 12_800, 1_024_000, 2.048e9)] == ["950", "12.8k", "1.02M", "2.05G"]
    assert [reporting.format_duration(s) for s in (40, 3600, 11_520)] == ["40 s", "60.0 min", "3.20 h"]
    text = reporting.markdown_table(["a", "b|c"], [[1, "x|y"], ["-2.0 ± 1.0", 3]], align="lr")
    assert text == "| a | b\\|c |\n|---|---:|\n| 1 | x\\|y |\n| -2.0 ± 1.0 | 3 |\n"
    with pytest.raises(ValueError, match="row 0 has 1 cells"):
        reporting.markdown_table(["a", "b"], [[1]])


# --------------------------------------------------------------------------------------------
# synthetic run directories, written with shed_jax/driver.py's own writers
# --------------------------------------------------------------------------------------------

LANDER_LOW = np.array([-11.99, 0.0, 0.0])
LANDER_HIGH = np.array([-0.01, 20.0, 2.0])


def _write_run(out: pathlib.Path, method: str, final: list[float], *, episodes: int, T: int, wall: float,
               m_eval: int = 10, chunk: int = 2, with_summary: bool = True, root_seed: int = 0) -> None:
    """A fake lander run: test return rises linearly from -600 to ``final`` (per seed) in every
    teacher episode; 1000 student env steps per budget step; levels drift inside the box."""
    exp = build_experiment("lander", method, "quick", episodes=episodes, steps_per_episode=T)
    S, total, L, n_test = len(final), episodes * T, 4, 10
    rng = np.random.default_rng(0)
    t = np.arange(total)
    frac = ((t % T) + 1) / T  # [total]
    test_return = -600 + frac[None, :] * (np.asarray(final)[:, None] + 600)  # [S, total]
    per_level = test_return[..., None] + np.linspace(-50, 50, n_test)  # [S, total, n_test]; mean = test_return
    levels = LANDER_LOW + (LANDER_HIGH - LANDER_LOW) * rng.uniform(0.2, 0.8, (S, total, L, 3)) * frac[None, :, None, None]
    extras = {"teacher_state": per_level[..., :m_eval] + 5.0} if method in ("shed", "hmdp") else {}
    if method == "shed":  # the student's PPO statistics (the DR run goes without: no panels drawn)
        extras["ppo"] = {"entropy": np.broadcast_to(1.0 - 0.1 * t, (S, total)).astype(np.float32),
                         "clip_frac": np.full((S, total), 0.1, np.float32)}
    info = StepInfo(
        levels=levels.astype(np.float32),
        env_steps_train=np.full((S, total), 1000, np.int32),
        env_steps_eval=np.full((S, total), 50, np.int32),
        teacher_reward=np.full((S, total), np.nan if method == "dr" else 0.5, np.float32),
        num_new_levels=np.full((S, total), L, np.int32),
        extras=extras,
    )
    metrics = {"step": np.broadcast_to(t, (S, total)).astype(np.int32), "episode": np.broadcast_to(t // T, (S, total)),
               "step_in_episode": np.broadcast_to(t % T, (S, total)), "test_return_per_level": per_level.astype(np.float32),
               "test_return": test_return.astype(np.float32), "info": info}
    out.mkdir(parents=True)
    config = {"experiment": exp.to_dict(), "seeds": S, "root_seed": root_seed, "backend": "cpu", "devices": ["cpu"],
              "chunk": chunk, "jax": "test"}
    (out / "config.json").write_text(json.dumps(config, indent=2, default=str))
    history = {}
    for start in range(0, total, chunk):  # as main(): one flatten/append per compiled chunk
        part = {k: (v[:, start:start + chunk] if k != "info" else None) for k, v in metrics.items()}
        part["info"] = jax.tree_util.tree_map(lambda v: v[:, start:start + chunk], info)
        flat = reporting.flatten_tree(part)
        for k, v in flat.items():
            history.setdefault(k, []).append(v)
        reporting.append_jsonl(out / "metrics.jsonl", reporting.step_records(flat, range(S)))
    hist = {k: np.concatenate(v, axis=1) for k, v in history.items()}
    if with_summary:
        (out / "summary.json").write_text(json.dumps(driver.summarize(exp, hist, wall, S), indent=2))


@pytest.fixture()
def runs(tmp_path):
    _write_run(tmp_path / "shed", "shed", [-100.0, -110.0, -120.0], episodes=2, T=3, wall=120.0)
    _write_run(tmp_path / "dr", "dr", [-200.0, -260.0], episodes=1, T=4, wall=7200.0)
    return tmp_path


def _png(path: pathlib.Path, min_bytes: int = 8000) -> tuple[int, int]:
    assert path.exists(), path
    assert path.stat().st_size > min_bytes, (path, path.stat().st_size)
    with Image.open(path) as im:
        return im.size


def test_load_run_reads_what_run_writes(runs):
    r = compare.load_run(runs / "shed")
    assert (r.env, r.method, r.preset, r.seeds, r.num_episodes) == ("lander", "shed", "quick", 3, 2)
    assert r.hist["test_return"].shape == (3, 6)
    assert r.hist["info/levels"].shape == (3, 6, 4, 3)
    assert r.hist["info/extras/teacher_state"].shape == (3, 6, 10)
    assert np.all(np.isnan(compare.load_run(runs / "dr").hist["info/teacher_reward"]))
    x, y = compare.curve(r)  # last teacher episode only
    np.testing.assert_array_equal(x, [1000, 2000, 3000])
    np.testing.assert_allclose(y[:, -1], [-100, -110, -120], atol=1e-4)
    assert compare.env_steps(r) == (3000.0, 6000.0)
    assert compare.final_return(r) == pytest.approx((-110.0, 10 / math.sqrt(3)))


def test_until_step_compares_runs_at_one_budget(runs, capsys):
    """``--until-step N``: budget steps before N only; a run cut there is partial, its summary and
    final evaluation (later students') left out; a run that ends before N is read whole."""
    whole = compare.load_run(runs / "shed")
    _write_named_eval(runs / "shed", np.zeros((3, 1, 2)), ["flat"])
    cut = compare.load_run(runs / "shed", until_step=4)
    assert cut.cut and cut.partial and not whole.cut and not whole.partial
    np.testing.assert_array_equal(cut.hist["test_return"], whole.hist["test_return"][:, :4])
    assert cut.hist["info/levels"].shape == (3, 4, 4, 3)
    assert compare._named_eval(cut) is None and compare._named_eval(compare.load_run(runs / "shed")) is not None
    at_end = compare.load_run(runs / "shed", until_step=6)
    assert not at_end.cut and at_end.summary == whole.summary
    assert compare.main([str(runs / "dr"), str(runs / "shed"), "--out", str(runs / "cut"), "--until-step", "4"]) == 0
    assert "(partial)" in (runs / "cut" / "results.md").read_text()
    for bad, says in (("0", "--until-step must be at least 1, got 0"), ("-3", "--until-step must be at least 1, got -3")):
        with pytest.raises(SystemExit) as stop:
            compare.main([str(runs / "dr"), "--out", str(runs / "cut"), "--until-step", bad])
        assert stop.value.code == 2 and capsys.readouterr().err.strip().endswith(says)


def test_compare_table_rows_and_plots(runs, capsys):
    out = runs / "report"
    assert compare.main([str(runs / "dr"), str(runs / "shed"), "--out", str(out), "--paper", "lander"]) == 0
    md = (out / "results.md").read_text()
    lines = md.splitlines()
    assert lines[0] == ("| method | env | preset | seeds | final test return (mean ± SE) | student env steps | "
                        "all teacher episodes | wall time / seed | paper, update 1000 (docs/design.md §12.1, lander) |")
    # sorted best first; SE(shed) = 10/sqrt(3), SE(dr) = sd(-200,-260)/sqrt(2) = 30
    assert lines[2] == "| shed | lander | quick | 3 | -110.0 ± 5.8 | 3k | 6k (2 ep.) | 40 s | ≈ -100 |"
    assert lines[3] == "| dr | lander | quick | 2 | -230.0 ± 30.0 | 4k | 4k | 60.0 min | ≈ -257 |"
    for name in ("curves_lander.png", "params_lander_shed.png", "params_lander_dr.png", "eval_vector_lander_shed.png",
                 "per_level_lander_shed.png", "per_level_lander_dr.png"):
        _png(out / name)
        assert f"]({name})" in md
    assert not (out / "eval_vector_lander_dr.png").exists()  # DR has no performance vector
    _png(out / "student_lander_shed.png")  # two panels (entropy, clipped fraction) of the run's statistics
    assert "](student_lander_shed.png)" in md and not (out / "student_lander_dr.png").exists()
    w, h = _png(out / "params_lander_shed.png")
    assert w > h  # three parameter panels side by side
    assert "| shed | lander |" in capsys.readouterr().out
    # episodic runs get a per-teacher-episode table: each of shed's 2 episodes ends at its seeds' finals
    at = lines.index("| teacher episode | 0 | 1 |")
    assert lines[at + 2] == "| shed | -110.0 ± 5.8 | -110.0 ± 5.8 |" and not lines[at + 3].startswith("| dr")
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 4 + 3 * 6  # every (seed, budget step) of dr and shed has a test result
    assert [r["method"] for r in rows].count("dr") == 8
    last = next(r for r in rows if (r["method"], r["seed"], r["episode"], r["step_in_episode"]) == ("shed", "1", "1", "2"))
    assert (last["student_env_steps_in_episode"], last["teacher_reward"]) == ("3000", "0.50")  # restarts per episode
    assert (float(last["test_return"]), float(last["test_level_1"]), float(last["test_level_10"])) == (-110, -160, -60)
    assert rows[0]["method"] == "dr" and rows[0]["teacher_reward"] == ""  # DR has no teacher reward: empty cell


def test_compare_partial_run_and_duplicate_methods(runs):
    _write_run(runs / "shed-b", "shed", [-50.0, -70.0], episodes=1, T=3, wall=10.0, with_summary=False)
    out = runs / "report2"
    assert compare.main([str(runs / "shed"), str(runs / "shed-b"), "--out", str(out)]) == 0
    lines = (out / "results.md").read_text().splitlines()
    # no summary.json: the last step of metrics.jsonl, marked partial; labels disambiguated by directory
    assert lines[2] == "| shed (shed-b) | lander | quick | 2 | -60.0 ± 10.0 (partial) | 3k | 3k | n/a |"
    assert lines[3] == "| shed (shed) | lander | quick | 3 | -110.0 ± 5.8 | 3k | 6k (2 ep.) | 40 s |"
    _png(out / "params_lander_shed_shed-b.png")
    # labels given by the user replace those everywhere: table, plot names, CSV
    out3 = runs / "report3"
    assert compare.main([str(runs / "shed"), str(runs / "shed-b"), "--labels", "SHED L1,SHED short", "--out", str(out3)]) == 0
    lines = (out3 / "results.md").read_text().splitlines()
    assert lines[2].startswith("| SHED short | lander |") and lines[3].startswith("| SHED L1 | lander |")
    _png(out3 / "params_lander_SHED_short.png")
    assert (out3 / "results.csv").read_text().splitlines()[1].startswith("SHED L1,lander,0,0,0,1000,")
    for bad in ("a", "a,a", "a,"):  # one non-empty label per run directory; "a,a" would pool runs of other configs
        with pytest.raises(SystemExit):
            compare.main([str(runs / "shed"), str(runs / "shed-b"), "--labels", bad, "--out", str(out3)])


def _write_named_eval(run_dir: pathlib.Path, returns: np.ndarray, labels: list[str], threshold: float = 230.0) -> None:
    """``final_eval_named.json`` with the per-level statistics of ``eval.level_table`` (the numbers
    ``run --final-eval named`` writes), for hand-made returns [seeds, levels, episodes]."""
    from shed_jax import evaluation

    t = evaluation.level_table(returns, threshold=threshold)
    (run_dir / "final_eval_named.json").write_text(json.dumps({
        "levels": "named", "labels": labels, "seeds": returns.shape[0], "solved_threshold": threshold,
        "returns": returns.tolist(),
        "per_level": [{"label": lab, "mean": t["mean"][j], "se": t["se"][j], "solved_rate": t["solved_rate"][j],
                       "cvar": t["cvar"][j]} for j, lab in enumerate(labels)],
        "overall": t["overall"]}))


def test_compare_named_level_table_with_dcd_reference(runs):
    # the levels in another order than DCD's table, plus one extra level: lookup must be by label
    labels = ["Stump", "BipedalWalker", "Roughness", "Insane", "Hardcore", "PitGap", "Stairs"]
    returns = np.empty((2, 7, 2))
    for j, v in enumerate([-10.0, 0.0, -20.0, -300.0, -30.0, -40.0, -50.0]):  # a distinct value per level
        returns[:, j] = v
    # BipedalWalker: seed means 230 and 200 -> 215 ± 15; solved means > 230, so 230.0 itself is not
    returns[:, 1] = [[230.0, 230.0], [100.0, 300.0]]
    _write_named_eval(runs / "shed", returns, labels)
    out = runs / "report_named"
    assert compare.main([str(runs / "dr"), str(runs / "shed"), "--out", str(out), "--paper", "walker"]) == 0
    lines = (out / "results.md").read_text().splitlines()
    at = lines.index("| method | seeds | BipedalWalker | Hardcore | Stairs | PitGap | Stump | Roughness | all 7 named levels |")
    # each seed's mean over its 7 x 2 episodes; 1 of the 28 episodes (300) above 230
    s0 = (460 - 20 - 40 - 600 - 60 - 80 - 100) / 14
    s1 = (400 - 20 - 40 - 600 - 60 - 80 - 100) / 14
    pooled = f"{(s0 + s1) / 2:.1f} ± {abs(s0 - s1) / 2:.1f} (.036)"
    assert lines[at + 2] == ("| shed | 2 | 215.0 ± 15.0 (.250) | -30.0 ± 0.0 (.000) | -50.0 ± 0.0 (.000) | "
                             f"-40.0 ± 0.0 (.000) | -10.0 ± 0.0 (.000) | -20.0 ± 0.0 (.000) | {pooled} |")
    # the run without a named evaluation (dr) has no row; DCD's three methods follow as reference rows
    assert lines[at + 3] == ("| DCD ACCEL (docs/design.md §12.2) | 10 | 317.9 ± 0.9 (.998) | 210.8 ± 10.7 (.629) | 91.6 ± 9.7 (.206) | "
                             "112.0 ± 24.0 (.310) | 165.8 ± 14.0 (.491) | 253.3 ± 13.1 (.764) | — |")
    assert lines[at + 4] == ("| DCD PLR⊥ (docs/design.md §12.2) | 10 | 304.8 ± 2.3 (.992) | 84.8 ± 12.8 (.158) | 51.0 ± 4.8 (.045) | "
                             "43.3 ± 11.3 (.040) | 6.5 ± 5.5 (.006) | 129.7 ± 13.3 (.244) | — |")
    assert lines[at + 5].startswith("| DCD DR (docs/design.md §12.2) | 10 | 266.8 ± 13.3 (.836) |") and not lines[at + 6].startswith("|")
    _png(out / "named_levels.png")  # the same six levels as bars, linked from results.md
    assert "](named_levels.png)" in (out / "results.md").read_text()
    assert compare.plot_named([compare.load_run(runs / "dr")], out) is None
    # without --paper walker: no reference rows; no named evaluation: no table
    assert compare.named_table([compare.load_run(runs / "shed")]).count("\n") == 3
    assert compare.named_table([compare.load_run(runs / "dr")]) is None
    # named sets of different sizes: the pooled cells say how many levels each pools
    _write_run(runs / "shed-b", "shed", [-50.0, -70.0], episodes=1, T=3, wall=10.0)
    _write_named_eval(runs / "shed-b", np.delete(returns, 3, axis=1), [x for x in labels if x != "Insane"])
    text = compare.named_table([compare.load_run(runs / "shed"), compare.load_run(runs / "shed-b")])
    assert "| all named levels |" in text and " [7 levels] |" in text and " [6 levels] |" in text
    # a set without one of DCD's levels, or another solved threshold, is an error
    _write_named_eval(runs / "shed", np.delete(returns, 1, axis=1), [x for x in labels if x != "BipedalWalker"])
    with pytest.raises(ValueError, match=r"lacks the named levels \['BipedalWalker'\]"):
        compare.named_table([compare.load_run(runs / "shed")])
    _write_named_eval(runs / "shed", returns, labels, threshold=200.0)
    with pytest.raises(ValueError, match="above 200.0 as solved"):
        compare.named_table([compare.load_run(runs / "shed")])


def test_compare_pools_runs_that_share_a_label(runs):
    # a second SHED run with the same experiment and another root seed: one row of 3 + 2 seeds
    _write_run(runs / "shed-r1", "shed", [-50.0, -70.0], episodes=2, T=3, wall=30.0, root_seed=1)
    labels = ["BipedalWalker", "Hardcore", "Stairs", "PitGap", "Stump", "Roughness", "Insane"]
    a, b = np.full((3, 7, 2), -100.0), np.full((2, 7, 2), -100.0)
    a[:, 0] = [[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]]
    b[:, 0] = [[40.0, 40.0], [-150.0, 250.0]]  # seed means 40 and 50; one episode of the ten > 230
    _write_named_eval(runs / "shed", a, labels)
    _write_named_eval(runs / "shed-r1", b, labels)
    out = runs / "pooled"
    assert compare.main([str(runs / "shed"), str(runs / "dr"), str(runs / "shed-r1"),
                         "--labels", "SHED,DR,SHED", "--out", str(out)]) == 0
    lines = (out / "results.md").read_text().splitlines()
    # finals -100, -110, -120, -50, -70: mean -90, sd sqrt(3400 / 4); wall (120 + 30) s / 5 seeds
    assert lines[2] == f"| SHED | lander | quick | 5 | -90.0 ± {math.sqrt(850 / 5):.1f} | 3k | 6k (2 ep.) | 30 s |"
    assert lines[3].startswith("| DR | lander | quick | 2 |") and not lines[4].startswith("|")
    assert ("Pooled rows, seeds numbered in this order: **SHED** = shed (root seed 0, 3 seeds), "
            "shed-r1 (root seed 1, 2 seeds).") in lines
    # the named levels pooled over the five seeds: BipedalWalker seed means 10..50 -> 30 ± sd/sqrt 5
    named = next(x for x in lines if x.startswith("| SHED | 5 |"))
    assert named.split(" | ")[2] == f"30.0 ± {math.sqrt(250 / 5):.1f} (.100)"
    # CSV: seeds 0-2 from the first run, 3-4 from the second, in the order of the RUN_DIRs
    rows = [r for r in csv.DictReader(open(out / "results.csv")) if r["method"] == "SHED"]
    last = {int(r["seed"]): float(r["test_return"]) for r in rows if r["episode"] == "1" and r["step_in_episode"] == "2"}
    assert last == pytest.approx({0: -100.0, 1: -110.0, 2: -120.0, 3: -50.0, 4: -70.0})
    # what cannot be pooled: the same root seed, another experiment, a named evaluation on one side only
    sd = compare.load_run
    # a metric only one run logs (a newer version resumed it) is left out; the shared ones pool
    m = runs / "shed-r1" / "metrics.jsonl"
    m.write_text("".join(json.dumps(dict(json.loads(x), new=1.0)) + "\n" for x in m.read_text().splitlines()))
    (p,) = compare.pool_runs([sd(runs / "shed"), sd(runs / "shed-r1")], ["x", "x"])
    assert "new" not in p.hist and p.hist["test_return"].shape == (5, 6)
    with pytest.raises(ValueError, match=r"root seeds \[0, 0\] must be known and distinct"):
        compare.pool_runs([sd(runs / "shed"), sd(runs / "shed")], ["x", "x"])
    _write_run(runs / "shed-t4", "shed", [-50.0, -70.0], episodes=2, T=4, wall=30.0, root_seed=2)
    with pytest.raises(ValueError, match=r"experiments differ in \['loop', 'method_config'\]"):
        compare.pool_runs([sd(runs / "shed"), sd(runs / "shed-t4")], ["x", "x"])
    with pytest.raises(SystemExit):
        compare.main([str(runs / "shed"), str(runs / "dr"), "--labels", "x,x", "--out", str(out)])
    (runs / "shed-r1" / "final_eval_named.json").unlink()
    with pytest.raises(ValueError, match="has no final_eval_named.json"):
        compare.named_table(compare.pool_runs([sd(runs / "shed"), sd(runs / "shed-r1")], ["x", "x"]))


def test_compare_rejects_a_directory_that_is_not_a_run(tmp_path, capsys):
    """One line naming the directory and what it lacks, not a traceback."""
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as stop:
        compare.main([str(tmp_path / "empty"), "--out", str(tmp_path / "o")])
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert stop.value.code == 2 and last.endswith(f"{tmp_path / 'empty'} has no config.json: is it a run directory of "
                                                  "`python -m shed_jax run`?")


def test_paper_numbers_match_spec_section_3_4():
    assert compare.PAPER["lander"]["shed"][-1] == -100 and compare.PAPER["lander"]["paired"][-1] == -377
    assert compare.format_paper(compare.PAPER["walker"]["shed"][-1]) == "≈ 62–65"
    assert compare.format_paper(compare.PAPER["walker"]["paired"][-1]) == "≈ -10"


def test_plots_direct(tmp_path):
    rng = np.random.default_rng(1)
    x = np.arange(1, 21) * 5000.0
    y = np.cumsum(rng.normal(5, 3, (3, 20)), axis=1)
    y[:, 1::2] = np.nan  # test set every other step: the lines must still be drawn
    reporting.plot_curves({"a": (x, y), "b": (x, y - 20)}, tmp_path / "c.png", xlabel="steps", ylabel="R", title="t",
                          reference_curves={"paper a": (x[::5], np.array([0.0, 10.0, 20.0, 30.0]), "a")})
    reporting.plot_panels(x, y[..., None] + np.arange(10), tmp_path / "pl.png", title="per level")
    reporting.plot_eval_vector(np.arange(20), rng.normal(-100, 50, (2, 20, 10)), tmp_path / "ev.png", title="ev",
                               episode_starts=[10])
    for name in ("c.png", "pl.png", "ev.png"):
        _png(tmp_path / name)
    with pytest.raises(ValueError, match="curve has 5 x values"):
        reporting.plot_curves({"a": (x[:5], y)}, tmp_path / "bad.png", xlabel="", ylabel="", title="")
    levels = ["flat", "stairs", "pits"]
    reporting.plot_level_bars(levels, {"a": ([120.0, -30.0, -60.0], [40.0, 5.0, 8.0]), "b": ([10.0, 20.0, -5.0], [1, 2, 3])},
                              tmp_path / "bars.png", title="bars", threshold=230.0,
                              references={"paper": [300.0, 90.0, 110.0]})
    w, h = _png(tmp_path / "bars.png")
    assert w > h
    with pytest.raises(ValueError, match="'b' has 2 means and 3 SEs for 3 levels"):
        reporting.plot_level_bars(levels, {"b": ([1.0, 2.0], [1.0, 1.0, 1.0])}, tmp_path / "bad.png", title="")
    with pytest.raises(ValueError, match="reference 'paper' has 2 values"):
        reporting.plot_level_bars(levels, {"a": ([0.0] * 3, [0.0] * 3)}, tmp_path / "bad.png", title="",
                                  references={"paper": [1.0, 2.0]})
    assert not (tmp_path / "bad.png").exists()
