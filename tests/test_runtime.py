"""shed_jax/runtime.py (the CLI's start-up: compilation cache, backend line, GPU-unused warning) and the
walker's quiet MJX import."""
import os
import pathlib
import subprocess
import sys
from types import SimpleNamespace

from shed_jax import _backend_select as select
from shed_jax import runtime

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _python(code, **env):
    base = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT", "SHED_JAX"))}
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, env={**base, "PYTHONPATH": str(ROOT), **env},
                          capture_output=True, text=True, timeout=300)


def test_describe_devices_groups_by_kind():
    gpus = [SimpleNamespace(platform="gpu", device_kind="NVIDIA H200") for _ in range(2)]
    assert runtime.describe_devices(gpus) == "2 x NVIDIA H200"
    assert runtime.describe_devices([SimpleNamespace(platform="cpu", device_kind="cpu")]) == "1 x cpu"
    mixed = [SimpleNamespace(platform="gpu", device_kind=k) for k in ("A", "B", "A")]
    assert runtime.describe_devices(mixed) == "2 x A, 1 x B"


def test_gpu_unused_warning(monkeypatch):
    def probe(cuda):
        return lambda: (cuda, "570.124.06", "nvidia-smi: driver 570.124.06, CUDA " + ".".join(map(str, cuda or ())))

    monkeypatch.setattr(select, "installed_plugins", lambda: set())
    assert runtime.gpu_unused_warning("cpu", "", probe((12, 8))) == (
        "[shed_jax] warning: nvidia-smi: driver 570.124.06, CUDA 12.8, but JAX has no CUDA build and runs on "
        "the CPU; install it with: make setup JAX_BACKEND=cuda12")
    assert runtime.gpu_unused_warning("cpu", "cuda,cpu", probe((13, 0))).endswith("make setup JAX_BACKEND=cuda13")
    assert runtime.gpu_unused_warning("gpu", "", probe((12, 8))) is None  # JAX found the GPU
    assert runtime.gpu_unused_warning("cpu", "cpu", probe((12, 8))) is None  # the user asked for the CPU
    assert runtime.gpu_unused_warning("cpu", "", probe(None)) is None  # no GPU
    assert runtime.gpu_unused_warning("cpu", "", probe((11, 4))) is None  # too old for any CUDA build

    monkeypatch.setattr(select, "installed_plugins", lambda: {"jax-cuda12-plugin", "jax-cuda12-pjrt"})
    assert "JAX's cuda12 plugin did not start" in runtime.gpu_unused_warning("cpu", "", probe((12, 8)))


def test_start_up_caches_even_short_cpu_compiles(tmp_path):
    """A fresh process: the backend line names the cache folder, and a tiny jit (far under JAX's 1 s default
    floor) is written there."""
    code = ("from shed_jax.runtime import start_up; start_up()\n"
            "import jax, jax.numpy as jnp\n"
            "print(float(jax.jit(lambda x: (x * 2 + 1).sum())(jnp.arange(3.0))))\n")
    proc = _python(code, SHED_JAX_CACHE=str(tmp_path), JAX_PLATFORMS="cpu")
    assert proc.returncode == 0, proc.stderr
    line, value = proc.stdout.splitlines()
    assert line.startswith("[shed_jax] jax ") and ", backend cpu: 1 x cpu;" in line
    assert line.endswith(f"; compilation cache {tmp_path / 'jax'}")
    assert value == "9.0"
    assert "warning" not in proc.stderr  # JAX_PLATFORMS=cpu: no GPU hint
    assert [p for p in (tmp_path / "jax").iterdir() if p.name.startswith("jit_")]  # the entry of the jit

    off = _python(code, SHED_JAX_CACHE=str(tmp_path / "off"), JAX_PLATFORMS="cpu", JAX_ENABLE_COMPILATION_CACHE="false")
    assert off.stdout.splitlines()[0].endswith("; compilation cache off") and not (tmp_path / "off").exists()


