"""Start-up: the package imports lazily (no JAX for `sqjax --help`), every public name still resolves,
and the command line keeps compiled kernels in the persistent cache (opt-out by flag or environment)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import sqjax

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, env=None, timeout=120):
    e = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}", **(env or {})}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e, timeout=timeout)


def test_help_does_not_import_jax():
    r = _python("import sys\nfrom sqjax.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
                "for c in ('segment', 'demo', 'fit'):\n    main([c, '--help'])\n"
                "print('JAX' if 'jax' in sys.modules else 'NOJAX')")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().endswith("NOJAX"), r.stdout[-300:]


def test_help_is_fast():
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "sqjax", "--help"], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60)
    wall = time.perf_counter() - t
    assert r.returncode == 0 and "demo" in r.stdout
    assert wall < 3.0, f"sqjax --help took {wall:.2f} s (target 1 s; 3 s allows for a loaded test machine)"


def test_lazy_names_resolve_and_dir_is_complete():
    for name in sqjax.__all__:
        assert getattr(sqjax, name) is not None, name
    assert set(sqjax.__all__) <= set(dir(sqjax))
    from sqjax import Superquadric, segment  # noqa: F401
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        sqjax.nonsense  # noqa: B018


def test_enable_compilation_cache_sets_jax(tmp_path):
    import jax

    before = (jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)
    try:
        assert sqjax.enable_compilation_cache(tmp_path / "c") == tmp_path / "c"
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "c")
        assert jax.config.jax_persistent_cache_min_compile_time_secs < 1.0
        assert sqjax.enable_compilation_cache("/proc/sqjax-test/cache") is None   # unusable: no failure
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])


def test_default_cache_dir(monkeypatch, tmp_path):
    from sqjax.cache import cache_disabled_by_env, default_cache_dir

    monkeypatch.delenv("SQJAX_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "sqjax" / "jax"
    monkeypatch.setenv("SQJAX_NO_CACHE", "1")
    assert cache_disabled_by_env()
    monkeypatch.setenv("SQJAX_NO_CACHE", "0")
    assert not cache_disabled_by_env()


def test_cli_fills_the_cache_unless_told_not_to(tmp_path):
    pts = tmp_path / "p.xyz"
    np.savetxt(pts, np.random.default_rng(0).normal(size=(64, 3)) * [0.3, 0.2, 0.1])
    code = f"from sqjax.cli import main\nraise SystemExit(main(['fit', {str(pts)!r}, '--max-steps', '2'] + EXTRA))"
    off = tmp_path / "off"
    r = _python(code.replace("EXTRA", "['--no-cache']"), {"SQJAX_CACHE_DIR": str(off)}, timeout=300)
    assert r.returncode == 0, r.stderr
    assert not off.exists() or not any(off.iterdir())
    on = tmp_path / "on"
    r = _python(code.replace("EXTRA", "[]"), {"SQJAX_CACHE_DIR": str(on), "SQJAX_NO_CACHE": ""}, timeout=300)
    assert r.returncode == 0, r.stderr
    assert any(on.iterdir()), "no compiled kernel was cached"


def test_figure_and_progress_dependencies_are_core():
    """`pip install . && sqjax demo` must draw figure.png: matplotlib (and tqdm) are not extras."""
    import tomllib

    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    names = {d.split(">")[0].split("=")[0].split(";")[0].strip() for d in deps}
    assert {"matplotlib", "tqdm"} <= names


def test_importing_the_segment_module_keeps_the_segment_function():
    import importlib

    module = importlib.import_module("sqjax.segment")   # as `from sqjax.segment import ...` does
    assert sqjax.segment is module.segment and callable(sqjax.segment)
    assert sqjax.evaluate is importlib.import_module("sqjax.evaluate")   # public modules stay modules
