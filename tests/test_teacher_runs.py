"""experiments/teacher_runs.py: summaries of a sweep's metrics and the pooled record, on hand-made runs."""
import json
import math

import pytest

import numpy as np

from experiments import teacher_runs
from experiments.teacher_runs import aggregate, record, reward_noise, summarise_point


def _write_point(d, method, point, rows, finals):
    d.mkdir(parents=True)
    (d / "summary.json").write_text(json.dumps({"method": method, "point": point, "values": {}, "seeds": len(finals),
                                                "wall_time_s": 1.0, "final_test_return_per_seed": finals}))
    (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")


def _rows(seed, tests, bounds):
    """Two episodes of two steps; the test runs at each episode's last step."""
    out = []
    for ep in (0, 1):
        for t in (0, 1):
            out.append({"seed": seed, "episode": ep, "test_return": tests[ep] if t == 1 else math.nan,
                        "info/extras/at_bound_fraction": bounds[ep][t], "info/teacher_reward": 1.0 + t,
                        "info/extras/box_width": [0.5, 1.0, 1.5]})
    return out


def test_summarise_and_pool_two_runs(tmp_path):
    a, b = tmp_path / "a" / "hmdp-x" / "default", tmp_path / "b" / "hmdp-x" / "default"
    _write_point(a, "hmdp-x", "default", _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]]), [14.0])
    _write_point(b, "hmdp-x", "default", _rows(0, [20.0, 18.0], [[0.0, 0.0], [0.5, 0.5]]), [18.0])
    runs = [summarise_point(a), summarise_point(b)]
    assert runs[0]["test_by_seed_episode"] == {"0": {"0": 10.0, "1": 14.0}}
    assert runs[0]["diagnostics_by_episode"]["at_bound_fraction"] == {"0": pytest.approx(0.1), "1": pytest.approx(0.2)}
    assert runs[0]["diagnostics_by_episode"]["box_width"]["0"] == pytest.approx(1.0)
    assert runs[0]["diagnostics_by_episode"]["teacher_reward"]["1"] == pytest.approx(1.5)
    e = aggregate(runs)["hmdp-x"]
    assert e["seeds"] == 2 and e["final_episode"] == [1]
    assert e["final_mean"] == pytest.approx(16.0) and e["final_se"] == pytest.approx(2.0)  # sd(14, 18) / sqrt 2
    assert e["episode0_mean"] == pytest.approx(15.0) and e["episode0_se"] == pytest.approx(5.0)
    assert e["paired_gain_mean"] == pytest.approx(1.0) and e["paired_gain_se"] == pytest.approx(3.0)  # gains 4, -2
    assert e["at_bound_fraction"] == pytest.approx((0.2 + 0.5) / 2)  # last episode, mean over runs
    assert e["late_mean"] is None and e["paired_late_gain_mean"] is None  # two tested episodes: no late endpoint
    (tmp_path / "c.json").write_text(json.dumps(runs))
    record([tmp_path / "c.json"], tmp_path / "r.json", "cpu", "cmd", "2026-01-01", ["a note"])
    rec = json.loads((tmp_path / "r.json").read_text())
    assert rec["device"] == "cpu" and rec["notes"] == ["a note"] and rec["lander"]["hmdp-x"]["seeds"] == 2


def test_reward_noise_hand_computed_and_summarised(tmp_path):
    # (step in episode, r, again, crossed, crossed back)
    rows = [(0, 10.0, 8.0, 12.0, 6.0), (0, 20.0, 20.0, 14.0, 26.0), (3, 1.0, 3.0, 0.0, 4.0), (7, 2.0, 2.0, 2.0, 2.0),
            (8, 4.0, 2.0, float("nan"), 1.0)]  # a row with a NaN check is left out
    out = reward_noise(rows)
    assert out["t0"] == {"n": 2, "reward_mean": 15.0, "reward_sd": pytest.approx(50 ** 0.5),
                         "paired_noise_sd": pytest.approx((4 / 2 / 2) ** 0.5),  # diffs 2, 0
                         "crossed_noise_sd": pytest.approx(((36 + 144) / 2 / 2) ** 0.5)}  # diffs 6, -12
    assert "t1-4" not in out and "t5+" not in out  # one row each: no SD
    assert out["all"]["n"] == 4 and out["all"]["paired_noise_sd"] == pytest.approx(((4 + 0 + 4 + 0) / 4 / 2) ** 0.5)
    d = tmp_path / "s" / "hmdp-x" / "default"
    base = _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]])
    for i, r in enumerate(base):  # teacher reward 1 + t; the checks 1 + t + 1, + 2, - 2
        t = i % 2
        r.update({"step_in_episode": t, "info/extras/reward_again": 2.0 + t, "info/extras/reward_crossed": 3.0 + t,
                  "info/extras/reward_crossed_back": -1.0 + t})
    _write_point(d, "hmdp-x", "default", base, [14.0])
    noise = summarise_point(d)["reward_noise"]
    assert noise["all"]["paired_noise_sd"] == pytest.approx(0.5 ** 0.5) and noise["all"]["crossed_noise_sd"] == pytest.approx(8 ** 0.5)
    assert aggregate([summarise_point(d)])["hmdp-x"]["reward_noise"] == [noise]


