"""experiments/aot_cache.py's cache-key tools, on this host's own (CPU) programs: the key the hook
records is the one JAX files the executable under, and the key's parts name what differs."""
import numpy as np
import pytest

import jax
import jax.numpy as jnp

from experiments import aot_cache


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

    class Gpu:  # the key of a GPU host's program, computed here
        platform, platform_version = "gpu", "PJRT C API\ncuda 13.0.0"

    aot_cache.hook_keys(seen, present_in=str(tmp_path))
    key = cc.get_cache_key(module, devices, options, Gpu())
    name = key.split("-")[0]
    assert "present" not in seen[name]
    (tmp_path / f"{key}-cache").write_bytes(b"an executable")
    with pytest.raises(aot_cache._Captured):
        cc.get_cache_key(module, devices, options, Gpu())
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
