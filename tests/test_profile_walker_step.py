"""experiments/profile_walker_step.py's input checks: one line and exit 2, before anything is built."""
from experiments import profile_walker_step


def test_from_run_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert profile_walker_step.main(["--from-run", str(tmp_path), "--out", str(tmp_path / "p.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"profile_walker_step: {tmp_path} is not a run directory (no config.json)"
    assert not (tmp_path / "p.json").exists()


def test_from_run_refuses_ppo_overrides(tmp_path, capsys):
    (tmp_path / "config.json").write_text("{}")
    argv = ["--from-run", str(tmp_path), "--ppo", "lr=1e-4", "--out", str(tmp_path / "p.json")]
    assert profile_walker_step.main(argv) == 2
    assert "--ppo cannot change a saved run's students" in capsys.readouterr().err
    assert not (tmp_path / "p.json").exists()


def test_env_choices_are_the_two_walkers(capsys):
    import pytest

    with pytest.raises(SystemExit) as e:
        profile_walker_step.main(["--env", "lander"])
    assert e.value.code == 2 and "invalid choice: 'lander'" in capsys.readouterr().err


def test_parts_outside_the_four_are_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "p.json"
    assert profile_walker_step.main(["--parts", "rollout,eval", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "profile_walker_step: --parts takes a comma-separated list of rollout, update, teacher_eval, test; got 'rollout,eval'"
    assert profile_walker_step.main(["--parts", ",", "--out", str(out)]) == 2
    assert not out.exists()
