"""experiments/run_piece.sh: a run carried across machine leases in pieces. The run itself is a stub
``python`` on PATH (it records its arguments, writes a "checkpoint" and a "cache" and exits 75), so
what is checked is the script's own work: start or resume, the run's sources put in place, the
time limit, the parts it returns, and its errors."""
import os
import pathlib
import shutil
import subprocess
import tarfile

import pytest

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "run_piece.sh"
ADOPT = SCRIPT.with_name("adopt_piece.sh")
STUB = """#!/bin/bash
echo "$@" >> "$STUB_LOG"
if [ "${2:-}" = probe ]; then  # experiments/aot_cache.py probe ARGS OUT.json
  echo '{"programs": {"jit_init_point": {"key": "jit_init_point-abc", "portable_key": "jit_init_point-portable-def"}}}' > "$4"; echo probed; exit 0
fi
[ -n "${STUB_KEY:-}" ] && mkdir -p .cache/device/jax && touch ".cache/device/jax/$STUB_KEY-cache"
[ -n "${PIECE_SETTING:-}" ] && echo "setting $PIECE_SETTING" >> "$STUB_LOG"
[ -f runs/x/state ] && echo "found $(cat runs/x/state)" >> "$STUB_LOG"
[ -n "${STUB_STEPS:-}" ] && for s in $STUB_STEPS; do mkdir -p runs/x/checkpoints/${s%+}; [ "${s%+}" = "$s" ] || touch runs/x/checkpoints/${s%+}/commit_success.txt; done
mkdir -p .cache/device/jax
echo cached > .cache/device/jax/entry
echo kernels > .cache/device/jax/xla_gpu_kernel_cache_file
[ -n "${STUB_BIG_CACHE:-}" ] && head -c "$STUB_BIG_CACHE" /dev/urandom > .cache/device/jax/big
[ -n "${STUB_NO_RUN:-}" ] && exit 1  # a compile cut off: no run directory, the cache alone
if [ -n "${STUB_MISS:-}" ]; then  # the chunk is not in the cache: the run says so, then compiles for long
  echo "logging [${JAX_EXPLAIN_CACHE_MISSES:-}] [${JAX_LOGGING_LEVEL:-}] [${JAX_DEBUG_LOG_MODULES:-}]" >> "$STUB_LOG"
  echo "$STUB_MISS"; echo "killed" > "$STUB_LOG.term"; sleep 60; rm "$STUB_LOG.term"; exit 0
fi
mkdir -p runs/x
echo "piece $PIECE" > runs/x/state
echo '{"step": 0}' > runs/x/metrics.jsonl
exit ${STUB_RC:-75}
"""


def _tree(root: pathlib.Path, folder: pathlib.Path) -> pathlib.Path:
    """A disposable copy of a repository: stale sources, the script, and the in-flight folder's files."""
    repo = root / "repo"
    for d in ("shed_jax", "envs", "experiments"):
        (repo / d).mkdir(parents=True)
        (repo / d / "stale.txt").write_text("the tree's own")
    shutil.copy(SCRIPT, repo / "experiments" / "run_piece.sh")
    shutil.copytree(folder, repo / "inflight")
    return repo


