"""experiments/aot_cache.py's cache-key tools, on this host's own (CPU) programs: the key the hook
records is the one JAX files the executable under, and the key's parts name what differs."""
import numpy as np
import pytest

import jax
import jax.numpy as jnp

from experiments import aot_cache


class _Gpu:  # a GPU host's backend as the key sees it (its platform and the CUDA runtime's version)
    platform = "gpu"

    def __init__(self, version):
        self.platform_version = version


@pytest.fixture
def hooked(monkeypatch):
    """``hook_keys`` installed for one test; the key function's arguments captured as well."""
    from jax._src import cache_key as ck
    from jax._src import compilation_cache as cc

    monkeypatch.setattr(cc, "get_cache_key", cc.get_cache_key)  # restored after the test
    calls = []
    real_get = ck.get

    def get(module, devices, options, backend, *rest):
        calls.append((module, devices, options, backend, rest[0]))
        return real_get(module, devices, options, backend, *rest)

    monkeypatch.setattr(ck, "get", get)
    seen: dict = {}
    aot_cache.hook_keys(seen)
    return seen, calls


def test_the_hook_records_each_programs_key_and_parts(hooked):
    seen, calls = hooked
    offset = float(np.random.default_rng().integers(1 << 30))  # a program no earlier test compiled

    def aot_cache_probe_target(x):
        return jnp.sin(x) * 2.0 + offset

    jax.block_until_ready(jax.jit(aot_cache_probe_target)(jnp.ones(3)))
    rec = seen["jit_aot_cache_probe_target"]
    name, digest = rec["key"].split("-")
    assert name == "jit_aot_cache_probe_target" and len(digest) == 64
    assert list(rec["parts"]) == ["computation", "jax_lib version", "backend version", "XLA flags",
                                  "compile_options", "accelerator_config", "compression", "custom_hook",
                                  aot_cache.PROGRAM_FREE_OPTIONS]
    module, devices, options, backend, compression = calls[-1]
    assert aot_cache.key_parts(module, devices, options, backend, compression) == rec["parts"]


def test_another_platform_version_changes_that_part_alone(hooked):
    from jax._src import cache_key as ck

    seen, calls = hooked
    jax.block_until_ready(jax.jit(lambda x: jnp.cos(x) - 3.0)(jnp.ones(4)))
    module, devices, options, backend, compression = calls[-1]
    other = aot_cache._Backend(backend, "PJRT C API\ncuda 13.0.0")
    assert other.platform == backend.platform  # everything else is the backend's own
    mine = aot_cache.key_parts(module, devices, options, backend, compression)
    theirs = aot_cache.key_parts(module, devices, options, other, compression)
    assert [k for k in mine if mine[k] != theirs[k]] == ["backend version"]
    assert ck.get(module, devices, options, other, compression) != ck.get(module, devices, options, backend, compression)
    zlib = aot_cache.key_parts(module, devices, options, backend, "zlib" if compression != "zlib" else "zstandard")
    assert [k for k in mine if mine[k] != zlib[k]] == ["compression"]


def test_a_fill_traces_as_the_gpu_host_and_restores_this_host():
    """The fill lowers on a CPU host the program the GPU host lowers: there ``"auto"`` fused loops are
    Pallas kernels (a fill once compiled the XLA loops instead: another program, filed under keys the
    GPU never asks for)."""
    from envs.physics2d import fused

    assert jax.default_backend() == "cpu" and fused.resolve_mode("auto") == "xla"
    with aot_cache._as_gpu_host(jax.devices()[0]):
        assert jax.default_backend() == "gpu" and fused.resolve_mode("auto") == "pallas"
    assert jax.default_backend() == "cpu" and fused.resolve_mode("auto") == "xla"


