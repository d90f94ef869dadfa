import os
from pathlib import Path

import pytest

_ROOT = Path(__file__).resolve().parents[1]
_DATA = Path(os.environ.get("SQJAX_DATA", _ROOT.parent / "shared" / "data"))

# One persistent compilation cache per test process: the kernels compiled by the in-process tests are
# read back by the notebooks' kernels, the command-line subprocesses and the Dask workers (each a fresh
# process that would otherwise compile them again), which is most of their time. Set before JAX is
# imported, so every child process inherits it; a run that sets its own JAX_COMPILATION_CACHE_DIR
# keeps it. One folder per pytest-xdist worker: JAX writes cache entries without a lock unless
# eviction is on, so two processes must not fill one folder at once.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      str(_ROOT / ".pytest_cache" / "jax" / os.environ.get("PYTEST_XDIST_WORKER", "main")))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")


def data_path(*parts) -> Path:
    """Path into the real test data (``../shared/data`` beside the clone, or $SQJAX_DATA); skips when absent."""
    p = _DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real test data not found at {p} (set SQJAX_DATA to the shared/data folder)")
    return p