def test_a_sweeps_set_values_keep_its_runs_apart(tmp_path):
    """Two sweeps of hmdp-x at the point actor_lr=1e-05, one with --set twin_critics=true: the group name from
    sweep.json keeps them two entries, where the method name alone would pool their seeds."""
    from experiments.teacher_runs import summarise

    for name, group, finals in (("plain", "hmdp-x", [14.0]), ("td3", "hmdp-x[twin_critics=true]", [30.0])):
        d = tmp_path / name
        _write_point(d / "hmdp-x" / "actor_lr=1e-05", "hmdp-x", "actor_lr=1e-05",
                     _rows(0, [10.0, finals[0]], [[0.0, 0.0], [0.0, 0.0]]), finals)
        (d / "sweep.json").write_text(json.dumps({"rows": [{"method": "hmdp-x", "group": group, "point": "actor_lr=1e-05",
                                                             "dir": "hmdp-x/actor_lr=1e-05"}]}))
    summarise([tmp_path / "plain", tmp_path / "td3"], tmp_path / "c.json")
    entries = aggregate(json.loads((tmp_path / "c.json").read_text()))
    assert sorted(entries) == ["hmdp-x[actor_lr=1e-05]", "hmdp-x[twin_critics=true][actor_lr=1e-05]"]
    assert entries["hmdp-x[twin_critics=true][actor_lr=1e-05]"]["final_mean"] == 30.0
    assert entries["hmdp-x[actor_lr=1e-05]"]["seeds"] == 1


def test_shorter_sweeps_get_their_own_entry_and_a_stopped_run_is_kept(tmp_path):
    """A sweep run with --episodes 2 is labelled episodes=2, so it never pools with full-length runs; a run
    stopped by --time-limit (no summary.json, no sweep.json row) is summarised from its metrics so far, its
    group taken from config.json, its last tested episode as final and marked stopped."""
    from experiments.teacher_runs import summarise

    full = tmp_path / "full" / "hmdp-x" / "default"
    _write_point(full, "hmdp-x", "default", _rows(0, [10.0, 14.0], [[0.0, 0.0], [0.0, 0.0]]), [14.0])
    short = tmp_path / "short"
    _write_point(short / "hmdp-x" / "default", "hmdp-x", "default", _rows(0, [10.0, 20.0], [[0.0, 0.0], [0.0, 0.0]]), [20.0])
    (short / "sweep_args.json").write_text(json.dumps({"episodes": 2}))
    stopped = tmp_path / "stopped" / "hmdp-x" / "default"
    stopped.mkdir(parents=True)
    (stopped / "config.json").write_text(json.dumps({"seeds": 1, "sweep_point": {
        "name": "default", "values": {}, "group": "hmdp-x[num_eval_episodes=32]"}}))
    (stopped / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in _rows(0, [10.0, 7.0], [[0.0, 0.0], [0.0, 0.0]])[:3]))
    (tmp_path / "stopped" / "sweep_args.json").write_text(json.dumps({"episodes": 2}))
    summarise([tmp_path / "full", short, tmp_path / "stopped"], tmp_path / "c.json")
    runs = json.loads((tmp_path / "c.json").read_text())
    assert [r["group"] for r in runs] == ["hmdp-x", "hmdp-x[episodes=2]", "hmdp-x[num_eval_episodes=32,episodes=2]"]
    assert runs[2]["stopped"] is True and runs[2]["final_per_seed"] is None
    assert runs[2]["test_by_seed_episode"] == {"0": {"0": 10.0}}  # episode 1 never reached its test
    entries = aggregate(runs)
    assert entries["hmdp-x"]["final_mean"] == 14.0 and entries["hmdp-x[episodes=2]"]["final_mean"] == 20.0
    e = entries["hmdp-x[num_eval_episodes=32,episodes=2]"]
    assert e["final_episode"] == [0] and e["runs"][0]["stopped"] is True