def test_a_gpu_program_already_in_the_cache_is_not_compiled_again(hooked, tmp_path, monkeypatch):
    """A fill leaves an entry the cache already holds (the GPU host's own executable, which a CPU host
    cannot load to check) instead of replacing it with its own compile."""
    from jax._src import compilation_cache as cc

    seen, calls = hooked
    jax.block_until_ready(jax.jit(lambda x: jnp.tanh(x) * 5.0)(jnp.ones(6)))
    module, devices, options, backend, _ = calls[-1]

    gpu = _Gpu("PJRT C API\ncuda 13.0.0")  # the key of a GPU host's program, computed here
    aot_cache.hook_keys(seen, present_in=str(tmp_path))
    key = cc.get_cache_key(module, devices, options, gpu)
    name = key.split("-")[0]
    assert "present" not in seen[name]
    (tmp_path / f"{key}-cache").write_bytes(b"an executable")
    with pytest.raises(aot_cache._Captured):
        cc.get_cache_key(module, devices, options, gpu)
    assert seen[name]["present"] and seen[name]["key"] == key


def test_sources_digest_names_the_python_sources_and_nothing_else(tmp_path):
    """A fill trusts a probe's program only when the probe ran the same sources: the digest must move
    with any byte or path of a .py file under the source folders, and with nothing else."""
    for top in aot_cache.SOURCE_DIRS:
        (tmp_path / top / "sub").mkdir(parents=True)
        (tmp_path / top / "sub" / "m.py").write_text(f"X = '{top}'\n")
    d0 = aot_cache.sources_digest(str(tmp_path))
    assert len(d0) == 64 and d0 == aot_cache.sources_digest(str(tmp_path))
    (tmp_path / "envs" / "notes.txt").write_text("not a source")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "x.py").write_text("outside the source folders")
    assert aot_cache.sources_digest(str(tmp_path)) == d0
    (tmp_path / "envs" / "sub" / "m.py").write_text("X = 'envs' \n")
    d1 = aot_cache.sources_digest(str(tmp_path))
    assert d1 != d0
    (tmp_path / "envs" / "sub" / "m.py").rename(tmp_path / "envs" / "sub" / "n.py")
    assert aot_cache.sources_digest(str(tmp_path)) not in (d0, d1)


def test_program_free_options_match_across_programs_of_other_arities(hooked):
    """Two programs with other numbers of inputs and outputs: JAX's compile options differ (per input
    and output fields), the program-free ones do not, so a probe of one program can vouch for the
    host-dependent options of another."""
    seen, _ = hooked
    salt = float(np.random.default_rng().integers(1 << 30))

    def aot_cache_one_in(x):
        return x * salt

    def aot_cache_three_in(x, y, z):
        return x + y * z + salt, x - salt

    jax.block_until_ready(jax.jit(aot_cache_one_in)(jnp.ones(3)))
    jax.block_until_ready(jax.jit(aot_cache_three_in)(jnp.ones(3), jnp.ones(3), jnp.ones(3)))
    a, b = seen["jit_aot_cache_one_in"]["parts"], seen["jit_aot_cache_three_in"]["parts"]
    assert a["compile_options"] != b["compile_options"]
    assert a[aot_cache.PROGRAM_FREE_OPTIONS] == b[aot_cache.PROGRAM_FREE_OPTIONS]
    assert [k for k in a if a[k] != b[k]] == list(aot_cache.PROGRAM_PARTS)


def test_portable_keys_leave_out_the_gpu_hosts_parts(hooked):
    """Two GPU hosts that differ in the CUDA runtime's version get two JAX keys and one portable key;
    the portable key still moves with the program and the device kind, and not with the topology."""
    from jax._src import compilation_cache as cc

    seen, calls = hooked
    jax.block_until_ready(jax.jit(lambda x: jnp.exp(x) * 7.0)(jnp.ones(5)))
    module, devices, options, _, _ = calls[-1]
    said: list = []
    aot_cache.hook_keys(seen, portable=True, say=said.append)
    keys = []
    for version in ("PJRT C API\ncuda 13000", "PJRT C API\ncuda 13010"):
        filed = cc.get_cache_key(module, devices, options, _Gpu(version))
        name = filed.split("-")[0]
        assert filed == seen[name]["portable_key"] and aot_cache.is_portable(filed)
        keys.append((seen[name]["key"], filed, seen[name]["parts"]))
    (jax_a, port_a, parts_a), (jax_b, port_b, parts_b) = keys
    assert jax_a != jax_b and port_a == port_b
    assert len(said) == 1 and said[0].startswith(f"aot_cache: {name} under its portable key {port_a[:56]}")
    assert [k for k in parts_a if parts_a[k] != parts_b[k]] == ["backend version"]
    kinds = [d.device_kind for d in devices.flat]
    assert aot_cache.portable_key(name, parts_a, kinds) == port_a
    assert aot_cache.portable_key(name, dict(parts_a, accelerator_config="0" * 64), kinds) == port_a
    assert aot_cache.portable_key(name, parts_a, ["NVIDIA H100 PCIe"]) != port_a
    assert aot_cache.portable_key(name, dict(parts_a, computation="0" * 64), kinds) != port_a
    assert not aot_cache.is_portable(jax_a)
    # a CPU program (the host's own eager operations, a CPU run) keeps JAX's key
    salt = float(np.random.default_rng().integers(1 << 30))

    def aot_cache_cpu_program(x):
        return jnp.exp(x) * salt

    jax.block_until_ready(jax.jit(aot_cache_cpu_program)(jnp.ones(5)))
    rec = seen["jit_aot_cache_cpu_program"]
    assert "portable_key" not in rec and not aot_cache.is_portable(rec["key"])


