"""experiments.compile_size: its one-line error and its record (the measurement itself is a compile,
run by hand: docs/log/benchmarks.md)."""
import json

from experiments import checkpoint_size, compile_size


def test_unknown_preset_is_one_line(capsys):
    assert compile_size.main(["--env", "bipedal", "--preset", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("compile_size: unknown preset 'nope'")


def test_record_merges_labels(tmp_path, monkeypatch):
    sizes = iter([{"init_lower_s": 1.0, "chunk_stablehlo_chars": 14}, {"init_lower_s": 2.0, "chunk_stablehlo_chars": 12}])
    monkeypatch.setattr(checkpoint_size, "build_batch", lambda env, method, preset, seeds: (None, (env, method, preset, seeds)))
    monkeypatch.setattr(compile_size, "measure", lambda batch: next(sizes))
    out = tmp_path / "r.json"
    assert compile_size.main(["--label", "before", "--out", str(out)]) == 0
    assert compile_size.main(["--method", "plr", "--label", "after", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert set(doc) == {"before", "after"}
    assert doc["before"]["chunk_stablehlo_chars"] == 14 and doc["after"]["chunk_stablehlo_chars"] == 12
    assert doc["after"]["experiment"] == {"env": "bipedal", "method": "plr", "preset": "paper", "seeds": 1}
    assert doc["after"]["command"] == "python -m experiments.compile_size --method plr --label after --out " + str(out)
    assert doc["before"]["device"] and doc["before"]["date"]