def test_paper_csv_and_dr_reference_join_the_record(tmp_path):
    """The paper teachers' CSV: the test at each tested episode's last step; other methods' rows left out.
    DR comes from the baselines record with null teacher fields."""
    from experiments.teacher_runs import paper_runs
    head = "method,env,seed,episode,step_in_episode,student_env_steps_in_episode,teacher_reward,test_return\n"
    rows = []
    for method, off in (("SHED", 0.0), ("h-MDP", 100.0), ("SHED eta=10", 500.0)):
        for seed in (0, 1):
            for ep in (0, 10):
                for t in (0, 1):
                    rows.append(f"{method},lander,{seed},{ep},{t},0,{2.0 + t},{off + 10 * seed + ep + 0.5 * t}")
    csv_path = tmp_path / "p.csv"
    csv_path.write_text(head + "\n".join(rows) + "\n")
    runs = {r["method"]: r for r in paper_runs(csv_path)}
    assert sorted(runs) == ["hmdp", "shed"]
    assert runs["shed"]["test_by_seed_episode"] == {"0": {"0": 0.5, "10": 10.5}, "1": {"0": 10.5, "10": 20.5}}
    assert runs["hmdp"]["diagnostics_by_episode"]["teacher_reward"] == {"0": 2.5, "10": 2.5}
    (tmp_path / "b.json").write_text(json.dumps({"lander": {"dr": {"seeds": 10, "final_mean": 111.8, "final_se": 4.4}}}))
    (tmp_path / "none.json").write_text("[]")
    record([tmp_path / "none.json"], tmp_path / "r.json", "cpu", "cmd", "2026-01-01", (), csv_path, tmp_path / "b.json")
    lander = json.loads((tmp_path / "r.json").read_text())["lander"]
    assert sorted(lander) == ["dr", "hmdp", "shed"]
    assert lander["dr"]["final_mean"] == 111.8 and lander["dr"]["episode0_mean"] is None
    shed = lander["shed"]
    assert shed["final_mean"] == pytest.approx(15.5) and shed["episode0_mean"] == pytest.approx(5.5)
    assert shed["paired_gain_mean"] == pytest.approx(10.0) and shed["paired_gain_se"] == pytest.approx(0.0)
    assert shed["at_bound_fraction"] is None and shed["final_episode"] == [10]


def test_late_endpoint_is_the_mean_of_the_last_three_tested_episodes():
    from experiments.teacher_runs import aggregate
    run = {"method": "m", "point": "default", "diagnostics_by_episode": {},
           "test_by_seed_episode": {"0": {"0": 10.0, "10": 30.0, "20": 14.0, "30": 16.0, "49": 18.0},
                                    "1": {"0": 20.0, "10": 0.0, "20": 26.0, "30": 20.0, "49": 20.0}}}
    e = aggregate([run])["m"]
    assert e["late_episodes"] == 3
    assert e["late_mean"] == pytest.approx(19.0) and e["late_se"] == pytest.approx(3.0)  # late 16 and 22
    assert e["paired_late_gain_mean"] == pytest.approx(4.0) and e["paired_late_gain_se"] == pytest.approx(2.0)  # 6 and 2
    assert e["paired_gain_mean"] == pytest.approx(4.0)  # last episode alone: 8 and 0


def test_plot_labels_tell_apart_runs_of_one_pooled_group():
    from experiments.teacher_runs import plot_labels
    runs = [{"method": "hmdp-x", "group": "g", "sweep": "runs/a"}, {"method": "hmdp-x", "group": "g", "sweep": "runs/b"},
            {"method": "shed-x", "sweep": "runs/a"}]
    assert plot_labels(runs) == ["g (a)", "g (b)", "shed-x"]


def test_plot_panels_are_the_test_return_and_the_diagnostics_some_run_logged():
    from experiments.teacher_runs import plot_panels
    paper = {"diagnostics_by_episode": {"at_bound_fraction": {"0": 0.1, "1": 0.5}, "box_width": {"0": None},
                                        "teacher_reward": {"0": None, "1": 150.0}}}
    learning = {"diagnostics_by_episode": {"box_width": {"0": None, "1": 0.4}}}
    assert [k for _, k in plot_panels([paper])] == [None, "at_bound_fraction", "teacher_reward"]
    assert [k for _, k in plot_panels([paper, learning])] == [None, "at_bound_fraction", "teacher_reward", "box_width"]
    assert plot_panels([{"diagnostics_by_episode": {}}]) == [("test return", None)]


