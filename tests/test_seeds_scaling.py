"""experiments.seeds_scaling and piece_record on a run's first piece: seconds per budget step and seed."""
import json

import pytest

from experiments import piece_record, seeds_scaling


def fresh_log(seeds: int, steps: int, elapsed: str) -> str:
    """A fresh run's first piece as run_piece.sh logs it (progress bar, time limit, checkpoint)."""
    return (
        "[shed_jax] jax 0.11.2, backend gpu: 1 x NVIDIA H100 80GB HBM3; compilation cache /c\n"
        f"[shed_jax] hmdp on bipedal: 20 episode(s) x 50 budget steps, {seeds} seed(s), ~196,608 student env "
        "steps per budget step -> runs/x\n"
        "[shed_jax] compiled in 95.1 s\n"
        f"hmdp/bipedal:   0%| | 2/1000 [00:05<1:00:00, 5.00s/step]\r"
        f"hmdp/bipedal:   1%| | {steps}/1000 [{elapsed}<1:00:00, 5.00s/step]\n"
        f"[shed_jax] --time-limit 60s reached: stopped at budget step {steps}/1000\n"
    )


def test_a_first_piece_starts_at_budget_step_0_and_names_its_seeds():
    p = piece_record.parse(fresh_log(5, 10, "00:53"))
    assert p["budget_steps"] == [0, 10] and p["steps"] == 10 and p["seeds"] == 5
    assert p["bar_elapsed_s"] == 53 and p["s_per_step"] == 5.3 and p["compiled_in_s"] == 95.1


def test_rows_per_seed_against_the_fewest_seeds():
    table = seeds_scaling.rows({"s20.log": fresh_log(20, 6, "00:48"), "s5.log": fresh_log(5, 10, "00:53")})
    assert [r["seeds"] for r in table] == [5, 20]  # sorted by seeds, whatever the order given
    five, twenty = table
    assert five["s_per_step_per_seed"] == 1.06 and five["seed_cost_vs_fewest"] == 1.0
    assert twenty["s_per_step"] == 8.0 and twenty["s_per_step_per_seed"] == 0.4
    assert twenty["step_time_vs_fewest"] == round(8.0 / 5.3, 3)
    assert twenty["seed_cost_vs_fewest"] == round(0.4 / 1.06, 3)


def test_a_log_that_ran_no_step_is_named(tmp_path, capsys):
    log = tmp_path / "s10.log"
    log.write_text("[shed_jax] hmdp on bipedal: 10 seed(s)\n[shed_jax] compiled in 99 s\n")
    assert seeds_scaling.main([str(log), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("seeds_scaling: s10.log: ") and "\n" not in err


def test_the_record_holds_the_logs_gpu_and_the_rows(tmp_path):
    a, b = tmp_path / "s5.log", tmp_path / "s20.log"
    a.write_text(fresh_log(5, 10, "00:53"))
    b.write_text(fresh_log(20, 6, "00:48"))
    out = tmp_path / "r.json"
    assert seeds_scaling.main([str(a), str(b), "--out", str(out), "--note", "h-MDP"]) == 0
    rec = json.loads(out.read_text())
    assert rec["device"] == "1 x NVIDIA H100 80GB HBM3" and rec["note"] == "h-MDP"
    assert [r["seeds"] for r in rec["rows"]] == [5, 20]


@pytest.mark.parametrize("text", ["", "[shed_jax] stopped at budget step 4/1000\n"])
def test_parse_names_what_a_log_lacks(text):
    with pytest.raises(ValueError, match="names no resumed budget step or run start"):
        piece_record.parse(text)


def test_the_device_script_runs_each_folder_fresh_and_returns_only_its_log(tmp_path):
    """experiments/seeds_scaling.sh over run_piece.sh, the run a stub ``python`` that prints a line and
    exits 75: one log per folder comes back, no checkpoint or cache; a folder with a checkpoint is
    refused (exit 1) and the others still run."""
    import os
    import shutil
    import subprocess
    import tarfile

    from tests.test_run_piece import SCRIPT

    repo = tmp_path / "repo"
    src = tmp_path / "src"
    for d in ("shed_jax", "envs", "experiments"):
        (repo / d).mkdir(parents=True)
        (src / d).mkdir(parents=True)
    shutil.copy(SCRIPT, repo / "experiments" / "run_piece.sh")
    shutil.copy(SCRIPT, src / "experiments" / "run_piece.sh")  # the run's sources hold it too
    shutil.copy(SCRIPT.with_name("seeds_scaling.sh"), repo / "experiments" / "seeds_scaling.sh")
    for d in (repo, src):  # AOT_GATE=1 probes with it (the stub's probe fails, so nothing is gated)
        (d / "experiments" / "aot_cache.py").write_text("")
    for name, seeds in (("s5", 5), ("s20", 20), ("old", 5)):
        f = repo / name
        f.mkdir()
        with tarfile.open(f / "src.tgz", "w:gz") as tar:
            for d in ("shed_jax", "envs", "experiments"):
                tar.add(src / d, arcname=d)
        (f / "run.args").write_text(f"--env bipedal --method hmdp --seeds {seeds} --out runs/{name}\n")
    (repo / "old" / "ckpt.tgz.aa").write_text("a checkpoint")
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "python").write_text('#!/bin/bash\n[ "${2:-}" = probe ] && exit 1\n'
                                 'echo "ran $*"; mkdir -p .cache/device runs/x; echo c > .cache/device/e; exit 75\n')
    (bin_ / "python").chmod(0o755)
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "tmp").mkdir()
    env = {**os.environ, "PATH": f"{bin_}:{os.environ['PATH']}", "OUT": str(out), "RUN_PIECE_GPU": "",
           "TMPDIR": str(tmp_path / "tmp")}
    env.pop("AOT_GATE", None)
    r = subprocess.run(["bash", "experiments/seeds_scaling.sh", "100", "s5", "old", "s20/"], cwd=repo, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "seeds_scaling: old has a checkpoint" in r.stdout
    assert sorted(p.name for p in out.iterdir()) == ["s20.log", "s5.log"], r.stdout + r.stderr
    assert "--seeds 5 --out runs/s5" in (out / "s5.log").read_text()
    assert "--seeds 20 --out runs/s20" in (out / "s20.log").read_text()
    assert not list((tmp_path / "tmp").iterdir())  # the scratch folders are gone
