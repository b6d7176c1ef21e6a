"""experiments/slim_tree.sh: a device call's tree slimmed to one carried run's folder and restored,
in a throwaway git repository."""
import hashlib
import pathlib
import shutil
import subprocess
import zipfile

SCRIPT = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "slim_tree.sh"


def _git(repo, *args):
    return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, check=True).stdout


def _repo(tmp_path):
    repo = tmp_path / "repo"
    for rel, text in {"docs/guide.md": "guide", "docs/img/a.png": "png", "docs/results/run_inflight/ckpt.tgz.aa": "ckpt",
                      "docs/results/other_inflight/cache.tgz.aa": "x" * 5000, "docs/results/r.json": "{}",
                      "experiments/slim_tree.sh": SCRIPT.read_text(),
                      "experiments/carried_size.sh": SCRIPT.with_name("carried_size.sh").read_text(), "README.md": "readme",
                      "tests/test_x.py": "def test_x(): pass\n"}.items():
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text(text)
    (repo / ".gitignore").write_text(".whl/\n")
    _git(repo, "init", "-q")
    _git(repo, "add", "-A")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "init")
    (repo / ".whl").mkdir()
    for w in ("mujoco_core-4.0.0-cp312.whl", "orjson-3.13.0.whl", "brax-0.14.2-py3-none-any.whl", "trimesh-5.2.0-py3-none-any.whl",
              "jaxopt-0.8.5-py3-none-any.whl", "ml_collections-1.1.0-py3-none-any.whl", "tensorboardx-2.6.5-py3-none-any.whl"):
        (repo / ".whl" / w).write_text(w)
    with zipfile.ZipFile(repo / ".whl" / MJX, "w") as z:  # MJX's wheel in small: its package, test data, RECORD
        z.writestr("mujoco/mjx/__init__.py", "from mujoco.mjx._src import x\n")
        z.writestr("mujoco/mjx/_src/x.py", "x = 1\n")
        z.writestr("mujoco/mjx/test_data/humanoid.xml", "<mujoco>" + "m" * 4000 + "</mujoco>")
        z.writestr("mujoco_mjx-3.17.0.dist-info/RECORD", "mujoco/mjx/__init__.py,sha256=a,31\nmujoco/mjx/_src/x.py,sha256=b,6\n"
                   "mujoco/mjx/test_data/humanoid.xml,sha256=c,4017\nmujoco_mjx-3.17.0.dist-info/RECORD,,\n")
    return repo


MJX = "mujoco_mjx-3.17.0-py3-none-any.whl"


def _run(repo, *args):
    return subprocess.run(["bash", "experiments/slim_tree.sh", *args], cwd=repo, capture_output=True, text=True, timeout=60)


def _files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and ".git/" not in str(p.relative_to(root)) + "/")


def test_slim_keeps_one_folder_and_restore_gives_the_tree_back(tmp_path):
    repo = _repo(tmp_path)
    before = _files(repo)
    mjx = (repo / ".whl" / MJX).read_bytes()
    commit = _git(repo, "describe", "--always", "--dirty").strip()  # the tree's, before the slim moves files
    r = _run(repo, "--bipedal-wheels", "docs/results/run_inflight/")
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(str(p.relative_to(repo)) for p in (repo / "docs").rglob("*") if p.is_file()) == ["docs/results/run_inflight/ckpt.tgz.aa"]
    assert not (repo / "tests").exists()
    # the wheels a 2-D walker run needs: those `python -m shed_jax` checks for, and orjson
    assert sorted(p.name for p in (repo / ".whl").iterdir()) == ["brax-0.14.2-py3-none-any.whl", MJX, "orjson-3.13.0.whl"]
    # MJX's wheel is carried without its test data, which its RECORD no longer lists
    with zipfile.ZipFile(repo / ".whl" / MJX) as z:
        assert sorted(z.namelist()) == ["mujoco/mjx/__init__.py", "mujoco/mjx/_src/x.py", "mujoco_mjx-3.17.0.dist-info/RECORD"]
        assert z.read("mujoco/mjx/_src/x.py") == b"x = 1\n"
        assert z.read("mujoco_mjx-3.17.0.dist-info/RECORD").decode().splitlines() == [
            "mujoco/mjx/__init__.py,sha256=a,31", "mujoco/mjx/_src/x.py,sha256=b,6", "mujoco_mjx-3.17.0.dist-info/RECORD,,"]
    assert (repo / ".whl" / MJX).stat().st_size < len(mjx) - 3000
    # what the call carries: README, .gitignore, the scripts, the folder and the wheels left
    # and the tree's commit for the call's records (the device's copy of .git may be older)
    assert (repo / ".source_commit").read_text().strip() == commit and not commit.endswith("-dirty")
    carried = sum(p.stat().st_size for p in (repo / "README.md", repo / ".gitignore", repo / "experiments/slim_tree.sh",
                                             repo / "experiments/carried_size.sh", repo / ".source_commit",
                                             repo / "docs/results/run_inflight/ckpt.tgz.aa", *(repo / ".whl").iterdir()))
    assert f"carries {carried} bytes" in r.stdout
    assert ".aside" not in _git(repo, "status", "--porcelain", "--untracked-files=all")  # ignored, so not carried
    assert _run(repo, "docs/results/run_inflight").returncode == 2  # twice: restore first
    r = _run(repo, "--restore")
    assert r.returncode == 0, r.stdout + r.stderr
    assert _files(repo) == before and not (repo / ".aside").exists()
    assert (repo / ".whl" / MJX).read_bytes() == mjx  # the original wheel, over the copy
    assert _git(repo, "status", "--porcelain") == ""