def test_plot_writes_a_figure_and_names_what_is_missing(tmp_path):
    from experiments.teacher_runs import plot
    a = tmp_path / "s" / "hmdp-x" / "default"
    _write_point(a, "hmdp-x", "default", _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]]), [14.0])
    (tmp_path / "c.json").write_text(json.dumps([summarise_point(a)]))
    plot([tmp_path / "c.json"], tmp_path / "f.png", ["hmdp-x"])
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(SystemExit, match=r"^plot: no run named shed-x in "):
        plot([tmp_path / "c.json"], tmp_path / "g.png", ["shed-x"])


def test_late_box_means_each_steps_lowest_and_highest_level(tmp_path, capsys):
    rows = [  # (episode, levels [n, d]); episode 0 is before the window and must not count
        (0, [[-100.0, 0.0], [100.0, 9.0]]),
        (1, [[-2.0, 1.0], [-1.0, 3.0], [-1.5, 2.0]]),
        (2, [[-4.0, 0.5], [0.0, 5.0]]),
    ]
    point = tmp_path / "hmdp-x" / "default"
    point.mkdir(parents=True)
    (point / "metrics.jsonl").write_text("\n".join(json.dumps({"seed": 0, "episode": e, "info/levels": lv}) for e, lv in rows))
    box = teacher_runs.late_box([point], from_episode=1)
    assert box["steps"] == 2
    np.testing.assert_allclose(box["low"], [(-2 - 4) / 2, (1 + 0.5) / 2])
    np.testing.assert_allclose(box["high"], [(-1 + 0) / 2, (3 + 5) / 2])
    np.testing.assert_allclose(box["low_sd"], [1.0, 0.25])
    teacher_runs.main(["late-box", str(point), "--from-episode", "1"])
    assert "--set low=[-3,0.75] --set high=[-0.5,4]" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no budget step with info/levels at teacher episode >= 3"):
        teacher_runs.late_box([point], from_episode=3)


def _write_sweep(d, root_seed, finals, device="gpu: test"):
    (d / "dr" / "default").mkdir(parents=True)
    (d / "sweep.json").write_text(json.dumps({"device": device, "command": "sweep ...", "date": "2026-11-28", "root_seed": root_seed,
                                              "rows": [{"method": "dr", "group": "dr", "dir": "dr/default"}]}))
    (d / "dr" / "default" / "summary.json").write_text(json.dumps({"final_test_return_per_seed": finals}))


def test_paired_matches_seeds_by_root_seed_and_index(tmp_path, capsys):
    _write_sweep(tmp_path / "a0", 0, [10.0, 20.0])
    _write_sweep(tmp_path / "a1", 1, [30.0, 40.0])
    _write_sweep(tmp_path / "b1", 1, [25.0, 31.0])  # listed first: pairing is by key, not by order
    _write_sweep(tmp_path / "b0", 0, [4.0, 18.0])
    res = teacher_runs.paired([tmp_path / "a0", tmp_path / "a1"], [tmp_path / "b1", tmp_path / "b0"])
    assert res["a"]["mean"] == pytest.approx(25.0) and res["a"]["seeds"] == 4
    assert res["a"]["se"] == pytest.approx(np.std([10, 20, 30, 40], ddof=1) / 2)
    assert res["b"]["mean"] == pytest.approx(19.5) and res["b"]["final_by_root_seed"] == {"0": [4.0, 18.0], "1": [25.0, 31.0]}
    # a - b per seed: 6, 2, 5, 9
    assert res["paired"]["mean"] == pytest.approx(5.5) and res["paired"]["seeds"] == 4
    assert res["paired"]["se"] == pytest.approx(np.std([6, 2, 5, 9], ddof=1) / 2)
    assert res["a"]["sweeps"][1]["device"] == "gpu: test" and res["b"]["sweeps"][0]["root_seed"] == 1
    out = tmp_path / "c.json"
    teacher_runs.main(["paired", str(tmp_path / "a0"), str(tmp_path / "a1"), "--vs", str(tmp_path / "b0"), "--out", str(out)])
    rec = json.loads(out.read_text())
    # a0 and a1 against b0 alone: only root seed 0 pairs (6, 2); a keeps its 4 seeds
    assert rec["paired"] == {"seeds": 2, "mean": pytest.approx(4.0), "se": pytest.approx(2.0)}
    assert rec["a"]["seeds"] == 4 and rec["device"] == "gpu: test" and "date" in rec and rec["command"].startswith("python -m")
    assert "a - b, paired: 4.0 ± 2.0 (2 seeds)" in capsys.readouterr().out
    teacher_runs.main(["paired", str(tmp_path / "a0"), "--vs", str(tmp_path / "b0"), "--plot", str(tmp_path / "c.png")])
    assert (tmp_path / "c.png").stat().st_size > 1000