def test_walker_import_drops_only_the_warp_missing_lines():
    from envs.walker import mjx_import

    # the MJX engine loads with the env class (the level modules need only JAX)
    proc = _python("import sys, envs.walker; assert 'mujoco' not in sys.modules; "
                   "from envs.walker import BipedalWalker; assert 'mujoco.mjx' in sys.modules; print('ok')", JAX_PLATFORMS="cpu")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "ok\n" and "warp" not in proc.stderr.lower()
    drop = mjx_import._WARP_MISSING.fullmatch
    assert drop("Failed to import warp: No module named 'warp'")
    assert drop("Failed to import mujoco_warp: No module named 'warp'")
    assert not drop("Failed to import warp: CUDA driver version is insufficient")  # a broken Warp still shows


def test_provenance_names_device_command_and_date():
    import re

    import jax

    from shed_jax.runtime import provenance

    p = provenance("experiments.x", ["--a", "1"])
    assert p["command"] == "python -m experiments.x --a 1"
    assert p["device"].startswith(f"{jax.default_backend()}: ") and " x " in p["device"]
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", p["date"])
    assert p["commit"] == runtime.source_commit()  # this checkout's commit (None in a copied tree)


def test_source_commit_names_the_checkouts_commit_and_marks_edits(tmp_path, monkeypatch):
    from shed_jax import rundir

    def git(*args):
        return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path,
                              capture_output=True, text=True, check=True).stdout.strip()

    assert runtime.source_commit(tmp_path) is None  # no .git of its own (a repository above does not count)
    git("init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("commit", "-q", "-m", "one")
    sha = git("rev-parse", "HEAD")
    first = runtime.source_commit(tmp_path)
    assert first and sha.startswith(first)
    (tmp_path / "a.py").write_text("x = 2\n")
    assert runtime.source_commit(tmp_path) == first + "-dirty"
    # a device call's copy: the commit slim_tree.sh wrote wins over the copy's (older) git metadata
    (tmp_path / runtime.SOURCE_COMMIT_FILE).write_text("abc1234-dirty\n")
    assert runtime.source_commit(tmp_path) == "abc1234-dirty"
    (tmp_path / runtime.SOURCE_COMMIT_FILE).unlink()
    # a resumed run names the commit it started at when the code has moved on, and nothing otherwise
    monkeypatch.setattr(rundir, "source_commit", lambda: first + "-dirty")
    assert rundir.commit_note({"commit": first}) == f"this run started at commit {first} and continues at {first}-dirty"
    assert rundir.commit_note({"commit": first + "-dirty"}) is None
    assert rundir.commit_note({}) is None  # a run saved before runs recorded their commit


def test_required_modules_name_every_pyproject_dependency():
    import re
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert list(runtime.REQUIRED_MODULES) == [re.split(r"[<>=!~\[; ]", d, maxsplit=1)[0].lower() for d in deps]


def test_missing_packages_finds_modules_without_importing_them():
    modules = {"absent": "shed_jax_no_such_module", "numpy": "numpy", "package-dir": "numpy.linalg",
               "module-file": "json.decoder", "absent-sub": "json.no_such", "absent-deep": "numpy.linalg.no_such",
               "file-is-no-package": "json.decoder.no_such"}
    assert runtime.missing_packages(modules) == ["absent", "absent-sub", "absent-deep", "file-is-no-package"]
    assert runtime.missing_packages({"numpy": "shed_jax_no_such_module"}) == []  # its metadata is installed
    assert runtime.missing_packages() == []  # this environment has every dependency
    out = _python("import sys; from shed_jax import runtime; assert runtime.missing_packages() == []; "
                  "print([m for m in ('mujoco', 'orbax', 'orjson', 'brax', 'flax') if m in sys.modules])")
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr


def test_missing_packages_finds_a_package_split_across_path_entries(tmp_path, monkeypatch):
    first, second = tmp_path / "a" / "splitpkg", tmp_path / "b" / "splitpkg"
    first.mkdir(parents=True)
    (second / "inner").mkdir(parents=True)
    (first / "__init__.py").write_text("__path__ = __import__('pkgutil').extend_path(__path__, __name__)\n")
    (second / "part.py").write_text("")
    (second / "inner" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path / "b"))
    monkeypatch.syspath_prepend(str(tmp_path / "a"))
    modules = {"x-part": "splitpkg.part", "x-inner": "splitpkg.inner", "x-none": "splitpkg.none"}
    assert runtime.missing_packages(modules) == ["x-none"]
    assert "splitpkg" not in sys.modules  # looked up, not imported