def test_refuses_uncommitted_docs_and_a_folder_outside_results(tmp_path):
    repo = _repo(tmp_path)
    (repo / "docs" / "guide.md").write_text("edited")
    r = _run(repo, "docs/results/run_inflight")
    assert r.returncode == 2 and "uncommitted changes outside docs/results/run_inflight" in r.stdout
    assert (repo / "docs" / "results" / "other_inflight").is_dir()  # nothing moved
    (repo / "docs" / "guide.md").write_text("guide")
    # changes inside the folder itself are the point (a piece's parts, adopted)
    (repo / "docs" / "results" / "run_inflight" / "ckpt.tgz.aa").write_text("new ckpt")
    assert _run(repo, "docs/results/run_inflight").returncode == 0
    assert _run(repo, "--restore").returncode == 0
    r = _run(repo, "docs/guide.md")
    assert r.returncode == 2 and "must be a folder under docs/results/" in r.stdout
    shutil.rmtree(repo / "docs" / "results" / "other_inflight")
    assert _run(repo, "docs/results/missing").returncode == 2


def test_gpu_model_sets_the_folders_other_caches_aside_and_restore_puts_them_back(tmp_path):
    repo = _repo(tmp_path)
    run = repo / "docs" / "results" / "run_inflight"
    for rel in ("cache.tgz.aa", "gpu-h100/cache.tgz.aa", "gpu-h100/aot_report.json", "gpu-h200/cache.tgz.aa"):
        (run / rel).parent.mkdir(parents=True, exist_ok=True)
        (run / rel).write_text(rel)
    _git(repo, "add", "-A")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "caches")
    before = _files(repo)
    r = _run(repo, "--gpu", "h100", "docs/results/run_inflight")
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(str(p.relative_to(run)) for p in run.rglob("*") if p.is_file()) == [
        "ckpt.tgz.aa", "gpu-h100/aot_report.json", "gpu-h100/cache.tgz.aa"]
    (run / "gpu-h100" / "cache.tgz.aa").write_text("the piece's new cache")  # adopted
    r = _run(repo, "--restore")
    assert r.returncode == 0 and "exists in the tree too" not in r.stdout, r.stdout + r.stderr
    assert _files(repo) == before and (run / "gpu-h100" / "cache.tgz.aa").read_text() == "the piece's new cache"
    # committed after the restore, the piece changes only what it replaced (no cache recorded as deleted)
    assert _git(repo, "status", "--porcelain", "--", "docs").split() == ["M", "docs/results/run_inflight/gpu-h100/cache.tgz.aa"]
    assert _run(repo, "--gpu", "v100", "docs/results/run_inflight").returncode == 2