def test_paired_refuses_too_few_common_seeds_repeated_roots_and_unfinished_sweeps(tmp_path):
    _write_sweep(tmp_path / "a", 0, [1.0, 2.0])
    _write_sweep(tmp_path / "b", 3, [1.0, 2.0])
    _write_sweep(tmp_path / "c", 0, [3.0, 5.0, 9.0])  # root seed 0 with 3 seeds: its seeds 0 and 1 are a's
    with pytest.raises(SystemExit, match="0 seed"):
        teacher_runs.paired([tmp_path / "a"], [tmp_path / "b"])
    res = teacher_runs.paired([tmp_path / "a"], [tmp_path / "c"])
    assert res["paired"] == {"seeds": 2, "mean": pytest.approx(-2.5), "se": pytest.approx(0.5)}  # 1-3, 2-5
    with pytest.raises(SystemExit, match="root seed 0 appears twice"):  # the same students would count twice
        teacher_runs.paired([tmp_path / "a", tmp_path / "c"], [tmp_path / "b"])
    _write_sweep(tmp_path / "stopped", 3, None)
    with pytest.raises(SystemExit, match="no finite final test return"):
        teacher_runs.paired([tmp_path / "stopped"], [tmp_path / "b"])
    with pytest.raises(SystemExit, match="is not a finished sweep"):
        teacher_runs.paired([tmp_path / "nowhere"], [tmp_path / "b"])
    _write_sweep(tmp_path / "old", 3, [7.0, 8.0])  # a sweep from before sweep.json kept its root seed
    sweep = json.loads((tmp_path / "old" / "sweep.json").read_text())
    del sweep["root_seed"]
    (tmp_path / "old" / "sweep.json").write_text(json.dumps(sweep))
    (tmp_path / "old" / "dr" / "default" / "config.json").write_text(json.dumps({"root_seed": 3}))
    assert teacher_runs.paired([tmp_path / "old"], [tmp_path / "b"])["paired"]["mean"] == pytest.approx(6.0)
    (tmp_path / "a" / "sweep.json").write_text(json.dumps({"rows": [{"dir": "x"}, {"dir": "y"}]}))
    with pytest.raises(SystemExit, match="2 points"):
        teacher_runs.paired([tmp_path / "a"], [tmp_path / "b"])



def test_targets_use_the_late_gain_and_the_named_dr_entry():
    lander = {
        "dr": {"seeds": 10, "final_mean": 100.0, "final_se": 4.0, "episode0_mean": None},
        "dr[x] (40 seeds)": {"seeds": 40, "final_mean": 110.0, "final_se": 3.0, "episode0_mean": None},
        "t": {"seeds": 30, "episode0_mean": 1.0, "final_mean": 130.0, "final_se": 1.0, "late_mean": 124.0, "late_se": 4.0,
              "paired_gain_mean": 9.0, "paired_gain_se": 1.0, "paired_late_gain_mean": 5.0, "paired_late_gain_se": 2.6,
              "at_bound_fraction": 0.02},
        "u": {"seeds": 10, "episode0_mean": 1.0, "final_mean": 119.0, "final_se": 4.0, "paired_gain_mean": 9.0,
              "paired_gain_se": 4.0, "paired_late_gain_mean": None, "at_bound_fraction": 0.5},
    }
    t = teacher_runs.targets(lander, "dr[x] (40 seeds)")
    assert t["dr_reference"] == "dr[x] (40 seeds)" and sorted(t["by_method"]) == ["t", "u"]
    assert teacher_runs.targets(lander)["by_method"]["t"]["margin_over_dr"] == pytest.approx(24.0)  # "dr": 124 - 100
    assert "margin_over_dr" not in teacher_runs.targets(lander, "nope")["by_method"]["t"]
    one_seed = lander | {"dr": {"seeds": 1, "final_mean": 100.0, "final_se": None, "episode0_mean": None},
                         "untested": {"seeds": 3, "episode0_mean": math.nan, "final_mean": 1.0}}
    t1 = teacher_runs.targets(one_seed)  # a reference without an SE gives no margin, and no crash
    assert "margin_over_dr" not in t1["by_method"]["t"] and "untested" not in t1["by_method"]
    a = t["by_method"]["t"]  # late endpoint: gain 5.0 < 2 x 2.6; margin 124 - 110 = 14 > 2 x hypot(4, 3) = 10
    assert a["endpoint"] == "late" and a["gain_over_episode0"] == 5.0 and not a["gain_shown"]
    assert a["margin_over_dr"] == pytest.approx(14.0) and a["margin_se"] == pytest.approx(5.0) and a["beats_dr_shown"]
    assert a["at_bound_met"]
    b = t["by_method"]["u"]  # no late endpoint: final; gain 9 > 2 x 4; margin 9 < 2 x 5
    assert b["endpoint"] == "final" and b["gain_shown"] and not b["beats_dr_shown"] and b["at_bound_met"] is False