def _piece(root, repo, piece, seconds="100", out=True, **extra):
    bin_ = root / "bin"
    bin_.mkdir(exist_ok=True)
    (bin_ / "python").write_text(STUB)
    (bin_ / "python").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_}:{os.environ['PATH']}", "STUB_LOG": str(root / "stub.log"), "PIECE": str(piece),
           "RUN_PIECE_GPU": "", "TMPDIR": str(root / "tmp"), **extra}  # no GPU model unless a test names one
    (root / "tmp").mkdir(exist_ok=True)
    if out:
        env["OUT"] = str(root / f"out{piece}")
        (root / f"out{piece}").mkdir()
    else:
        env.pop("OUT", None)
    return subprocess.run(["bash", "experiments/run_piece.sh", "inflight", seconds], cwd=repo, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.fixture
def folder(tmp_path):
    src = tmp_path / "src"
    for d in ("shed_jax", "envs", "experiments"):
        (src / d).mkdir(parents=True)
        (src / d / "run_sources.txt").write_text("the run's own")
    f = tmp_path / "folder"
    f.mkdir()
    with tarfile.open(f / "src.tgz", "w:gz") as tar:
        for d in ("shed_jax", "envs", "experiments"):
            tar.add(src / d, arcname=d)
    (f / "run.args").write_text("--env lander --method dr --preset quick --seeds 1 --out runs/x\n")
    return f


def test_start_then_resume_from_the_returned_parts(tmp_path, folder):
    first = tmp_path / "first"
    repo = _tree(first, folder)
    (repo / ".source_commit").write_text("abc1234\n")  # the tree's commit, from slim_tree.sh
    r = _piece(first, repo, 1)
    assert r.returncode == 75, r.stdout + r.stderr
    assert not (repo / ".source_commit").exists()  # it does not describe the run's sources
    call = (first / "stub.log").read_text().split()
    # started with the folder's flags, the script's own, and a limit that leaves the piece's last
    # 45 s to the run's checkpoint and the packing
    assert call[:3] == ["-m", "shed_jax", "run"] and "--resume" not in call
    assert " ".join(call[3:13]) == "--env lander --method dr --preset quick --seeds 1 --out runs/x"
    assert call[13:18] == ["--keep", "1", "--no-gif", "--checkpoint-every", "120"]
    assert call[18] == "--time-limit" and 50 <= int(call[19]) <= 55
    # the run's sources replaced the tree's before it ran
    assert (repo / "shed_jax" / "run_sources.txt").is_file() and not (repo / "shed_jax" / "stale.txt").exists()
    out = first / "out1"
    assert sorted(p.name for p in out.iterdir()) == ["cache.tgz.aa", "ckpt.tgz.aa", "run.log"]
    # with a checkpoint, the cache comes back without XLA's kernel cache file
    with tarfile.open(out / "cache.tgz.aa") as tar:
        assert sorted(tar.getnames()) == [".cache/device", ".cache/device/jax", ".cache/device/jax/entry"]

    # the next lease: a fresh copy of the tree, the returned parts copied into the folder
    for part in out.glob("*.tgz.*"):
        shutil.copy(part, folder / part.name)
    second = tmp_path / "second"
    repo2 = _tree(second, folder)
    assert _piece(second, repo2, 2).returncode == 75
    log = (second / "stub.log").read_text().splitlines()
    assert log[0].split()[3:5] == ["--resume", "runs/x"] and "--env" not in log[0]
    assert log[1] == "found piece 1"  # the checkpoint was unpacked before the run resumed
    assert (repo2 / ".cache" / "device" / "jax" / "entry").read_text() == "cached\n"


def test_a_piece_cut_off_before_its_first_checkpoint_keeps_the_kernel_cache(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    r = _piece(tmp_path, repo, 1, STUB_NO_RUN="1")
    assert r.returncode == 1, r.stdout + r.stderr
    out = tmp_path / "out1"
    assert sorted(p.name for p in out.iterdir()) == ["cache.tgz.aa", "run.log"]
    with tarfile.open(out / "cache.tgz.aa") as tar:
        assert ".cache/device/jax/xla_gpu_kernel_cache_file" in tar.getnames()


def test_a_run_that_finished_returns_its_results_without_its_cache(tmp_path, folder):
    """A finished run's cache is read by no later piece; leaving it out keeps several finished runs'
    results within one call's return. adopt_piece.sh takes the results and keeps the folder's cache."""
    repo = _tree(tmp_path, folder)
    r = _piece(tmp_path, repo, 1, STUB_RC="0")
    assert r.returncode == 0, r.stdout + r.stderr
    out = tmp_path / "out1"
    assert sorted(p.name for p in out.iterdir()) == ["ckpt.tgz.aa", "run.log"]
    assert "its compilation cache is not packed" in r.stdout
    (folder / "cache.tgz.aa").write_bytes(b"the folder's cache")
    a = _adopt(folder, out, tmp_path)
    assert a.returncode == 0, a.stdout + a.stderr
    assert (folder / "cache.tgz.aa").read_bytes() == b"the folder's cache"
    assert (folder / "ckpt.tgz.aa").read_bytes() == (out / "ckpt.tgz.aa").read_bytes()
    assert "keeps its cache" in a.stdout
    # KEEP_CACHE=1 packs it all the same
    r = _piece(tmp_path / "keep", _tree(tmp_path / "keep", folder), 3, STUB_RC="0", KEEP_CACHE="1")
    assert r.returncode == 0 and (tmp_path / "keep" / "out3" / "cache.tgz.aa").is_file()


def test_a_run_that_goes_on_leaves_its_metrics_jsonl_to_the_checkpoints_history(tmp_path, folder):
    """A resume writes metrics.jsonl again from the checkpoint's history, so a piece that stops with a
    complete checkpoint packs the run without it; a finished run, or one with no complete checkpoint
    to rebuild it from, packs it."""
    def packed(name, **extra):
        root = tmp_path / name
        r = _piece(root, _tree(root, folder), 1, **extra)
        with tarfile.open(root / "out1" / "ckpt.tgz.aa") as tar:
            return r.returncode, sorted(n for n in tar.getnames() if n.startswith("runs/x/") and "/checkpoints/" not in n)

    assert packed("goes_on", STUB_STEPS="4+") == (75, ["runs/x/checkpoints", "runs/x/state"])
    assert packed("finished", STUB_STEPS="4+", STUB_RC="0") == (0, ["runs/x/checkpoints", "runs/x/metrics.jsonl", "runs/x/state"])
    assert packed("uncommitted", STUB_STEPS="4") == (75, ["runs/x/checkpoints", "runs/x/metrics.jsonl", "runs/x/state"])


def test_run_env_is_exported_to_every_piece(tmp_path, folder):
    (folder / "run.env").write_text("# the same for every piece\nPIECE_SETTING=all\n\n")
    repo = _tree(tmp_path, folder)
    assert _piece(tmp_path, repo, 1).returncode == 75
    assert (tmp_path / "stub.log").read_text().splitlines()[1] == "setting all"


def test_bad_arguments_are_refused_before_any_work(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    r = _piece(tmp_path, repo, 1, seconds="ten")
    assert r.returncode == 2 and "SECONDS must be a whole number" in r.stdout
    r = _piece(tmp_path, repo, 5, seconds="40")  # less than the checkpoint and the packing need
    assert r.returncode == 2 and "leaves no time to run" in r.stdout
    r = _piece(tmp_path, repo, 6, CHECKPOINT_EVERY="2m")
    assert r.returncode == 2 and "CHECKPOINT_EVERY must be a whole number of seconds" in r.stdout
    r = _piece(tmp_path, repo, 2, out=False)
    assert r.returncode != 0 and "OUT set" in r.stderr
    (repo / "inflight" / "run.args").write_text("--env lander --method dr\n")
    r = _piece(tmp_path, repo, 3)
    assert r.returncode == 2 and "lacks --out DIR" in r.stdout
    (repo / "inflight" / "run.args").write_text("--env lander --method dr --out runs/x\n")
    (repo / "inflight" / "run.env").write_text("PIECE_SETTING=a; touch pwned\n")  # sourced: shell syntax refused
    r = _piece(tmp_path, repo, 4)
    assert r.returncode == 2 and "run.env: every line must be NAME=VALUE" in r.stdout
    assert not (repo / "pwned").exists()
    # nothing ran, and the tree's own sources are still there
    assert not (tmp_path / "stub.log").exists() and (repo / "shed_jax" / "stale.txt").is_file()


def _adopt(folder, src, cwd):
    return subprocess.run(["bash", str(ADOPT), str(folder), str(src)], cwd=cwd, capture_output=True, text=True, timeout=60)


def test_adopt_takes_the_returned_parts_and_refuses_a_broken_archive(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    assert _piece(tmp_path, repo, 1).returncode == 75
    out = tmp_path / "out1"
    (folder / "cache.tgz.ab").write_bytes(b"a stale second part")  # an older, longer split
    r = _adopt(folder, out, tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(p.name for p in folder.glob("*.tgz.*")) == ["cache.tgz.aa", "ckpt.tgz.aa"]
    assert (folder / "ckpt.tgz.aa").read_bytes() == (out / "ckpt.tgz.aa").read_bytes()
    assert "ckpt: 1 part(s)" in r.stdout

    # a piece that saved nothing: the cache is taken, the folder's checkpoint kept
    cut = tmp_path / "cut"
    cut.mkdir()
    shutil.copy(out / "cache.tgz.aa", cut / "cache.tgz.aa")
    ckpt = (folder / "ckpt.tgz.aa").read_bytes()
    r = _adopt(folder, cut, tmp_path)
    assert r.returncode == 0 and "keeps its checkpoint" in r.stdout
    assert (folder / "ckpt.tgz.aa").read_bytes() == ckpt
    assert not (folder / "aot_probe.json").exists()

    # a piece run with AOT_PROBE=1: its probe comes into the folder too
    (cut / "aot_probe.json").write_text('{"programs": {}}')
    r = _adopt(folder, cut, tmp_path)
    assert r.returncode == 0 and (folder / "aot_probe.json").read_text() == '{"programs": {}}'

    # a truncated archive: refused, the folder untouched
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "cache.tgz.aa").write_bytes((out / "cache.tgz.aa").read_bytes()[:-8])
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    r = _adopt(folder, broken, tmp_path)
    assert r.returncode == 3 and "not a whole gzip archive" in r.stdout
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    r = _adopt(folder, tmp_path / "nothing", tmp_path)
    assert r.returncode == 2 and "holds no cache.tgz" in r.stdout


def test_aot_probe_runs_before_the_run_and_its_key_is_checked_after(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1, AOT_PROBE="1", STUB_KEY="jit_init_point-abc")
    assert r.returncode == 75, r.stdout + r.stderr
    calls = (tmp_path / "stub.log").read_text().splitlines()
    assert calls[0].split()[1:] == ["probe", "inflight/run.args", str(tmp_path / "out1" / "aot_probe.json")]
    assert calls[0].split()[0].endswith(".py") and "--env lander" in calls[1]  # the probe first, then the run
    assert (tmp_path / "out1" / "aot_probe.json").exists() and "probed" in r.stdout
    assert "the run's initial state is in the cache under the probed key" in r.stdout
    assert not list((tmp_path / "tmp").iterdir())  # the probe tool's copy is gone with the script


def test_aot_probe_names_a_run_whose_initial_state_has_another_key(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1, AOT_PROBE="1", STUB_KEY="jit_init_point-zzz")
    assert r.returncode == 75, r.stdout + r.stderr
    assert "the cache holds no initial state under the probed key jit_init_point-abc" in r.stdout


@pytest.mark.parametrize("carried", [True, False])
def test_aot_gate_runs_only_where_the_carried_cache_serves_this_host(tmp_path, folder, carried):
    """AOT_GATE=1 probes, and starts the run only when the carried cache holds the initial state
    under the key this host computes (the stub's probe says jit_init_point-abc)."""
    _cache_archive(folder / "cache.tgz.aa", "jit_init_point-abc-cache" if carried else "jit_init_point-old-cache")
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1, AOT_GATE="1")
    calls = (tmp_path / "stub.log").read_text().splitlines()
    assert calls[0].split()[1] == "probe"
    if carried:
        assert r.returncode == 75, r.stdout + r.stderr
        assert "holds the initial state under this host's key" in r.stdout and "--env lander" in calls[1]
        # the probe's key parts come back at the end of the run's log, not as files of their own (a
        # call returns 8 files at most)
        assert {p.name for p in (tmp_path / "out1").iterdir()} == {"run.log", "cache.tgz.aa", "ckpt.tgz.aa"}
        log = (tmp_path / "out1" / "run.log").read_text()
        assert log.endswith('"portable_key": "jit_init_point-portable-def"}}}\n') and "the carried cache served them" in log
        assert "the run's initial state is in the cache under the probed key" in r.stdout
    else:
        assert r.returncode == 6, r.stdout + r.stderr
        assert "holds no initial state under this host's key jit_init_point-abc" in r.stdout
        assert len(calls) == 1 and sorted(p.name for p in (tmp_path / "out1").iterdir()) == ["aot_probe.json", "aot_probe.log"]
    assert not list((tmp_path / "tmp").iterdir())  # removed on every exit, the gate's included


@pytest.mark.parametrize("line", ["[shed_jax] jit_chunk is not in the compilation cache (key jit_chunk-ab...): compiling it",
                                  "W1205 jax._src.compiler PERSISTENT COMPILATION CACHE MISS for 'jit_chunk' with key 'jit_chunk-ab'"])
def test_aot_gate_stops_a_run_whose_chunk_is_not_in_the_carried_cache(tmp_path, folder, line):
    """With AOT_GATE=1 a run that starts to compile its chunk (the run's own line, or JAX's for older
    sources) is stopped at once: exit 7 within seconds, not the compile's minutes, and nothing packed."""
    _cache_archive(folder / "cache.tgz.aa", "jit_init_point-abc-cache")
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1, AOT_GATE="1", STUB_MISS=line)
    assert r.returncode == 7, r.stdout + r.stderr
    assert "the chunk is not in the carried cache: the run was stopped before compiling it" in r.stdout
    assert (tmp_path / "stub.log.term").exists()  # the stub was killed in its compile, not left to finish
    assert not list((tmp_path / "out1").glob("*.tgz.*"))
    assert (tmp_path / "out1" / "aot_probe.json").exists()  # this host's key parts, to find what differed
    # these sources lack the run's own line, so JAX's miss line is shown: through the compiler module's
    # debug log, not JAX_EXPLAIN_CACHE_MISSES, whose tracing explainer raised inside GPU traces
    assert "logging [] [WARNING] [jax._src.compiler]" in (tmp_path / "stub.log").read_text().splitlines()


@pytest.mark.parametrize("entry", [None, "jit_init_point-old-cache"])
def test_aot_gate_lets_a_resume_without_any_initial_state_entry_run(tmp_path, folder, entry):
    """A resume never compiles the initial state, so a folder may leave its entry out of the cache to
    fit a call: AOT_GATE=1 then runs the piece and leaves the decision to the chunk's lookup. An entry
    under another host's key still stops it (exit 6), as does a missing entry for a first piece."""
    _cache_archive(folder / "cache.tgz.aa", entry or "jit_chunk-x-cache")
    ckpt = tmp_path / "ckpt_src"
    (ckpt / "runs" / "x").mkdir(parents=True)
    (ckpt / "runs" / "x" / "state").write_text("piece 1")
    with tarfile.open(folder / "ckpt.tgz.aa", "w:gz") as tar:
        tar.add(ckpt / "runs", arcname="runs")
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 2, AOT_GATE="1")
    calls = (tmp_path / "stub.log").read_text().splitlines()
    if entry is None:
        assert r.returncode == 75, r.stdout + r.stderr
        assert "holds no initial state under any key (a resume does not compile it)" in r.stdout
        assert calls[1].split()[:5] == ["-m", "shed_jax", "run", "--resume", "runs/x"] and "found piece 1" in calls
        # the probe's key parts at the end of the run's log, not files of their own (8 files a call)
        assert {p.name for p in (tmp_path / "out2").iterdir()} == {"run.log", "cache.tgz.aa", "ckpt.tgz.aa"}
        assert (tmp_path / "out2" / "run.log").read_text().endswith('"portable_key": "jit_init_point-portable-def"}}}\n')
    else:
        assert r.returncode == 6, r.stdout + r.stderr
        assert len(calls) == 1  # the probe alone


def test_aot_gate_stops_a_first_piece_whose_cache_has_no_initial_state(tmp_path, folder):
    _cache_archive(folder / "cache.tgz.aa", "jit_chunk-x-cache")
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1, AOT_GATE="1")
    assert r.returncode == 6 and "holds no initial state under this host's key" in r.stdout, r.stdout + r.stderr


