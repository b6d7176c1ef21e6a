"""experiments.walker_loop's arithmetic: the protocol estimate from per-kind step times, and the
flat-level PPO record read from a bench_ppo results file, the named-level rates, and the
baselines record written from sweep directories (hand-computed cases)."""
import json

import pytest

from experiments import walker_loop
from shed_jax.loop import LoopSpec


def test_protocol_estimate_counts_each_kind_of_step():
    # 3 episodes of 4 steps, the test set in episodes 0 and 2 (the last): 8 tested steps, 3 starts
    spec = LoopSpec(steps_per_episode=4, num_episodes=3, test_episode_every=2)
    est = walker_loop.protocol_estimate(spec, {"plain": 1.0, "tested": 3.0, "episode_start": 1.5})
    assert est["total_steps"] == 12 and est["tested_steps"] == 8
    assert est["protocol_s_estimate"] == pytest.approx(12 * 1.0 + 8 * 2.0 + 3 * 0.5)
    assert est["budget_step_s_mean"] == pytest.approx(29.5 / 12)
    # a schedule that tests every step has no plain step to time: every step costs "tested"
    every = LoopSpec(steps_per_episode=5, num_episodes=1)
    assert walker_loop.protocol_estimate(every, {"tested": 2.0})["protocol_s_estimate"] == pytest.approx(10.0)


def test_ppo_flat_record(tmp_path):
    evals = [{"env_steps_per_seed": 2_000_000, "per_seed": [100.0, 240.0, 250.0]},
             {"env_steps_per_seed": 4_000_000, "per_seed": [200.0, 231.0, 260.0]},
             {"env_steps_per_seed": 6_000_000, "per_seed": [229.0, 235.0, 262.0]},
             {"env_steps_per_seed": 12_000_000, "per_seed": [240.0, 235.0, 262.0]}]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"device": "H200", "date": "2026-11-25", "command": "x",
                                "sections": {"walker": {"evals": evals}}}))
    r = walker_loop.ppo_flat(str(path))
    assert r["seeds"] == 3 and r["eval_median"] == [240.0, 231.0, 235.0, 240.0]
    assert r["median_steps_to_230"] == 2_000_000  # median 240 >= 230 at the first evaluation
    assert r["seeds_at_230_by_10M"] == 2  # the first seed reaches 230 only at 12M
    assert r["source"]["device"] == "H200"