def test_a_paired_file_joins_the_record_as_two_dr_entries(tmp_path):
    _write_sweep(tmp_path / "a", 0, [10.0, 20.0, 30.0])
    _write_sweep(tmp_path / "b", 0, [12.0, 18.0, 24.0])
    c = tmp_path / "c.json"
    teacher_runs.main(["paired", str(tmp_path / "a"), "--vs", str(tmp_path / "b"), "--out", str(c)])
    (tmp_path / "none.json").write_text("[]")
    record([tmp_path / "none.json"], tmp_path / "r.json", "cpu", "cmd", "2026-01-01", controls=[c])
    rec = json.loads((tmp_path / "r.json").read_text())
    lander = rec["lander"]  # both sets are group "dr", so each name says its side
    assert lander[f"dr (3 seeds) [first set of {c}]"]["final_mean"] == pytest.approx(20.0)
    assert lander[f"dr (3 seeds) [second set of {c}]"]["final_se"] == pytest.approx(np.std([12, 18, 24], ddof=1) / math.sqrt(3))
    with pytest.raises(SystemExit, match="two entries named"):  # the same control twice would overwrite itself
        record([tmp_path / "none.json"], tmp_path / "r2.json", "cpu", "cmd", "2026-01-01", controls=[c, c])
    with pytest.raises(SystemExit, match="--dr-reference 'dr' is not an entry"):
        record([tmp_path / "none.json"], tmp_path / "r2.json", "cpu", "cmd", "2026-01-01", controls=[c], dr_reference="dr")
    assert rec["targets"]["by_method"] == {}


