"""experiments.piece_record: a piece's log read into the facts its record states."""
import json

import pytest

from experiments import piece_record

LOG = (
    "[shed_jax] jax 0.11.2, backend gpu: 1 x NVIDIA H100 80GB HBM3; compilation cache /c\n"
    "[shed_jax] resuming runs/paper_shed from budget step 752/1000\n"
    "aot_cache: b52d3155b3128bd3... read from its stand-in in 7.8 s, not traced\n"
    "[shed_jax] compiled in 7.8 s\n"
    "shed/bipedal:  75%| | 752/1000 [00:00<?, ?step/s]\r"
    "shed/bipedal:  75%| | 754/1000 [00:10<21:58,  5.36s/step]aot_cache: 77917dd6f70f19cf... read from its stand-in in 2.0 s, not traced\n"
    "aot_cache: 0123456789abcdef... stand-in written\n"
    "aot_cache: fedcba9876543210... stand-in not used (ValueError: entry changed); tracing it\n"
    "aot_cache: 1111222233334444... not compiled, so no stand-in (RuntimeError: out of memory (while autotuning))\n"
    "shed/bipedal:  84%| | 844/1000 [08:08<13:49,  5.31s/step]\n"
    "[shed_jax] --time-limit 494s reached: stopped at budget step 844/1000\n"
)


def test_parse_reads_steps_time_and_stand_ins():
    p = piece_record.parse(LOG)
    assert p["gpu"] == "1 x NVIDIA H100 80GB HBM3" and p["jax"] == "0.11.2"
    assert p["budget_steps"] == [752, 844] and p["steps"] == 92 and p["of"] == 1000
    assert p["bar_elapsed_s"] == 8 * 60 + 8
    assert p["s_per_step"] == pytest.approx(488 / 92, abs=1e-3)
    assert p["compiled_in_s"] == 7.8
    assert p["stand_ins_read"] == [{"key": "b52d3155b3128bd3", "s": 7.8}, {"key": "77917dd6f70f19cf", "s": 2.0}]
    assert p["stand_ins_written"] == ["0123456789abcdef"]
    assert p["stand_ins_passed_over"] == [{"key": "fedcba9876543210", "why": "ValueError: entry changed"}]
    assert p["programs_failed"] == [{"key": "1111222233334444", "stage": "compiled",
                                     "why": "RuntimeError: out of memory (while autotuning)"}]


def test_parse_reads_the_last_piece_by_its_end_of_training():
    last = LOG.replace("[shed_jax] --time-limit 494s reached: stopped at budget step 844/1000\n",
                       "shed/bipedal: 100%| | 1000/1000 [22:08<00:00,  5.36s/step]\n"
                       "[shed_jax] training done (1000/1000 budget steps); writing the plots and summary.json...\n")
    p = piece_record.parse(last)
    assert p["budget_steps"] == [752, 1000] and p["steps"] == 248 and p["finished"] is True
    assert p["bar_elapsed_s"] == 22 * 60 + 8
    assert piece_record.parse(LOG)["finished"] is False


def test_parse_hours_on_the_bar():
    p = piece_record.parse(LOG.replace("[08:08<13:49", "[1:00:08<13:49"))
    assert p["bar_elapsed_s"] == 3608


def test_parse_names_a_log_without_a_resume():
    with pytest.raises(ValueError, match="no resumed budget step"):
        piece_record.parse(LOG.replace("resuming", "starting"))


def test_main_writes_the_record_and_refuses_a_missing_piece(tmp_path, capsys):
    (tmp_path / "piece3.log").write_text(LOG)
    out = tmp_path / "r.json"
    assert piece_record.main([str(tmp_path), "--pieces", "3", "--out", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["pieces"]["3"]["steps"] == 92 and "piece_record" in rec["command"]
    assert rec["device"] == "1 x NVIDIA H100 80GB HBM3" and rec["date"]
    assert piece_record.main([str(tmp_path), "--pieces", "4", "--out", str(out)]) == 2
    assert "piece4.log does not exist" in capsys.readouterr().err
