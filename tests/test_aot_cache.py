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