def _write_run(d, root_seed, rows, finals=None):
    """The directory of one `shed_jax run`: config.json and metrics.jsonl at its top; summary.json once finished."""
    d.mkdir(parents=True)
    from shed_jax.presets import build_experiment
    exp = build_experiment("walker", "hmdp-x", "paper", episodes=2).to_dict()  # what `run --episodes 2` saves
    (d / "config.json").write_text(json.dumps({"experiment": exp, "seeds": 2, "root_seed": root_seed,
                                               "backend": "gpu", "devices": ["cuda:0"]}))
    (d / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    if finals is not None:
        (d / "summary.json").write_text(json.dumps({"env": "walker", "method": "hmdp-x", "seeds": len(finals),
                                                    "wall_time_s": 9.0, "final_test_return_per_seed": finals}))


def test_a_run_directory_is_summarised_and_paired_like_a_sweep(tmp_path, capsys):
    rows = _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]]) + _rows(1, [20.0, 30.0], [[0.0, 0.0], [0.0, 0.0]])
    _write_run(tmp_path / "stopped", 0, rows)  # stopped by --time-limit: no summary.json yet
    _write_run(tmp_path / "run", 0, rows, finals=[14.0, 30.0])
    teacher_runs.summarise([tmp_path / "stopped", tmp_path / "run"], tmp_path / "c.json")
    stopped, run = json.loads((tmp_path / "c.json").read_text())
    # the preset's walker hmdp-x has 20 teacher episodes, these runs 2: their label says so
    assert stopped["stopped"] and stopped["group"] == "hmdp-x[episodes=2]" and stopped["env"] == "walker"
    assert run["group"] == "hmdp-x[episodes=2]"
    assert run["test_by_seed_episode"] == {"0": {"0": 10.0, "1": 14.0}, "1": {"0": 20.0, "1": 30.0}}
    assert run["final_per_seed"] == [14.0, 30.0] and run["env"] == "walker" and "stopped" not in run
    e = aggregate([run])["hmdp-x[episodes=2]"]
    assert e["paired_gain_mean"] == pytest.approx(7.0) and e["paired_gain_se"] == pytest.approx(3.0)  # gains 4, 10
    _write_sweep(tmp_path / "dr", 0, [4.0, 18.0])  # the same root seed: its seeds pair with the run's
    res = teacher_runs.paired([tmp_path / "run"], [tmp_path / "dr"])
    assert res["paired"] == {"seeds": 2, "mean": pytest.approx(11.0), "se": pytest.approx(1.0)}  # 10, 12
    assert res["a"]["sweeps"][0]["device"] == "gpu: cuda:0" and res["a"]["sweeps"][0]["group"] == "hmdp-x[episodes=2]"
    with pytest.raises(SystemExit, match="not a finished sweep or run"):  # a stopped run has no summary.json
        teacher_runs.paired([tmp_path / "stopped"], [tmp_path / "dr"])
    (tmp_path / "stopped" / "config.json").unlink()  # metrics but no config: one line, no traceback
    with pytest.raises(SystemExit, match="neither summary.json nor a run's config.json"):
        teacher_runs.summarise([tmp_path / "stopped"], tmp_path / "e.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="holds no run"):  # never an empty summary written as if it were one
        teacher_runs.summarise([tmp_path / "empty"], tmp_path / "e.json")
    assert not (tmp_path / "e.json").exists()


def test_a_walker_record_keeps_its_runs_under_walker_with_the_walker_dr(tmp_path, monkeypatch):
    rows = _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]]) + _rows(1, [20.0, 30.0], [[0.0, 0.0], [0.0, 0.0]])
    _write_run(tmp_path / "run", 0, rows, finals=[14.0, 30.0])
    teacher_runs.summarise([tmp_path / "run"], tmp_path / "c.json")
    # the walker's baselines record keeps DR's final as test_set_b
    (tmp_path / "b.json").write_text(json.dumps({"walker": {"dr": {"seeds": 5, "test_set_b": {"mean": 15.0, "se": 1.0}}}}))
    teacher_runs.main(["record", str(tmp_path / "c.json"), "--env", "walker", "--dr", str(tmp_path / "b.json"),
                       "--device", "gpu", "--command", "cmd", "--out", str(tmp_path / "r.json")])
    rec = json.loads((tmp_path / "r.json").read_text())
    assert "lander" not in rec and sorted(rec["walker"]) == ["dr", "hmdp-x[episodes=2]"]
    assert rec["walker"]["dr"]["final_mean"] == 15.0 and rec["walker"]["hmdp-x[episodes=2]"]["final_mean"] == pytest.approx(22.0)
    t = rec["targets"]["by_method"]["hmdp-x[episodes=2]"]
    assert t["margin_over_dr"] == pytest.approx(7.0) and t["margin_se"] == pytest.approx(math.hypot(8.0, 1.0))
    with pytest.raises(SystemExit, match="the runs are on walker, the record on lander"):  # never filed under the wrong env
        record([tmp_path / "c.json"], tmp_path / "x.json", "gpu", "cmd", None)
    with pytest.raises(SystemExit, match="no lander DR entry"):
        record([], tmp_path / "x.json", "gpu", "cmd", None, dr=tmp_path / "b.json")
    assert not (tmp_path / "x.json").exists()
    # without --out a walker record never lands on the lander's record
    monkeypatch.chdir(tmp_path)
    teacher_runs.main(["record", str(tmp_path / "c.json"), "--env", "walker", "--device", "gpu", "--command", "cmd"])
    assert (tmp_path / "docs/results/teacher_walker.json").exists() and not (tmp_path / "docs/results/teacher.json").exists()


