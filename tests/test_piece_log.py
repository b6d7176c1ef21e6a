"""experiments.piece_log: a piece's run.log made readable without losing what piece_record reads."""
from experiments import piece_log, piece_record

HIT = "DEBUG:jax._src.compiler:Persistent compilation cache hit for 'jit_chunk' with key 'jit_chunk-portable-ab'"
RAW = (
    "[shed_jax] jax 0.11.2, backend gpu: 1 x NVIDIA H100 80GB HBM3; compilation cache /c\n"
    "DEBUG:2026-12-06 17:48:16,023:jax._src.compiler:318: Enabling XLA kernel cache at '/c/k'\n"
    "DEBUG:jax._src.compiler:Enabling XLA kernel cache at '/c/k'\n"
    "DEBUG:2026-12-06 17:48:16,028:jax._src.compiler:166: Persistent compilation cache hit for 'jit_chunk' with key 'jit_chunk-portable-ab'\n"
    f"{HIT}\n{HIT}\n"
    "WARNING:jax._src.interpreters.partial_eval:TRACING CACHE MISS at f.py:1 because:\n"
    "  never seen input type signature:\n"
    "    x: f32[2]\n"
    "[shed_jax] resuming runs/x from budget step 118/1000\n"
    "[shed_jax] compiled in 9.2 s\n"
    "hmdp/bipedal:  12%| | 118/1000 [00:00<?, ?step/s]\r"
    "hmdp/bipedal:  12%| | 120/1000 [00:24<2:59:18, 12.23s/step]   step   120/1000  episode 2\r"
    "hmdp/bipedal:  16%| | 164/1000 [08:18<2:30:55, 10.83s/step]\n"
    "\n"
    "[shed_jax] --time-limit 503s reached: stopped at budget step 164/1000\n"
)


def test_readable_keeps_the_runs_lines_and_the_cache_hits_once():
    kept, explained, debug = piece_log.readable(RAW)
    assert explained == 3  # the explanation's first line and its indented body
    assert debug == 4  # both kernel-cache lines, the long form of the hit and its repeat
    assert kept == [
        "[shed_jax] jax 0.11.2, backend gpu: 1 x NVIDIA H100 80GB HBM3; compilation cache /c",
        HIT,
        "[shed_jax] resuming runs/x from budget step 118/1000",
        "[shed_jax] compiled in 9.2 s",
        "hmdp/bipedal:  12%| | 118/1000 [00:00<?, ?step/s]",
        "hmdp/bipedal:  12%| | 120/1000 [00:24<2:59:18, 12.23s/step]   step   120/1000  episode 2",
        "hmdp/bipedal:  16%| | 164/1000 [08:18<2:30:55, 10.83s/step]",
        "[shed_jax] --time-limit 503s reached: stopped at budget step 164/1000",
    ]


def test_the_readable_log_still_gives_piece_records_facts(tmp_path):
    raw = tmp_path / "run.log"
    raw.write_text(RAW)
    out = tmp_path / "piece3.log"
    assert piece_log.main([str(raw), str(out), "--name", "piece3"]) == 0
    text = out.read_text()
    assert text.startswith("[piece3: the run's log, carriage returns as line breaks, with 3 lines of JAX's "
                           "tracing-cache explanations and 4 lines of JAX's compiler debug output")
    assert piece_record.parse(text) == piece_record.parse(RAW)
    assert piece_record.parse(text)["budget_steps"] == [118, 164]


def test_a_missing_log_is_one_line(tmp_path, capsys):
    assert piece_log.main([str(tmp_path / "none.log"), str(tmp_path / "o.log"), "--name", "p"]) == 2
    assert capsys.readouterr().err.strip() == f"piece_log: no log at {tmp_path / 'none.log'}"