def test_restore_keeps_a_split_archive_whole(tmp_path):
    """A piece that ran on another GPU than the one named writes its one-part cache into the folder
    itself, where the set-aside cache had two parts: restore must not put the old second part beside
    the new first one (a corrupt mix), and leaves the old set aside, saying so."""
    repo = _repo(tmp_path)
    run = repo / "docs" / "results" / "run_inflight"
    for rel in ("cache.tgz.aa", "cache.tgz.ab", "gpu-h100/cache.tgz.aa"):
        (run / rel).parent.mkdir(parents=True, exist_ok=True)
        (run / rel).write_text("old " + rel)
    _git(repo, "add", "-A")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "caches")
    assert _run(repo, "--gpu", "h100", "docs/results/run_inflight").returncode == 0
    assert not (run / "cache.tgz.aa").exists() and not (run / "cache.tgz.ab").exists()
    (run / "cache.tgz.aa").write_text("new one-part cache")  # adopted from a piece on an H200
    r = _run(repo, "--restore")
    assert r.returncode == 1 and "holds other parts of cache.tgz." in r.stdout, r.stdout + r.stderr
    assert sorted(p.name for p in run.glob("cache.tgz.*")) == ["cache.tgz.aa"]
    assert (run / "cache.tgz.aa").read_text() == "new one-part cache"
    assert sorted(p.name for p in (repo / ".aside" / "docs" / "results" / "run_inflight").iterdir()) == ["cache.tgz.aa", "cache.tgz.ab"]
    assert (repo / "docs" / "guide.md").read_text() == "guide"  # the rest came back


def test_several_folders_stay_for_pieces_run_together(tmp_path):
    """experiments/run_pieces.sh carries two runs' folders: both stay, with their own GPU model's cache."""
    repo = _repo(tmp_path)
    for rel in ("docs/results/run_inflight/gpu-h100/cache.tgz.aa", "docs/results/run_inflight/cache.tgz.aa",
                "docs/results/other_inflight/gpu-h100/cache.tgz.aa"):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text(rel)
    _git(repo, "add", "-A")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "caches")
    before = _files(repo)
    r = _run(repo, "--gpu", "h100", "docs/results/run_inflight", "docs/results/other_inflight/")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "docs/ holds only docs/results/run_inflight docs/results/other_inflight;" in r.stdout
    assert sorted(str(p.relative_to(repo)) for p in (repo / "docs").rglob("*") if p.is_file()) == [
        "docs/results/other_inflight/gpu-h100/cache.tgz.aa",  # its H200 cache (cache.tgz.aa) aside
        "docs/results/run_inflight/ckpt.tgz.aa", "docs/results/run_inflight/gpu-h100/cache.tgz.aa"]
    assert _run(repo, "--gpu", "h100", "docs/results/nowhere").returncode == 2
    r = _run(repo, "--restore")
    assert r.returncode == 0, r.stdout + r.stderr
    assert _files(repo) == before and _git(repo, "status", "--porcelain") == ""