def test_a_control_paired_with_the_records_own_teacher_adds_only_the_other_set(tmp_path, capsys):
    for name in ("t", "t2"):  # two teacher sweeps of the same group: only the one in the record is left out
        _write_sweep(tmp_path / name, 0, [10.0, 20.0, 30.0])
        sweep = json.loads((tmp_path / name / "sweep.json").read_text())
        sweep["rows"][0]["group"] = "hmdp-x"
        (tmp_path / name / "sweep.json").write_text(json.dumps(sweep))
    _write_sweep(tmp_path / "d", 0, [12.0, 18.0, 24.0])
    c, c2 = tmp_path / "c.json", tmp_path / "c2.json"
    teacher_runs.main(["paired", str(tmp_path / "t"), "--vs", str(tmp_path / "d"), "--out", str(c)])
    teacher_runs.main(["paired", str(tmp_path / "t2"), "--vs", str(tmp_path / "d"), "--out", str(c2)])
    p = tmp_path / "runs" / "hmdp-x" / "default"  # sweep t's teacher as `summarise` writes it
    _write_point(p, "hmdp-x", "default", _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]]), [14.0])
    (tmp_path / "s.json").write_text(json.dumps([{"sweep": str(tmp_path / "t"), **summarise_point(p)}]))
    capsys.readouterr()
    record([tmp_path / "s.json"], tmp_path / "r.json", "cpu", "cmd", "2026-01-01", controls=[c])
    assert "its first set (hmdp-x (3 seeds)) is already in the record from its runs; left out" in capsys.readouterr().out
    lander = json.loads((tmp_path / "r.json").read_text())["lander"]
    assert sorted(lander) == ["dr (3 seeds)", "hmdp-x"]  # no teacher-less copy of hmdp-x from the control
    assert lander["hmdp-x"]["episode0_mean"] == pytest.approx(10.0) and lander["dr (3 seeds)"]["final_mean"] == pytest.approx(18.0)
    record([tmp_path / "s.json"], tmp_path / "r2.json", "cpu", "cmd", "2026-01-01", controls=[c2])
    lander = json.loads((tmp_path / "r2.json").read_text())["lander"]  # t2 is other runs of the same group: kept
    assert sorted(lander) == ["dr (3 seeds)", "hmdp-x", "hmdp-x (3 seeds)"]
    assert lander["hmdp-x (3 seeds)"]["final_mean"] == pytest.approx(20.0) and lander["hmdp-x (3 seeds)"]["episode0_mean"] is None


def test_paired_records_the_environment_and_a_record_refuses_a_control_of_another(tmp_path):
    rows = _rows(0, [10.0, 14.0], [[0.0, 0.2], [0.1, 0.3]]) + _rows(1, [20.0, 30.0], [[0.0, 0.0], [0.0, 0.0]])
    _write_run(tmp_path / "run", 0, rows, finals=[14.0, 30.0])  # a walker run
    _write_sweep(tmp_path / "dr", 0, [4.0, 18.0])
    (tmp_path / "dr" / "sweep_args.json").write_text(json.dumps({"env": "walker"}))
    c = tmp_path / "c.json"
    teacher_runs.main(["paired", str(tmp_path / "run"), "--vs", str(tmp_path / "dr"), "--out", str(c)])
    assert json.loads(c.read_text())["env"] == "walker"
    (tmp_path / "none.json").write_text("[]")
    with pytest.raises(SystemExit, match="compares runs on walker, the record is on lander"):
        record([tmp_path / "none.json"], tmp_path / "r.json", "cpu", "cmd", "2026-01-01", controls=[c])
    record([tmp_path / "none.json"], tmp_path / "r.json", "cpu", "cmd", "2026-01-01", controls=[c], env="walker")
    assert len(json.loads((tmp_path / "r.json").read_text())["walker"]) == 2
    # a lander sweep against the walker run: no pairing across environments
    _write_sweep(tmp_path / "lander", 0, [4.0, 18.0])
    (tmp_path / "lander" / "sweep_args.json").write_text(json.dumps({"env": "lander"}))
    with pytest.raises(SystemExit, match="the sets hold runs on lander and walker"):
        teacher_runs.paired([tmp_path / "run"], [tmp_path / "lander"])


def test_run_settings_leave_out_fields_added_after_the_run():
    """A carried run keeps its own sources, so its config.json lacks fields added since; one that today's
    preset holds at its declared default is no setting, while a changed value or a non-default still is."""
    from shed_jax.presets import build_experiment

    exp = build_experiment("lander", "dr", "quick")
    cfg = {"experiment": exp.to_dict()}
    assert teacher_runs.run_settings(cfg) == []
    del cfg["experiment"]["ppo"]["log_std_min"]  # the field's default: no bound, the earlier behaviour
    assert teacher_runs.run_settings(cfg) == []
    cfg["experiment"]["ppo"]["hparams"]["lr"] = 1e-3
    assert teacher_runs.run_settings(cfg) == ["ppo.hparams.lr=0.001"]
    assert teacher_runs._is_field_default(exp, "ppo.log_std_min", -math.inf)
    assert not teacher_runs._is_field_default(exp, "ppo.log_std_min", -2.3)  # a bound the run did not have
    assert not teacher_runs._is_field_default(exp, "ppo.no_such_field", 1)
    assert not teacher_runs._is_field_default(exp, "ppo.hparams.no_such_field", 1)