def test_record_composed_from_measured_parts(tmp_path):
    loops = {"device": "NVIDIA H200", "date": "2026-11-25", "command": "python -m experiments.walker_loop",
             "loops": {"dr": {"budget_step_s_mean": 21.0}}, "budget_step_seconds": {"dr": 21.0}}
    ppo = {"device": "NVIDIA H200", "date": "2026-11-25", "command": "bench",
           "sections": {"walker": {"evals": [{"env_steps_per_seed": 1_000_000, "per_seed": [240.0, 250.0]}]}}}
    (tmp_path / "loops.json").write_text(json.dumps(loops))
    (tmp_path / "ppo.json").write_text(json.dumps(ppo))
    out = tmp_path / "record.json"
    assert walker_loop.main(["--loops-from", str(tmp_path / "loops.json"), "--ppo-results", str(tmp_path / "ppo.json"),
                             "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["device"] == "NVIDIA H200" and rec["date"] == "2026-11-25"  # the measurement's, not today's machine
    assert rec["budget_step_seconds"] == {"dr": 21.0} and rec["loops_source"]["command"] == loops["command"]
    assert rec["ppo_flat"]["median_steps_to_230"] == 1_000_000 and rec["named_solved_rate"] is None


def _named_eval(path, rows, seeds=5, episodes=10):
    path.write_text(json.dumps({"seeds": seeds, "episodes": episodes, "per_level": [
        {"label": label, "mean": mean, "se": se, "solved_rate": solved} for label, mean, se, solved in rows]}))


def test_named_solved_rates_fold_in_per_method(tmp_path):
    loops = {"device": "NVIDIA H200", "date": "2026-11-25", "command": "c", "loops": {}, "budget_step_seconds": {}}
    (tmp_path / "loops.json").write_text(json.dumps(loops))
    _named_eval(tmp_path / "dr.json", [("BipedalWalker", 120.0, 29.5, 0.0), ("Stump", -46.1, 6.1, 0.0)])
    _named_eval(tmp_path / "accel.json", [("BipedalWalker", 250.0, 3.0, 0.9)], seeds=3)
    out = tmp_path / "record.json"
    assert walker_loop.main(["--loops-from", str(tmp_path / "loops.json"), "--named", f"dr={tmp_path / 'dr.json'}",
                             "--named", f"accel={tmp_path / 'accel.json'}@NVIDIA H100", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["named_solved_rate"] == {"dr": {"BipedalWalker": 0.0, "Stump": 0.0}, "accel": {"BipedalWalker": 0.9}}
    assert rec["named_sources"]["accel"]["seeds"] == 3 and rec["named_sources"]["dr"]["episodes"] == 10
    assert rec["named_sources"]["accel"]["device"] == "NVIDIA H100" and "device" not in rec["named_sources"]["dr"]


def test_baselines_record_reads_sweeps(tmp_path):
    from experiments import baselines_record

    lander, walker, walker2 = tmp_path / "lander", tmp_path / "walker", tmp_path / "walker2"
    for d, env, method, mean, se, extra in ((lander, "lander", "plr", 89.3, 6.0, ["level_switch=episode"]),
                                            (walker, "walker", "dr", -33.4, 7.3, []),
                                            (walker2, "walker", "accel", -51.0, 6.1, [])):
        (d / method / "default").mkdir(parents=True)
        (d / "sweep.json").write_text(json.dumps({"rows": [{"method": method, "seeds": 10, "dir": f"{method}/default",
                                                            "final_test_return_mean": mean, "final_test_return_se": se,
                                                            "group_wall_time_s": 100.0}]}))
        (d / "sweep_args.json").write_text(json.dumps({"env": env, "methods": method, "set": extra}))
    _named_eval(walker / "dr" / "default" / "final_eval_named.json", [("BipedalWalker", 120.0, 29.5, 0.0)])
    # DCD's six levels and one more, whose solved rate must not enter the six-level mean
    six = [("BipedalWalker", 254.0, 5.8, 0.9), ("Hardcore", -140.7, 12.5, 0.3), ("Stairs", -68.2, 2.7, 0.0),
           ("PitGap", -92.1, 1.7, 0.0), ("Stump", -143.8, 11.5, 0.0), ("Roughness", -90.9, 7.0, 0.0),
           ("Insane", 300.0, 1.0, 1.0)]
    _named_eval(walker2 / "accel" / "default" / "final_eval_named.json", six)
    out = tmp_path / "baselines.json"
    assert baselines_record.main(["--device", "NVIDIA H200", "--date", "2026-11-25", "--lander", str(lander),
                                  "--walker", str(walker), "--walker", str(walker2), "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert (rec["device"], rec["date"]) == ("NVIDIA H200", "2026-11-25")
    plr = rec["lander"]["plr"]
    assert (plr["seeds"], plr["final_mean"], plr["final_se"], plr["set"]) == (10, 89.3, 6.0, ["level_switch=episode"])
    assert plr["sweep_args"]["env"] == "lander"
    dr = rec["walker"]["dr"]
    assert dr["levels"] == {"BipedalWalker": {"return": 120.0, "se": 29.5, "solved": 0.0}}
    assert dr["test_set_b"] == {"mean": -33.4, "se": 7.3}
    assert dr["dcd_six_solved_mean"] is None  # not all six levels were evaluated
    assert rec["walker"]["accel"]["dcd_six_solved_mean"] == pytest.approx(1.2 / 6)


def test_baselines_record_keep_adds_a_run_and_keeps_the_entries_it_did_not_measure(tmp_path):
    from experiments import baselines_record

    def sweep(d, method, mean):
        (d / method / "default").mkdir(parents=True)
        (d / "sweep.json").write_text(json.dumps({"rows": [{"method": method, "seeds": 5, "dir": f"{method}/default",
                                                            "final_test_return_mean": mean, "final_test_return_se": 1.0}]}))
        (d / "sweep_args.json").write_text(json.dumps({"env": "walker", "methods": method, "set": []}))
        _named_eval(d / method / "default" / "final_eval_named.json", [("BipedalWalker", mean, 1.0, 0.5)])

    sweep(tmp_path / "a", "dr", -33.4)
    sweep(tmp_path / "b", "dr", -20.0)
    sweep(tmp_path / "c", "paired", -29.8)
    out = tmp_path / "baselines.json"
    assert baselines_record.main(["--device", "H200", "--date", "2026-11-25", "--walker", str(tmp_path / "a"),
                                  "--note", "first", "--out", str(out)]) == 0
    assert baselines_record.main(["--keep", "--device", "H100", "--date", "2026-11-26", "--walker", str(tmp_path / "c"),
                                  "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert [(r["device"], r["date"]) for r in rec["runs"]] == [("H200", "2026-11-25"), ("H100", "2026-11-26")]
    assert rec["runs"][0]["note"] == "first"
    assert (rec["walker"]["dr"]["run"], rec["walker"]["dr"]["test_set_b"]["mean"]) == (0, -33.4)
    assert (rec["walker"]["paired"]["run"], rec["walker"]["paired"]["test_set_b"]["mean"]) == (1, -29.8)
    # a method measured again replaces its entry and names the new run
    assert baselines_record.main(["--keep", "--device", "H100", "--date", "2026-11-27", "--walker", str(tmp_path / "b"),
                                  "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert len(rec["runs"]) == 3 and (rec["walker"]["dr"]["run"], rec["walker"]["dr"]["test_set_b"]["mean"]) == (2, -20.0)
    assert rec["walker"]["paired"]["run"] == 1


def test_baselines_record_reads_one_run_directory_and_refuses_another_env(tmp_path, capsys):
    from experiments import baselines_record
    from shed_jax.presets import build_experiment

    run = tmp_path / "bipedal_dr"
    run.mkdir()
    exp = build_experiment("bipedal", "dr", "paper").to_dict()
    exp["loop"]["num_episodes"] = 2  # one setting apart from the preset: it must be named in the entry
    (run / "config.json").write_text(json.dumps({"experiment": exp, "seeds": 5, "root_seed": 0}))
    (run / "summary.json").write_text(json.dumps({"method": "dr", "seeds": 5, "final_test_return_mean": -37.1,
                                                  "final_test_return_se": 2.5, "wall_time_s": 816.0}))
    _named_eval(run / "final_eval_named.json", [("BipedalWalker", 66.7, 27.1, 0.08)])
    out = tmp_path / "b.json"
    assert baselines_record.main(["--device", "H200", "--date", "2026-11-28", "--bipedal", str(run), "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    dr = rec["bipedal"]["dr"]
    assert dr["test_set_b"] == {"mean": -37.1, "se": 2.5} and dr["wall_time_s"] == 816.0
    assert dr["levels"] == {"BipedalWalker": {"return": 66.7, "se": 27.1, "solved": 0.08}}
    assert dr["set"] == ["episodes=2"] and dr["sweep_args"]["run"] == str(run)
    # the same directory under another env's flag, or a directory that is no run, is one line naming it
    for flag, path, words in (("--walker", run, "pass it with --bipedal"), ("--bipedal", tmp_path, "neither a sweep")):
        with pytest.raises(SystemExit) as e:
            baselines_record.main(["--device", "H200", flag, str(path), "--out", str(tmp_path / "x.json")])
        assert e.value.code == 2 and words in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_dcd_budget_runs_fill_the_bipedal_records_dcd_block_and_other_runs_are_refused(tmp_path, capsys):
    from experiments import baselines_record
    from shed_jax.presets import build_experiment

    def run(name, method, preset, flat, steps=3360 * 196_608, scored=0.0, **overrides):
        d = tmp_path / name
        d.mkdir()
        exp = build_experiment("bipedal", method, preset, **overrides).to_dict()
        (d / "config.json").write_text(json.dumps({"experiment": exp, "seeds": 5, "root_seed": 0}))
        (d / "summary.json").write_text(json.dumps({"method": method, "seeds": 5, "final_test_return_mean": 1.0,
                                                    "final_test_return_se": 0.5, "student_env_steps_last_episode": steps,
                                                    "student_env_steps_total": steps, "eval_env_steps_total": scored}))
        _named_eval(d / "final_eval_named.json", [("BipedalWalker", flat, 3.0, 0.9), ("Stump", -10.0, 2.0, 0.0)])
        return str(d)

    def refused(args, words):
        with pytest.raises(SystemExit) as e:
            baselines_record.main(args)
        assert e.value.code == 2 and words in capsys.readouterr().err

    target = tmp_path / "bipedal.json"
    target.write_text(json.dumps({"device": "cpu", "parity": {"flat": {"gym_mean": 1.0}}}))
    out = tmp_path / "dcd.json"
    common = ["--device", "H200", "--date", "2026-12-01", "--out", str(out), "--dcd-into", str(target)]
    assert baselines_record.main(["--bipedal", run("dr", "dr", "dcd", 266.0), *common]) == 0
    # a later call (another machine, another day) adds its method and keeps the first
    # ACCEL spends DCD's budget on training and on scoring new levels (DCD's accounting): both count
    trained = 292_505_955.4
    accel = run("accel", "accel", "dcd", 310.0, steps=trained, scored=3360 * 196_608 - trained)
    assert baselines_record.main(["--keep", "--bipedal", accel, *common[:3], "2026-12-02", *common[4:]]) == 0
    rec = json.loads(target.read_text())
    assert rec["parity"] == {"flat": {"gym_mean": 1.0}} and rec["device"] == "cpu"  # the record's other keys stay
    assert rec["dcd"]["dr"]["BipedalWalker"] == {"return": 266.0, "se": 3.0, "solved": 0.9}
    assert rec["dcd"]["accel"]["Stump"]["solved"] == 0.0
    assert {m: (v["date"], v["seeds"]) for m, v in rec["dcd_source"].items()} == {"dr": ("2026-12-01", 5),
                                                                                 "accel": ("2026-12-02", 5)}
    # not DCD's budget as the preset has it: another preset, a changed setting, a stopped-short run
    refused(["--bipedal", run("paper", "plr", "paper", 50.0), *common], "got plr (preset paper)")
    refused(["--bipedal", run("short", "plr", "dcd", 50.0, steps_per_episode=16), *common], "settings apart from the preset")
    refused(["--bipedal", run("cut", "plr", "dcd", 50.0, steps=1000), *common], "1000 student steps per seed (1000.0 with")
    refused(["--bipedal", run("cut2", "plr", "dcd", 50.0, steps=1000, scored=3360 * 196_608), *common],
            "1000 student steps per seed (660603880 with level scoring), not 660,602,880")
    # a teacher's student at the budget with its evaluation roll-outs on top: the training steps count
    assert baselines_record.main(["--keep", "--bipedal", run("shed", "shed", "dcd", 5.0, scored=1e7), *common]) == 0
    assert "shed" in json.loads(target.read_text())["dcd"]
    assert "plr" not in json.loads(target.read_text())["dcd"]
    # a broken record to write into, or a summary without its fields: one line, and --out is not written
    bad, out2 = tmp_path / "bad.json", tmp_path / "out2.json"
    bad.write_text("{not json")
    refused(["--bipedal", run("dr2", "dr", "dcd", 1.0), "--device", "H200", "--out", str(out2), "--dcd-into", str(bad)],
            f"--dcd-into {bad}")
    (tmp_path / "dr2" / "summary.json").write_text(json.dumps({"method": "dr"}))
    refused(["--bipedal", str(tmp_path / "dr2"), "--device", "H200", "--out", str(out2)], "lacks seeds, final_test_return_mean")
    (tmp_path / "dr2" / "summary.json").write_text("[]")
    refused(["--bipedal", str(tmp_path / "dr2"), "--device", "H200", "--out", str(out2)], "holds a JSON list")
    assert not out2.exists()