def test_the_two_calls_of_a_staged_piece_each_carry_part_of_the_folder(tmp_path):
    """--staging (call 1) carries the cache for the named GPU model and the checkpoint's first part,
    --staged (call 2) the rest, with the sums of the parts it left out, by which run_piece.sh checks
    the staged copies; restore gives it all back, the sums removed."""
    repo = _repo(tmp_path)
    run = repo / "docs" / "results" / "run_inflight"
    for rel in ("ckpt.tgz.ab", "ckpt.tgz.ac", "cache.tgz.aa", "gpu-h100/cache.tgz.aa", "gpu-h100/cache.tgz.ab",
                "gpu-h100/aot_report.json", "src.tgz", "run.args"):
        (run / rel).parent.mkdir(parents=True, exist_ok=True)
        (run / rel).write_text("old " + rel)
    _git(repo, "add", "-A")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "parts")
    before = _files(repo)
    here = lambda: sorted(str(p.relative_to(run)) for p in run.rglob("*") if p.is_file())
    r = _run(repo, "--gpu", "h100", "--staging", "docs/results/run_inflight")
    assert r.returncode == 0, r.stdout + r.stderr
    assert here() == ["ckpt.tgz.aa", "gpu-h100/aot_report.json", "gpu-h100/cache.tgz.aa", "gpu-h100/cache.tgz.ab",
                      "run.args", "src.tgz"]
    assert _run(repo, "--restore").returncode == 0 and _files(repo) == before

    r = _run(repo, "--gpu", "h100", "--staged", "docs/results/run_inflight")
    assert r.returncode == 0, r.stdout + r.stderr
    assert here() == ["ckpt.tgz.ab", "ckpt.tgz.ac", "gpu-h100/aot_report.json", "run.args", "src.tgz", "staged.sha256"]
    sums = dict(reversed(line.split()) for line in (run / "staged.sha256").read_text().splitlines())
    assert sums == {p: hashlib.sha256(f"old {p}".encode() if p != "ckpt.tgz.aa" else b"ckpt").hexdigest()
                    for p in ("gpu-h100/cache.tgz.aa", "gpu-h100/cache.tgz.ab", "ckpt.tgz.aa")}
    r = _run(repo, "--restore")
    assert r.returncode == 0, r.stdout + r.stderr
    assert _files(repo) == before and _git(repo, "status", "--porcelain") == ""  # the sums are gone too

    # restored after call 1 (nothing adopted): no "left in .aside" line, the copy of ckpt.tgz.aa dropped
    assert _run(repo, "--gpu", "h100", "--staging", "docs/results/run_inflight").returncode == 0
    r = _run(repo, "--restore")
    assert r.returncode == 0 and "aside" not in r.stdout.replace("nothing is aside", ""), r.stdout
    assert _files(repo) == before

    # adopted before the restore: the piece's parts (a shorter set) win, never mixed with the old ones
    assert _run(repo, "--gpu", "h100", "--staged", "docs/results/run_inflight").returncode == 0
    for p in run.glob("ckpt.tgz.*"):
        p.unlink()
    (run / "ckpt.tgz.aa").write_text("new ckpt.tgz.aa")
    (run / "gpu-h100" / "cache.tgz.aa").write_text("new cache")
    r = _run(repo, "--restore")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ckpt.tgz.* in the tree replace the set-aside ones" in r.stdout
    assert sorted(p.name for p in run.glob("ckpt.tgz.*")) == ["ckpt.tgz.aa"] and (run / "ckpt.tgz.aa").read_text() == "new ckpt.tgz.aa"
    assert sorted(p.name for p in (run / "gpu-h100").glob("cache.tgz.*")) == ["cache.tgz.aa"]
    assert not (repo / ".aside").exists() and not (run / "staged.sha256").exists()
    assert (repo / "docs" / "guide.md").read_text() == "guide" and (repo / "tests").is_dir()
    _git(repo, "checkout", "--", "docs")
    assert _files(repo) == before

    # without a cache of the named model, the folder's own is the one staged (gpu-h100/ aside, as ever)
    assert _run(repo, "--gpu", "h200", "--staged", "docs/results/run_inflight").returncode == 0
    assert here() == ["ckpt.tgz.ab", "ckpt.tgz.ac", "run.args", "src.tgz", "staged.sha256"]
    assert sorted(l.split()[1] for l in (run / "staged.sha256").read_text().splitlines()) == ["cache.tgz.aa", "ckpt.tgz.aa"]
    assert _run(repo, "--restore").returncode == 0 and _files(repo) == before


def test_staged_pieces_refuse_what_cannot_be_split(tmp_path):
    repo = _repo(tmp_path)
    before = _files(repo)
    r = _run(repo, "--staged", "docs/results/run_inflight")
    assert r.returncode == 2 and "--staged needs --gpu MODEL" in r.stdout
    r = _run(repo, "--gpu", "h100", "--staging", "--staged", "docs/results/run_inflight")
    assert r.returncode == 2 and "the two calls of one piece: give one" in r.stdout
    for flag, folder in (("--staged", "run_inflight"), ("--staging", "other_inflight")):  # no cache; no checkpoint
        r = _run(repo, "--gpu", "h100", flag, f"docs/results/{folder}")
        assert r.returncode == 2 and "needs a checkpoint and a cache for h100 to split between two calls" in r.stdout
        assert _files(repo) == before and not (repo / ".aside").exists()


def test_a_one_part_checkpoint_is_staged_and_restored_whole(tmp_path):
    repo = _repo(tmp_path)
    run = repo / "docs" / "results" / "run_inflight"
    (run / "cache.tgz.aa").write_text("cache")
    (run / "gpu-h100").mkdir()  # a model's folder without cache parts: the folder's own cache is the one
    (run / "gpu-h100" / "aot_report.json").write_text("{}")
    (run / "pieces").mkdir()
    (run / "pieces" / "staged.sha256").write_text("left by a broken session")
    _git(repo, "add", "-A")
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "parts")
    (run / "pieces" / "staged.sha256").unlink()
    _git(repo, "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qam", "gone")
    before = _files(repo)
    for flag, kept in (("--staging", ["cache.tgz.aa", "ckpt.tgz.aa"]), ("--staged", ["staged.sha256"])):
        r = _run(repo, "--gpu", "h100", flag, "docs/results/run_inflight")
        assert r.returncode == 0, r.stdout + r.stderr
        assert sorted(p.name for p in run.iterdir() if p.is_file()) == kept
        (run / "pieces" / "staged.sha256").write_text("a stray one, in a nested folder")
        r = _run(repo, "--restore")
        assert r.returncode == 0 and "left in" not in r.stdout, r.stdout
        assert _files(repo) == before, flag