def test_a_portable_fill_renames_an_entry_filed_under_the_probed_hosts_key(hooked, tmp_path):
    """``fill --portable`` over a cache filled for one host (JAX's keys) renames its entries to the
    portable keys instead of compiling them again; an entry already portable is left as it is."""
    from jax._src import compilation_cache as cc

    seen, calls = hooked
    jax.block_until_ready(jax.jit(lambda x: jnp.log1p(x) + 11.0)(jnp.ones(7)))
    module, devices, options, _, _ = calls[-1]
    gpu = _Gpu("PJRT C API\ncuda 13000")
    jax_key = cc.get_cache_key(module, devices, options, gpu)  # the plain hook: JAX's key
    (tmp_path / f"{jax_key}-cache").write_bytes(b"an executable")
    (tmp_path / f"{jax_key}-atime").write_bytes(b"1")
    aot_cache.hook_keys(seen, portable=True, present_in=str(tmp_path))
    with pytest.raises(aot_cache._Captured) as c:
        cc.get_cache_key(module, devices, options, gpu)
    rec = seen[c.value.args[0]]
    assert rec["rekeyed"] and rec["present"] and rec["key"] == jax_key
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{rec['portable_key']}-atime", f"{rec['portable_key']}-cache"]
    assert (tmp_path / f"{rec['portable_key']}-cache").read_bytes() == b"an executable"
    with pytest.raises(aot_cache._Captured) as c:  # found under its portable key the next time
        cc.get_cache_key(module, devices, options, gpu)
    assert seen[c.value.args[0]].get("present") and not seen[c.value.args[0]].get("rekeyed")


