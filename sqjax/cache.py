"""JAX's persistent compilation cache for sqjax: compiled kernels kept on disk between processes.

The command line turns it on by default (`--no-cache` or `SQJAX_NO_CACHE=1` turn it off); API users
call `sqjax.enable_compilation_cache()` once, before the first `segment` / `fit`.
"""

from __future__ import annotations

import os
from pathlib import Path

MIN_COMPILE_SECONDS = 0.0
"""Kernels that took at least this long to compile are cached (JAX's default, 1 s, misses most of ours)."""


def default_cache_dir() -> Path:
    """`$SQJAX_CACHE_DIR`, else `$XDG_CACHE_HOME/sqjax/jax`, else `~/.cache/sqjax/jax`."""
    if os.environ.get("SQJAX_CACHE_DIR"):
        return Path(os.environ["SQJAX_CACHE_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "sqjax" / "jax"


def cache_disabled_by_env() -> bool:
    """True when `SQJAX_NO_CACHE` is set to anything but "", "0", "false", "no"."""
    return os.environ.get("SQJAX_NO_CACHE", "").strip().lower() not in ("", "0", "false", "no")


def enable_compilation_cache(path=None) -> Path | None:
    """Turn on JAX's persistent compilation cache in `path` (default `default_cache_dir()`).

    Call it before the first compilation of the process (JAX reads the setting once). Returns the cache
    folder, or None when the folder cannot be created (then nothing is cached and nothing fails).
    """
    import jax

    path = Path(os.fspath(path)).expanduser() if path is not None else default_cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(path, os.W_OK | os.X_OK):
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