def test_a_missing_dependency_stops_the_cli_in_one_line_before_any_work(monkeypatch, capsys, tmp_path):
    from shed_jax.__main__ import main

    monkeypatch.setitem(runtime.REQUIRED_MODULES, "orjson-gone", "shed_jax_no_such_module")
    assert main(["run", "--env", "lander", "--method", "dr", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing package(s): orjson-gone;" in err and "make setup" in err
    assert not (tmp_path / "run").exists()
    # --help still helps, after the same line
    assert main(["run", "--help"]) == 0
    out, err = capsys.readouterr()
    assert "missing package(s): orjson-gone;" in err and "--resume DIR" in out
    assert main(["--help"]) == 0 and "COMMAND" in capsys.readouterr().out


def test_without_jax_a_command_help_is_the_missing_line_not_a_traceback():
    # a fresh machine before `make setup`: the commands' argument lists import the environments (JAX)
    code = ("import sys; sys.modules['jax'] = None\n"  # `import jax` now fails as if it were absent
            "from shed_jax import runtime; runtime.REQUIRED_MODULES['jax-gone'] = 'shed_jax_no_such_module'\n"
            "from shed_jax.__main__ import main\n"
            "sys.exit(main(sys.argv[1:]))")
    for argv, rc in ((["run", "--help"], 2), (["--help"], 0)):
        out = subprocess.run([sys.executable, "-c", code, *argv], cwd=ROOT, capture_output=True, text=True,
                             timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert out.returncode == rc, out.stderr
        assert "Traceback" not in out.stderr and "missing package(s): jax-gone;" in out.stderr
    assert "demo" in out.stdout and " run " not in out.stdout  # the top-level help lists what can run


def test_cache_lookups_report_a_miss_then_a_hit_and_leak_no_debug_lines(tmp_path):
    """``runtime.cache_lookups``: a program compiled into an empty persistent cache is a miss, the same
    program after the in-memory caches are cleared a hit under the same key, also with a nested block
    whose callback raises (the compile goes on); JAX's debug lines reach no handler, and the logger's
    level is put back when the outer block ends."""
    code = """
import logging, jax, jax.numpy as jnp
from shed_jax import runtime
leaked = []
class Catch(logging.Handler):
    def emit(self, record):
        if record.name == "jax._src.compiler":
            leaked.append(record.levelname)
logging.getLogger().addHandler(Catch())
def chunk(x):
    return jnp.sin(x) * 3.0
x = jnp.ones(3)
seen = []
def broken(*a):
    raise BrokenPipeError("a report that fails")
with runtime.cache_lookups(lambda *a: seen.append(a)):
    jax.jit(chunk)(x).block_until_ready()
    jax.clear_caches()
    with runtime.cache_lookups(broken):
        jax.jit(chunk)(x).block_until_ready()
    assert logging.getLogger("jax._src.compiler").level == logging.DEBUG  # the outer block still runs
print([(p, hit, key.startswith("jit_chunk-")) for p, hit, key in seen if p == "jit_chunk"])
print(len({key for p, _, key in seen if p == "jit_chunk"}), leaked, logging.getLogger("jax._src.compiler").level)
"""
    r = _python(code, JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(tmp_path),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="-1")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[-2] == "[('jit_chunk', False, True), ('jit_chunk', True, True)]"
    assert lines[-1] == "1 [] 0"


def test_cache_report_says_each_miss_and_names_each_program_read_once():
    """``driver.cache_report``: a miss of one of the run's programs is said at once; a program read
    twice (two chunk lengths) is named once and never reported as a miss; other programs are ignored."""
    from shed_jax import driver

    said = []
    looked_up, cached = driver.cache_report(said.append)
    looked_up("jit_chunk", True, "jit_chunk-aa")
    looked_up("jit_chunk", True, "jit_chunk-bb")
    looked_up("jit_stack", False, "jit_stack-cc")
    looked_up("jit_init_point", False, "jit_init_point-dd")
    assert cached == ["jit_chunk"]
    assert said == ["[shed_jax] jit_init_point is not in the compilation cache (key jit_init_point-dd...): compiling it"]