def test_run_runs_a_module_as_python_m_does(tmp_path):
    """``aot_cache.py run -m MODULE ARGS``: the module from the working folder, as ``__main__``, with
    its arguments, and its exit status."""
    import subprocess
    import sys

    (tmp_path / "some_tool").mkdir()
    (tmp_path / "some_tool" / "__init__.py").write_text("")
    (tmp_path / "some_tool" / "__main__.py").write_text(
        "import sys\nprint('main', __name__, sys.argv[1:])\nsys.exit(3)\n")
    r = subprocess.run([sys.executable, str(aot_cache.__file__), "run", "-m", "some_tool", "a", "--b", "c"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert r.returncode == 3, r.stderr
    assert r.stdout.strip() == "main __main__ ['a', '--b', 'c']"
    r = subprocess.run([sys.executable, str(aot_cache.__file__), "run", "some_tool"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "usage: python aot_cache.py run -m MODULE" in r.stderr


def test_the_final_evaluation_is_lowered_as_a_run_lowers_it_while_training(tmp_path):
    """``final_evals`` rebuilds, from the run's flags and ``build``'s abstract state, the program that
    ``driver.FinalEvalCompile`` lowers from a run's first students and ``seed_keys``: the same text, so
    a fill files it under the key the run looks up."""
    from shed_jax import driver, sharding
    from shed_jax import experiment as xp
    from shed_jax.evaluation import evaluation_program, final_level_sets

    args = tmp_path / "run.args"
    args.write_text(f"--env lander --method dr --preset quick --seeds 2 --final-eval test --compile-final-eval early --out {tmp_path / 'run'}")
    device = jax.devices()[0]
    init, ins, _, _, state = aot_cache.build(str(args), device)
    evals = aot_cache.final_evals(str(args), state)
    assert [name for name, _ in evals] == ["test"]
    ours = evals[0][1]().as_text()

    # the run's way: concrete students of point 0 (rows 0..S-1 of the batch), concrete keys
    opts = aot_cache._options(str(args)).with_output(None)
    exp = xp.experiment_from_args(opts, "cpu")
    parts = xp.build_checked(exp, True)
    batch = driver.make_batch(exp, parts, [({}, {})], num_seeds=2, root_seed=xp.DEFAULT_ROOT_SEED)
    placed = driver.place(batch, sharding.batch_mesh([device]))
    real = init(*placed.inputs)  # as a run places its state: split over the batch mesh
    (levels, _, name), = final_level_sets(opts.final_eval, exp, parts[0], parts[3])
    theirs = evaluation_program(batch.student, levels, opts.final_eval_episodes, exp.loop.test_max_steps).lower(
        batch.rows(real.student, 0), xp.seed_keys(0, 2)).as_text()
    assert name == "test" and ours == theirs

    # compiled after training (a resumed run forgets the flag) the program is the same; no level set, no program
    args.write_text(f"--env lander --method dr --preset quick --seeds 2 --final-eval test --compile-final-eval late --out {tmp_path / 'run'}")
    assert aot_cache.final_evals(str(args), state)[0][1]().as_text() == ours
    args.write_text(f"--env lander --method dr --preset quick --seeds 2 --final-eval none --out {tmp_path / 'run'}")
    assert aot_cache.final_evals(str(args), state) == []


def test_a_stand_in_key_follows_what_the_trace_follows():
    """Static arguments by value, dynamic Python scalars by type (their abstract value), arrays by
    shape, dtype and sharding; a plain function or a static argument that is not a scalar has none."""
    f = jax.jit(lambda x, n, t: x * n + t, static_argnums=1)
    key = lambda *a, context="c": aot_cache.stand_in_key(f, a, context)  # noqa: E731
    base = key(jnp.ones(3), 2, 5)
    assert len(base) == 64
    assert key(jnp.zeros(3), 2, 7) == base  # values of dynamic arguments: the same program
    assert key(jnp.ones(3), 3, 5) != base  # a static value: another program
    assert key(jnp.ones(4), 2, 5) != base and key(jnp.ones(3, jnp.int32), 2, 5) != base
    assert key(jnp.ones(3), 2, 5.0) != base  # a float, not an int: another abstract value
    assert key(jnp.ones(3), 2, 5, context="d") != base
    assert key((jnp.ones(3),), 2, 5) != base  # another tree
    assert key(jnp.ones(3), [2], 5) is None
    assert aot_cache.stand_in_key(lambda x: x, (jnp.ones(3),), "c") is None


def test_a_stand_in_context_leaves_out_output_settings_and_logging(tmp_path, monkeypatch):
    import json

    assert aot_cache.stand_in_context(None) is None and aot_cache.stand_in_context(str(tmp_path)) is None
    cfg = {"experiment": {"env": "bipedal"}, "seeds": 5, "commit": "abc", "output": {"keep": 3}}
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    monkeypatch.chdir(tmp_path)
    base = aot_cache.stand_in_context(str(tmp_path))
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "commit": "def", "output": {"keep": 1}}))
    monkeypatch.setenv("JAX_EXPLAIN_CACHE_MISSES", "1")
    monkeypatch.setenv("JAX_LOGGING_LEVEL", "WARNING")  # run_piece.sh's AOT_GATE=1, to see JAX's cache misses
    monkeypatch.setenv("JAX_DEBUG_LOG_MODULES", "jax._src.compiler")
    assert aot_cache.stand_in_context(str(tmp_path)) == base
    # the allocator's share of the GPU (experiments/run_pieces.sh) builds the same programs
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.45")
    monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    assert aot_cache.stand_in_context(str(tmp_path)) == base
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_autotune_level=0")
    assert aot_cache.stand_in_context(str(tmp_path)) != base
    monkeypatch.delenv("XLA_FLAGS")
    (tmp_path / "config.json").write_text(json.dumps({**cfg, "seeds": 4}))
    assert aot_cache.stand_in_context(str(tmp_path)) != base
    assert aot_cache._run_dir(["--resume", "runs/x", "--keep", "1"]) == "runs/x"
    assert aot_cache._run_dir(["--env", "lander", "--out=runs/y"]) == "runs/y"
    assert aot_cache._run_dir(["--env", "lander"]) is None


_STAND_IN_SCRIPT = """
import json, os, sys
import jax, jax.numpy as jnp
from experiments import aot_cache

jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
aot_cache.hook_keys({})
traces = []

def step(x, n, t):
    traces.append(1)  # runs only while tracing
    for _ in range(n):
        x = jnp.sin(x) * 1.5 + t
    return {"y": x, "s": jnp.sum(x)}

f = jax.jit(step, static_argnums=1)
lines = []
lower = aot_cache.with_stand_ins(lambda j, *a: j.trace(*a).lower(), lambda: sys.argv[2], lambda: "ctx", lines.append)
x = jnp.linspace(0.0, 1.0, 7)
if os.environ.get("STAND_IN_DEVICE"):  # a one-device program on another device of a host with several
    x = jax.device_put(x, jax.devices()[int(os.environ["STAND_IN_DEVICE"])])
out = []
for t in (0.25, 0.5):
    c = lower(f, x, 3, jnp.float32(t)).compile()
    r = c(x, jax.device_put(jnp.float32(t), x.sharding))
    out.append([float(v) for v in r["y"]] + [float(r["s"])])
print(json.dumps({"traces": len(traces), "out": out, "lines": lines}))
"""


@pytest.mark.parametrize("device", [None, "1"])
def test_a_stand_in_gives_the_compiled_program_without_a_trace(tmp_path, device):
    """The first lowering of a program traces it and its compile writes a stand-in; the next (in this
    process and in a new one) reads the executable from JAX's cache entry without tracing, and
    computes the same values, also for a one-device program on the second of two devices. A stand-in
    whose cache entry changed or is gone, or that another jax wrote, is not used: the program is traced."""
    import json
    import pathlib
    import subprocess
    import sys

    root = pathlib.Path(aot_cache.__file__).resolve().parents[1]
    script = tmp_path / "stand_in.py"
    script.write_text(_STAND_IN_SCRIPT)
    cache, store = tmp_path / "jax", tmp_path / "programs"

    env = {**__import__("os").environ, "JAX_PLATFORMS": "cpu"}
    if device:
        env["STAND_IN_DEVICE"] = device
        env["XLA_FLAGS"] = env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"

    def run():
        r = subprocess.run([sys.executable, str(script), str(cache), str(store)], cwd=root, capture_output=True,
                           text=True, timeout=300, env=env)
        assert r.returncode == 0, r.stderr[-2000:]
        return json.loads(r.stdout.strip().splitlines()[-1])

    first = run()
    assert first["traces"] == 1 and len(list(store.iterdir())) == 1, first["lines"]
    assert "stand-in written" in first["lines"][0] and "read from its stand-in" in first["lines"][1]
    second = run()
    assert second["traces"] == 0 and second["out"] == first["out"], second["lines"]
    want = [np.float32(v) for v in np.linspace(0.0, 1.0, 7, dtype=np.float32)]
    y = np.array(want, np.float32)
    for _ in range(3):
        y = np.sin(y) * np.float32(1.5) + np.float32(0.25)
    np.testing.assert_allclose(first["out"][0][:7], y, rtol=1e-6)
    (stand_in,) = store.iterdir()
    import pickle
    entry = pickle.loads(stand_in.read_bytes())
    stand_in.write_bytes(pickle.dumps({**entry, "sha256": "0" * 64}))  # as if the cache entry had changed
    third = run()
    assert third["traces"] == 1 and third["out"] == first["out"]
    assert "holds another executable" in third["lines"][0] and "stand-in written" in third["lines"][1]
    (cache / f"{entry['key']}-cache").unlink()  # the entry gone: traced and compiled again
    fourth = run()
    assert fourth["traces"] == 1 and fourth["out"] == first["out"]
    assert "holds no entry" in fourth["lines"][0] and "stand-in written" in fourth["lines"][1]
    entry = pickle.loads(stand_in.read_bytes())
    stand_in.write_bytes(pickle.dumps({**entry, "jax": "0.0.1"}))
    fifth = run()
    assert fifth["traces"] == 1 and fifth["out"] == first["out"] and "written by jax 0.0.1" in fifth["lines"][0]


def test_a_key_that_cannot_be_had_leaves_the_program_traced(tmp_path):
    """An error while naming the program (an unreadable config, no cache folder) is one line, and the
    program is lowered as without stand-ins."""
    f = jax.jit(lambda x: x + 1.0)
    lines, lowered = [], []

    def lower(jitted, *a):
        lowered.append(1)
        return jitted.trace(*a).lower()

    def broken():
        raise ValueError("config.json is not JSON")

    c = aot_cache.with_stand_ins(lower, lambda: str(tmp_path), broken, lines.append)(f, jnp.ones(2)).compile()
    assert lowered == [1] and float(c(jnp.ones(2))[0]) == 2.0
    assert lines == ["aot_cache: no stand-in (ValueError: config.json is not JSON)"]

    def no_folder():
        raise ValueError("the persistent compilation cache is off")

    aot_cache.with_stand_ins(lower, no_folder, lambda: "ctx", lines.append)(f, jnp.ones(2))
    assert lowered == [1, 1] and lines[-1] == "aot_cache: no stand-in (ValueError: the persistent compilation cache is off)"


def test_a_compile_that_fails_says_so_and_raises(tmp_path):
    """A program whose compile raises writes no stand-in and says why in one line before the error goes
    on to the caller (the final evaluation's worker swallows it, so the run's log would say nothing)."""
    lines = []

    class Lowered:
        def compile(self):
            raise RuntimeError("RESOURCE_EXHAUSTED: out of memory while autotuning\nmore detail")

    lower = aot_cache.with_stand_ins(lambda jitted, *a: Lowered(), lambda: str(tmp_path), lambda: "ctx", lines.append)
    with pytest.raises(RuntimeError, match="RESOURCE_EXHAUSTED"):
        lower(jax.jit(lambda x: x + 1.0), jnp.ones(2)).compile()
    assert len(lines) == 1 and lines[0].endswith(
        "... not compiled, so no stand-in (RuntimeError: RESOURCE_EXHAUSTED: out of memory while autotuning)")
    assert not list(tmp_path.glob("*.pkl"))

    def unlowerable(jitted, *a):
        raise ValueError("a shape the program does not take")

    lower = aot_cache.with_stand_ins(unlowerable, lambda: str(tmp_path), lambda: "ctx", lines.append)
    with pytest.raises(ValueError, match="a shape"):
        lower(jax.jit(lambda x: x + 1.0), jnp.ones(2))
    assert lines[-1].endswith("... not lowered, so no stand-in (ValueError: a shape the program does not take)")


@pytest.mark.parametrize("stand_ins", ["1", "0"])
def test_run_puts_the_stand_ins_in_the_drivers_lowering_as_it_is_imported(tmp_path, stand_ins):
    """``aot_cache.py run -m shed_jax ...`` wraps the run's own ``shed_jax.driver.lower_from_clean_caches``
    and ``shed_jax.evaluation.evaluation_program`` when the package imports them (``AOT_STAND_INS=0``:
    not at all)."""
    import os
    import subprocess
    import sys

    pkg = tmp_path / "shed_jax"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "driver.py").write_text("def lower_from_clean_caches(jitted, *args):\n    return 'traced'\n")
    (pkg / "evaluation.py").write_text(
        "def evaluation_program(student, levels, episodes, max_steps=None, deterministic=False):\n    return 'p'\n")
    (pkg / "__main__.py").write_text(
        "import sys\nfrom shed_jax import driver, evaluation\n"
        "program = evaluation.evaluation_program('student', [1.0, 2.0], 10)\n"
        "print(driver.lower_from_clean_caches.__name__, type(program).__name__, sys.argv[1:])\n")
    r = subprocess.run([sys.executable, str(aot_cache.__file__), "run", "-m", "shed_jax", "run", "--resume", "runs/x"],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120,
                       env={**os.environ, "AOT_STAND_INS": stand_ins})
    assert r.returncode == 0, r.stderr
    names = "lower_or_load _Program" if stand_ins == "1" else "lower_from_clean_caches str"
    assert r.stdout.strip() == f"{names} ['run', '--resume', 'runs/x']"


