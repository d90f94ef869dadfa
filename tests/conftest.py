import os
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]

# One persistent compilation cache for the whole run. The pytest-xdist controller sets it before the
# workers start and they inherit it, so a kernel compiled in one worker is read back by the other, by
# the notebooks' kernels, the command-line subprocesses and the Dask workers (fresh processes that
# would otherwise compile it again): most of their time. Set before JAX is imported; a run that sets
# its own JAX_COMPILATION_CACHE_DIR keeps it. JAX writes an entry once and without a lock when
# eviction is off; a read racing the write of the same entry would fail loudly (warnings are errors
# here) and has not been seen. JAX's locked mode (a size limit) made a cold run 20% slower.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_ROOT / ".pytest_cache" / "jax"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