def test_aot_gate_takes_0_or_1(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    r = _piece(tmp_path, repo, 1, AOT_GATE="yes")
    assert r.returncode == 2 and r.stdout.strip() == "run_piece: AOT_GATE must be 0 or 1, got 'yes'"


def test_without_aot_probe_nothing_is_probed(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    r = _piece(tmp_path, repo, 1)
    assert r.returncode == 75 and "probe" not in (tmp_path / "stub.log").read_text()
    assert not (tmp_path / "out1" / "aot_probe.json").exists() and "aot probe" not in r.stdout


def _cache_archive(path: pathlib.Path, name: str):
    """A cache part holding one marker file ``.cache/device/jax/NAME``."""
    src = path.parent / f"src_{name}"
    (src / ".cache" / "device" / "jax").mkdir(parents=True)
    (src / ".cache" / "device" / "jax" / name).write_text(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(path, "w:gz") as tar:
        tar.add(src / ".cache", arcname=".cache")


def test_a_gpu_models_own_cache_is_read_on_that_gpu_and_the_new_one_goes_back_there(tmp_path, folder):
    """FOLDER/gpu-h100/ (e.g. filled on a CPU host) serves an H100 host; FOLDER's own cache serves any
    other; adopt_piece puts each piece's cache back where it came from, the checkpoint always in FOLDER."""
    _cache_archive(folder / "cache.tgz.aa", "began_on_h200")
    _cache_archive(folder / "gpu-h100" / "cache.tgz.aa", "filled_for_h100")
    h200_cache = (folder / "cache.tgz.aa").read_bytes()
    runs = {}
    for gpu in ("h100", "h200"):
        root = tmp_path / gpu
        repo = _tree(root, folder)
        r = _piece(root, repo, 1, RUN_PIECE_GPU=gpu)
        assert r.returncode == 75, r.stdout + r.stderr
        have = {p.name for p in (repo / ".cache" / "device" / "jax").iterdir()}
        assert ("filled_for_h100" in have) == (gpu == "h100") and ("began_on_h200" in have) == (gpu == "h200")
        assert (root / "out1" / "gpu").read_text() == f"{gpu}\n"
        runs[gpu] = root / "out1"
    r = _adopt(folder, runs["h100"], tmp_path)
    assert r.returncode == 0 and "ran on h100" in r.stdout, r.stdout
    assert (folder / "gpu-h100" / "cache.tgz.aa").read_bytes() == (runs["h100"] / "cache.tgz.aa").read_bytes()
    assert (folder / "cache.tgz.aa").read_bytes() == h200_cache  # the other GPU's cache untouched
    assert (folder / "ckpt.tgz.aa").read_bytes() == (runs["h100"] / "ckpt.tgz.aa").read_bytes()
    assert not (folder / "gpu-h100" / "ckpt.tgz.aa").exists()
    r = _adopt(folder, runs["h200"], tmp_path)  # no gpu-h200/: the folder's own cache is replaced
    assert r.returncode == 0
    assert (folder / "cache.tgz.aa").read_bytes() == (runs["h200"] / "cache.tgz.aa").read_bytes()
    assert (folder / "gpu-h100" / "cache.tgz.aa").read_bytes() == (runs["h100"] / "cache.tgz.aa").read_bytes()


def test_gpu_model_names(tmp_path):
    model = SCRIPT.with_name("gpu_model.sh")
    names = {"NVIDIA H100 80GB HBM3": "h100", "NVIDIA H200": "h200", "NVIDIA A100-SXM4-40GB": "a100", "": ""}
    for name, want in names.items():
        r = subprocess.run(["bash", str(model), name], capture_output=True, text=True, timeout=30)
        assert r.returncode == 0 and r.stdout.strip() == want, (name, r.stdout)


def test_only_the_newest_committed_checkpoint_and_the_folders_own_cache_go_back(tmp_path, folder):
    """A stopped run may leave the checkpoint it resumed from (its deletion waits for the next save)
    and one it had not finished; only the newest complete one is packed. A warm machine's leftover
    cache of another run is not packed with this run's."""
    repo = _tree(tmp_path, folder)
    (repo / ".cache" / "device" / "jax").mkdir(parents=True)
    (repo / ".cache" / "device" / "jax" / "other-run-cache").write_text("another run's")
    # "+": the checkpoint is complete (commit_success.txt); 120 was cut off while being written
    r = _piece(tmp_path, repo, 1, STUB_STEPS="2+ 80+ 120")
    assert r.returncode == 75, r.stdout + r.stderr
    assert "left out checkpoint 2: the newest complete one is 80" in r.stdout and "left out checkpoint 120:" in r.stdout
    with tarfile.open(tmp_path / "out1" / "ckpt.tgz.aa") as tar:
        steps = {n.split("/")[3] for n in tar.getnames() if n.count("/") >= 3}
    assert steps == {"80"}
    with tarfile.open(tmp_path / "out1" / "cache.tgz.aa") as tar:
        assert sorted(tar.getnames()) == [".cache/device", ".cache/device/jax", ".cache/device/jax/entry"]


@pytest.mark.parametrize("gate", ["0", "1"])
def test_a_cache_with_portable_keys_runs_the_run_under_them(tmp_path, folder, gate):
    """A carried cache filled with portable keys (``aot_cache.py fill --portable``) is read through
    ``aot_cache.py run``, which files the run's GPU programs under the same keys, and AOT_GATE looks
    for the initial state under the probed portable key, not this host's own."""
    _cache_archive(folder / "cache.tgz.aa", "jit_init_point-portable-def-cache")
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1, AOT_GATE=gate)
    assert r.returncode == 75, r.stdout + r.stderr
    assert "the carried cache holds portable keys" in r.stdout
    run = (tmp_path / "stub.log").read_text().splitlines()[-1].split()
    assert run[0].endswith(".py") and run[1:5] == ["run", "-m", "shed_jax", "run"] and "--env" in run
    if gate == "1":
        assert "holds the initial state under this host's key" in r.stdout
    assert not list((tmp_path / "tmp").iterdir())


def test_a_cache_without_portable_keys_runs_as_python_m(tmp_path, folder):
    _cache_archive(folder / "cache.tgz.aa", "jit_init_point-abc-cache")
    repo = _tree(tmp_path, folder)
    shutil.copy(SCRIPT.with_name("aot_cache.py"), repo / "experiments" / "aot_cache.py")
    r = _piece(tmp_path, repo, 1)
    assert r.returncode == 75 and "holds portable keys" not in r.stdout, r.stdout + r.stderr
    assert (tmp_path / "stub.log").read_text().splitlines()[-1].split()[:3] == ["-m", "shed_jax", "run"]


def test_adopt_refuses_to_guess_the_gpu_of_a_folder_with_a_cache_per_model(tmp_path, folder):
    """A piece whose ``gpu`` file did not come back: with caches per GPU model in the folder, its cache
    could be put in the wrong one, so nothing is taken until the model is written."""
    _cache_archive(folder / "gpu-h100" / "cache.tgz.aa", "filled_for_h100")
    repo = _tree(tmp_path, folder)
    assert _piece(tmp_path, repo, 1, RUN_PIECE_GPU="h100").returncode == 75
    out = tmp_path / "out1"
    (out / "gpu").unlink()
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    r = _adopt(folder, out, tmp_path)
    assert r.returncode == 2 and "has no gpu file" in r.stdout, r.stdout
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before
    (out / "gpu").write_text("h100\n")
    r = _adopt(folder, out, tmp_path)
    assert r.returncode == 0 and "ran on h100" in r.stdout, r.stdout
    assert (folder / "gpu-h100" / "cache.tgz.aa").read_bytes() == (out / "cache.tgz.aa").read_bytes()



PIECES = SCRIPT.with_name("run_pieces.sh")
ADOPT_PIECES = SCRIPT.with_name("adopt_pieces.sh")


def _private_mounts() -> bool:
    r = subprocess.run(["unshare", "-m", "--propagation", "private", "true"], capture_output=True)
    return r.returncode == 0


def _pieces_tree(tmp_path, folder):
    repo = _tree(tmp_path, folder)
    shutil.rmtree(repo / "inflight")
    for name in ("a_inflight", "b_inflight"):
        shutil.copytree(folder, repo / "docs" / "results" / name)
    shutil.copy(PIECES, repo / "experiments")
    (tmp_path / "tmp").mkdir()
    out = tmp_path / "out"
    out.mkdir()
    return repo, out


@pytest.mark.skipif(shutil.which("unshare") is None or not _private_mounts(), reason="needs private mounts (root)")
def test_pieces_run_side_by_side_each_seeing_its_own_tree_at_the_trees_path(tmp_path, folder):
    """run_pieces.sh: two carried runs' pieces at once, each on its own copy of the tree (run_piece.sh
    replaces the tree's sources with its run's) seen at the tree's own path (cache keys hold absolute
    paths), with its share of the GPU's memory; each comes back as an archive of its own, which
    adopt_pieces.sh takes into its folder as adopt_piece.sh would."""
    repo, out = _pieces_tree(tmp_path, folder)
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "python").write_text(STUB.replace(
        'echo "$@" >> "$STUB_LOG"',
        'echo "$@" >> "$STUB_LOG"; echo "env $PWD $PYTHONPATH $XLA_PYTHON_CLIENT_MEM_FRACTION $(ls docs/results | tr \'\\n\' +)" >> "$STUB_LOG"'))
    (bin_ / "python").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_}:{os.environ['PATH']}", "STUB_LOG": str(tmp_path / "stub.log"), "PIECE": "1",
           "RUN_PIECE_GPU": "", "TMPDIR": str(tmp_path / "tmp"), "OUT": str(out)}
    r = subprocess.run(["bash", "experiments/run_pieces.sh", "100", "docs/results/a_inflight", "./docs/results/b_inflight/"],
                       cwd=repo, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "== a_inflight: rc 75" in r.stdout and "== b_inflight: rc 75" in r.stdout
    assert sorted(p.name for p in out.iterdir()) == ["a_inflight.tar.aa", "b_inflight.tar.aa"]
    envs = sorted(line.split()[1:] for line in (tmp_path / "stub.log").read_text().splitlines() if line.startswith("env "))
    # both at the tree's path, that path first on the Python path, each seeing only its own folder
    assert envs == [[str(repo), f"{repo}:/tmp/site", "0.45", "a_inflight+"], [str(repo), f"{repo}:/tmp/site", "0.45", "b_inflight+"]]
    assert not any((tmp_path / "tmp").glob("run_pieces.*"))  # the copies are removed
    assert not (repo / "runs").exists() and (repo / "shed_jax" / "stale.txt").is_file()  # the tree itself untouched

    whole = (out / "b_inflight.tar.aa").read_bytes()
    (out / "b_inflight.tar.aa").write_bytes(whole[:700])  # one piece cut short, inside its first member
    before_b = {p.name: p.read_bytes() for p in (repo / "docs/results/b_inflight").iterdir()}
    r = subprocess.run(["bash", str(ADOPT_PIECES), str(out), "docs/results/a_inflight", "docs/results/b_inflight"],
                       cwd=repo, env={**os.environ, "TMPDIR": str(tmp_path / "tmp")}, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stdout + r.stderr
    got = sorted(p.name for p in (repo / "docs/results/a_inflight").iterdir())
    assert got == ["cache.tgz.aa", "ckpt.tgz.aa", "run.args", "src.tgz"], got
    with tarfile.open(repo / "docs/results/a_inflight/ckpt.tgz.aa") as tar:
        assert tar.extractfile("runs/x/state").read() == b"piece 1\n"
    assert "its exit code: 75" in r.stdout and r.stdout.count("its run.log: ") == 1
    assert "b_inflight.tar.* is not a whole archive; docs/results/b_inflight left as it was" in r.stdout
    assert {p.name: p.read_bytes() for p in (repo / "docs/results/b_inflight").iterdir()} == before_b


@pytest.mark.skipif(shutil.which("unshare") is None or not _private_mounts(), reason="needs private mounts (root)")
def test_pieces_whose_files_would_not_fit_a_calls_return_leave_out_caches_first(tmp_path, folder):
    """Two pieces each returning a 300 kB cache against a 450 kB return: the larger cache is left out
    (its folder keeps the one it had), both checkpoints come back, and both folders take their piece."""
    repo, out = _pieces_tree(tmp_path, folder)
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "python").write_text(STUB)
    (bin_ / "python").chmod(0o755)
    (repo / "docs/results/a_inflight/cache.tgz.aa").write_bytes(b"a's own cache")
    (repo / "docs/results/b_inflight/cache.tgz.aa").write_bytes(b"b's own cache")
    env = {**os.environ, "PATH": f"{bin_}:{os.environ['PATH']}", "STUB_LOG": str(tmp_path / "stub.log"), "PIECE": "1",
           "RUN_PIECE_GPU": "", "TMPDIR": str(tmp_path / "tmp"), "OUT": str(out), "STUB_BIG_CACHE": "300000",
           "RETURN_BYTES": "450000"}
    r = subprocess.run(["bash", "experiments/run_pieces.sh", "100", "docs/results/a_inflight", "docs/results/b_inflight"],
                       cwd=repo, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.count("so that the pieces' checkpoints come back") == 1, r.stdout
    assert sum(p.stat().st_size for p in out.iterdir()) <= 450000
    r = subprocess.run(["bash", str(ADOPT_PIECES), str(out), "docs/results/a_inflight", "docs/results/b_inflight"],
                       cwd=repo, env={**os.environ, "TMPDIR": str(tmp_path / "tmp")}, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    kept = [n for n in ("a", "b") if (repo / f"docs/results/{n}_inflight/cache.tgz.aa").read_bytes() == f"{n}'s own cache".encode()]
    assert len(kept) == 1 and "keeps its cache" in r.stdout
    for n in ("a", "b"):
        with tarfile.open(repo / f"docs/results/{n}_inflight/ckpt.tgz.aa") as tar:
            assert tar.extractfile("runs/x/state").read() == b"piece 1\n"


def test_run_pieces_refuses_bad_arguments_and_a_machine_without_private_mounts(tmp_path, folder):
    repo, out = _pieces_tree(tmp_path, folder)
    env = {**os.environ, "OUT": str(out), "TMPDIR": str(tmp_path / "tmp")}

    def run(*args, **extra):
        return subprocess.run(["bash", "experiments/run_pieces.sh", *args], cwd=repo, env={**env, **extra},
                              capture_output=True, text=True, timeout=60)

    a, b = "docs/results/a_inflight", "docs/results/b_inflight"
    r = run("ten", a)
    assert r.returncode == 2 and "SECONDS must be a whole number, got 'ten'" in r.stdout
    r = run("100", "nowhere")
    assert r.returncode == 2 and "nowhere is not a carried run's folder" in r.stdout
    r = run("100", a, a + "/")
    assert r.returncode == 2 and "two folders named a_inflight" in r.stdout
    r = run("100", str(repo / a))
    assert r.returncode == 2 and "must be a path inside the tree" in r.stdout
    r = run("100", a, b, MEM_FRACTION="0.7")
    assert r.returncode == 2 and "MEM_FRACTION=0.7 for 2 pieces does not fit in one GPU" in r.stdout
    r = run("100", a, TMPDIR=str(repo / "tmp"))
    assert r.returncode == 2 and "TMPDIR is inside the tree" in r.stdout
    bin_ = tmp_path / "nomount"
    bin_.mkdir()
    (bin_ / "unshare").write_text("#!/bin/bash\necho 'unshare: unshare failed: Operation not permitted' >&2\nexit 1\n")
    (bin_ / "unshare").chmod(0o755)
    r = run("100", a, b, PATH=f"{bin_}:{os.environ['PATH']}")
    assert r.returncode == 5 and "gives no private mounts (unshare: unshare failed: Operation not permitted" in r.stdout
    assert list(out.iterdir()) == [] and not any((tmp_path / "tmp").glob("run_pieces.*"))


STAGE = SCRIPT.with_name("stage_parts.sh")


def _sums(root: pathlib.Path, parts) -> str:
    return subprocess.run(["sha256sum", *parts], cwd=root, capture_output=True, text=True, check=True).stdout


def test_parts_staged_by_an_earlier_call_go_back_into_the_folder_of_the_next(tmp_path, folder):
    """A folder too large for one call goes in two on one machine: the first carries its cache and its
    checkpoint's first part, which stage_parts.sh copies to .cache/staged/NAME; the second carries the
    rest with the staged parts' sums (slim_tree.sh --staged), and run_piece.sh puts the staged parts
    back once the sums match, then resumes as from a whole folder."""
    repo0 = _tree(tmp_path / "call0", folder)  # a piece that leaves a checkpoint in two parts
    assert _piece(tmp_path / "call0", repo0, 0, STUB_BIG_CACHE="1").returncode == 75
    whole = b"".join(p.read_bytes() for p in sorted((tmp_path / "call0" / "out0").glob("ckpt.tgz.*")))
    assert len(whole) > 100
    (folder / "ckpt.tgz.aa").write_bytes(whole[:100])
    (folder / "ckpt.tgz.ab").write_bytes(whole[100:])
    _cache_archive(folder / "gpu-h100" / "cache.tgz.aa", "filled_for_h100")
    staged_parts = ["ckpt.tgz.aa", "gpu-h100/cache.tgz.aa"]

    first = tmp_path / "call1"  # what --staging carries: the cache and the checkpoint's first part
    carried = tmp_path / "carried1"
    shutil.copytree(folder, carried, ignore=shutil.ignore_patterns("ckpt.tgz.ab"))
    repo1 = _tree(first, carried)
    shutil.copy(STAGE, repo1 / "experiments" / "stage_parts.sh")
    r = subprocess.run(["bash", "experiments/stage_parts.sh", "inflight/"], cwd=repo1, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    staged = repo1 / ".cache" / "staged" / "inflight"
    assert sorted(str(p.relative_to(staged)) for p in staged.rglob("*") if p.is_file()) == staged_parts
    assert all((staged / p).read_bytes() == (folder / p).read_bytes() for p in staged_parts)
    assert "inflight: 2 part(s)" in r.stdout and "staged in .cache/staged/inflight: ckpt.tgz.aa gpu-h100/cache.tgz.aa" in r.stdout

    light = tmp_path / "light"  # what --staged carries: the rest, and the staged parts' sums
    shutil.copytree(folder, light, ignore=shutil.ignore_patterns("ckpt.tgz.aa", "cache.tgz.*"))
    (light / "staged.sha256").write_text(_sums(folder, staged_parts))
    repo2 = _tree(tmp_path / "call2", light)
    r = _piece(tmp_path / "call2", repo2, 1, RUN_PIECE_GPU="h100", STAGED_DIR=str(repo1 / ".cache" / "staged"))
    assert r.returncode == 75, r.stdout + r.stderr
    assert f"2 part(s) staged by an earlier call on this machine put back into inflight ({staged})" in r.stdout
    assert "found piece 0" in (tmp_path / "call2" / "stub.log").read_text().splitlines()  # resumed from the whole checkpoint
    assert "filled_for_h100" in {p.name for p in (repo2 / ".cache" / "device" / "jax").iterdir()}
    # without STAGED_DIR the copies are looked for in the tree's own .cache/staged
    again = _tree(tmp_path / "again", light)
    shutil.copytree(repo1 / ".cache" / "staged", again / ".cache" / "staged")
    assert _piece(tmp_path / "again", again, 1, RUN_PIECE_GPU="h100").returncode == 75

    # a machine without the staged copies (a fresh one), or with others: nothing runs
    for name, other in (("fresh", None), ("other", "began_on_h200")):
        root = tmp_path / name
        repo = _tree(root, light)
        if other:
            shutil.copytree(staged, repo / ".cache" / "staged" / "inflight")
            _cache_archive(repo / ".cache" / "staged" / "inflight" / "gpu-h100" / "cache.tgz.aa", other)
        r = _piece(root, repo, 1, RUN_PIECE_GPU="h100")
        assert r.returncode == 8, r.stdout + r.stderr
        assert ("is not here" if other is None else "does not hold them as listed") in r.stdout
        assert not (root / "stub.log").exists() and list((root / "out1").iterdir()) == []


def test_stage_parts_refuses_a_folder_without_parts_before_staging_any(tmp_path, folder):
    _cache_archive(folder / "cache.tgz.aa", "own")
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "run.args").write_text("--out runs/y\n")
    repo = _tree(tmp_path, folder)
    shutil.copy(STAGE, repo / "experiments" / "stage_parts.sh")
    shutil.copytree(bare, repo / "bare")
    run = lambda *a: subprocess.run(["bash", "experiments/stage_parts.sh", *a], cwd=repo, capture_output=True, text=True, timeout=60)
    r = run("inflight", "bare")
    assert r.returncode == 2 and r.stdout.strip() == "stage_parts: bare holds no archive parts in this call"
    assert not (repo / ".cache").exists()
    r = run("shed_jax")
    assert r.returncode == 2 and "not a carried run's folder" in r.stdout
    r = run("inflight", "./inflight/")
    assert r.returncode == 2 and "two folders named inflight" in r.stdout and not (repo / ".cache").exists()
    r = run("inflight")
    assert r.returncode == 0 and (repo / ".cache" / "staged" / "inflight" / "cache.tgz.aa").is_file()


@pytest.mark.skipif(shutil.which("unshare") is None or not _private_mounts(), reason="needs private mounts (root)")
def test_pieces_read_parts_staged_in_the_trees_own_cache_folder(tmp_path, folder):
    """Each piece's private mount hides the tree's .cache/staged: run_pieces.sh hands the pieces a copy."""
    repo, out = _pieces_tree(tmp_path, folder)
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "python").write_text(STUB)
    (bin_ / "python").chmod(0o755)
    staged = repo / ".cache" / "staged" / "a_inflight"
    _cache_archive(staged / "cache.tgz.aa", "staged_for_a")
    (repo / "docs/results/a_inflight/staged.sha256").write_text(_sums(staged, ["cache.tgz.aa"]))
    env = {**os.environ, "PATH": f"{bin_}:{os.environ['PATH']}", "STUB_LOG": str(tmp_path / "stub.log"), "PIECE": "1",
           "RUN_PIECE_GPU": "", "TMPDIR": str(tmp_path / "tmp"), "OUT": str(out)}
    r = subprocess.run(["bash", "experiments/run_pieces.sh", "100", "docs/results/a_inflight", "docs/results/b_inflight"],
                       cwd=repo, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    with tarfile.open(out / "a_inflight.tar.aa") as tar:
        tar.extractall(tmp_path / "back", filter="data")
    assert "1 part(s) staged by an earlier call on this machine put back" in (tmp_path / "back/a_inflight/piece.out").read_text()
    with tarfile.open(tmp_path / "back/a_inflight/cache.tgz.aa") as tar:  # the staged programs, packed with the piece's
        assert ".cache/device/jax/staged_for_a" in tar.getnames()
    assert not any((tmp_path / "tmp").glob("run_pieces.*"))