def test_an_evaluation_programs_stand_in_is_named_by_what_it_closes_over():
    """The final evaluation's program closes over its levels, episodes and step limit: each goes into
    the name its ``lower`` passes on, the student (which the run's config decides) does not; a call
    runs the jitted program itself."""
    made, lowered = [], []

    def evaluation_program(student, levels, episodes, max_steps=None, deterministic=False):
        made.append(student)
        return jax.jit(lambda x: x * episodes)

    wrapped = aot_cache.evaluation_with_stand_ins(
        evaluation_program, lambda jitted, *a, closure: lowered.append(closure) or jitted.lower(*a))
    levels = {"g": jnp.array([1.0, 2.0])}
    p = wrapped("s1", levels, 10)
    assert float(p(jnp.float32(2.0))) == 20.0 and made == ["s1"]
    p.lower(jnp.ones(3)).compile()
    wrapped("s2", {"g": jnp.array([1.0, 2.0])}, 10).lower(jnp.ones(3))
    wrapped("s1", {"g": jnp.array([1.0, 2.5])}, 10).lower(jnp.ones(3))
    wrapped("s1", levels, 10, 2000).lower(jnp.ones(3))
    wrapped("s1", levels, episodes=11).lower(jnp.ones(3))
    assert lowered[0] == lowered[1] and len(set(lowered)) == 4


def test_the_stand_in_check_reads_the_runs_compile_time_and_refuses_a_missing_source(tmp_path, capsys):
    from experiments import stand_in_check

    log = "[shed_jax] compiling a chunk...\naot_cache: ab... read\n[shed_jax] compiled in 6.6 s\nstep 2\n"
    assert stand_in_check._compiled_s(log) == 6.6 and stand_in_check._compiled_s("nothing") is None
    assert stand_in_check._compiled_s(log + "[shed_jax] compiled in 12.25 s (the final evaluation)\n") == 12.25
    assert stand_in_check.main(["--src", str(tmp_path / "none.tgz")]) == 2
    assert "no file" in capsys.readouterr().err


def test_a_target_probe_serves_only_a_portable_fill(tmp_path, capsys):
    """A probe made from a target description (``target-probe``) knows no GPU host's own key parts, so a
    fill that would file programs under them is refused, in one line, before any work."""
    import json

    probe = tmp_path / "probe.json"
    probe.write_text(json.dumps({"jax": jax.__version__, "target_probe": {"target": "experiments/targets/h200.txtpb"},
                                 "programs": {}}))
    assert aot_cache.main(["fill", str(tmp_path / "run.args"), str(probe)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("aot_cache fill: ") and "--portable" in err and "\n" not in err


def test_a_target_probe_needs_this_hosts_jax_and_a_readable_target(tmp_path, capsys):
    import json

    probe = tmp_path / "probe.json"
    probe.write_text(json.dumps({"jax": "0.0.1", "programs": {}}))
    assert aot_cache.main(["target-probe", str(probe), "experiments/targets/h200.txtpb", str(tmp_path / "o.json")]) == 2
    assert capsys.readouterr().err.strip() == (f"aot_cache target-probe: {probe} is of jax 0.0.1, this host has "
                                               f"{jax.__version__}")
    probe.write_text(json.dumps({"jax": jax.__version__, "programs": {}}))
    missing = tmp_path / "none.txtpb"
    assert aot_cache.main(["target-probe", str(probe), str(missing), str(tmp_path / "o.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"aot_cache target-probe: cannot read {missing}: ") and not (tmp_path / "o.json").exists()
