"""How sqjax's kernels compile (`kernel_jit`, `compiler_options`), and JAX's persistent compilation
cache for them: compiled kernels kept on disk between processes.

The command line turns it on by default (`--no-cache` or `SQJAX_NO_CACHE=1` turn it off); API users
call `sqjax.enable_compilation_cache()` once, before the first `segment` / `fit`.

JAX's cache keeps the compiled code, but it can only be asked after the kernel has been traced and
lowered again, and for the fit kernels that is most of a warm start (about 1.5 s of Python per
kernel: 3.8 s of `sqjax demo`'s 9 s). So the fit and pair kernels (`persistent_kernel`), those
split over the CPU devices too, are also kept as serialized `jax.export` modules, next to JAX's
cache, keyed by sqjax's source, the JAX version, the backend, the number of devices and the kernel's
arguments (shapes, dtypes, static options): a later process deserializes the
module (no tracing) and JAX's cache supplies its compiled code. The results are those of the traced
kernel, bit for bit (the same StableHLO).
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
import tempfile
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
    set_kernel_dir(path / "sqjax-kernels")
    return path


# ----------------------------------------------------------------------------------------------------
# how the kernels compile

CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
"""XLA options of sqjax's kernels on CPU (all but `fit`'s batch kernel, `kernel_jit`): XLA's elemental
loop emitters instead of its MLIR fusion emitters, which trade run time for compile time. Measured
2026-12-04 on the 2-core machine (jaxlib 0.10.2, benchmarks/RESULTS.md):

- compile: the multistart fit kernel 3.2 s instead of 4.7 s; a first mOSD scene's kernels 14.6 s of
  XLA instead of 27.4 s; 59 mOSD scenes in one process with an empty cache 174 s instead of 234 s;
- run time: the fit kernels 15-24% slower in isolation, a segmented scene about 4% (interleaved A/B
  in two processes, 1.038 and 1.048).

A segmentation compiles about 36 kernels on a user's first run and in every notebook session (the API
keeps no cache unless `enable_compilation_cache` is called); 4% of a 2 s scene is what 10 s of compile
buys back after 125 scenes. `fit`'s batch kernel keeps XLA's defaults: one compile per bucket, then
whole batches through it. A long batch run with a warm cache can take XLA's
defaults instead: `sqjax.cache.CPU_COMPILER_OPTIONS.clear()` before the first kernel is called."""


def with_options(options: dict) -> dict:
    """`jax.jit`'s keyword for `options`, none when they are empty (a JAX older than `compiler_options`
    then works as before)."""
    return {"compiler_options": options} if options else {}


def compiler_options() -> dict:
    """The XLA options sqjax's kernels compile with: `CPU_COMPILER_OPTIONS` where `cpu_options` keeps them."""
    return cpu_options(CPU_COMPILER_OPTIONS)


def cpu_options(options: dict) -> dict:
    """`options` on CPU where this XLA knows every one of them (checked once per set, by compiling a
    one-line function with them), else none: an XLA without an option refuses it ("No such compile
    option"), and a jax.jit without the keyword refuses that."""
    return dict(_known_on_cpu(tuple(sorted(options.items()))))


@functools.cache
def _known_on_cpu(items: tuple) -> tuple:
    import jax

    if not items or jax.default_backend() != "cpu":
        return ()
    try:
        jax.jit(lambda x: x + 1, compiler_options=dict(items)).lower(1.0).compile()
    except Exception:
        return ()
    return items


class kernel_jit:
    """`jax.jit(fn, **jit_kwargs)` (with `filter`, `equinox.filter_jit`) compiled with `compiler_options()`
    (with `fast_compile`, the default) or with XLA's defaults.

    `fast_compile=False` is for kernels whose run time matters more than their compile: `fit`'s batch
    kernel, compiled once per bucket and then run on whole batches (the loop emitters cost it 15-24% of
    its throughput). The jitted functions are made on the first call (or attribute access: `lower`,
    `trace`), not at import, so that importing sqjax starts no JAX backend. Called under a
    transformation (tracers among the arguments), it is a plain nested jit: JAX takes compiler options
    at the top level only."""

    def __init__(self, fn, *, filter: bool = False, fast_compile: bool = True, **jit_kwargs):
        functools.update_wrapper(self, fn)
        self._fn, self._filter, self._fast, self._kwargs = fn, filter, fast_compile, jit_kwargs
        self._jitted: dict = {}

    def options(self) -> dict:
        """The XLA options this kernel compiles with at the top level."""
        return compiler_options() if self._fast else {}

    def jitted(self, top: bool = True):
        """The jitted function: with this kernel's compiler options (`top`), or plain (nested in a trace)."""
        if top not in self._jitted:
            import jax

            options = {**with_options(self.options()), **self._kwargs} if top else self._kwargs
            if self._filter:
                import equinox as eqx

                self._jitted[top] = eqx.filter_jit(self._fn, **options)  # pyright: ignore[reportCallIssue]
            else:
                self._jitted[top] = jax.jit(self._fn, **options)
        return self._jitted[top]

    def __call__(self, *args, **kwargs):
        import jax

        traced = any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves((args, kwargs)))  # pyright: ignore[reportAttributeAccessIssue]
        return self.jitted(not traced)(*args, **kwargs)

    def __getattr__(self, name):  # lower, trace, eval_shape, _cache_size ...
        if name.startswith("__") or name in ("_fn", "_filter", "_fast", "_kwargs", "_jitted"):
            raise AttributeError(name)
        return getattr(self.jitted(), name)


# ----------------------------------------------------------------------------------------------------
# traced-and-lowered kernels on disk (jax.export)

_KERNEL_DIR: Path | None = None
"""Where `persistent_kernel` keeps serialized modules; None: off (every call traces as usual)."""
_LOADED: dict = {}
"""In this process: key -> jitted call of the deserialized module (or None after a failed export)."""
_KEEP_VERSIONS = 4
"""Folders of other sqjax sources / JAX versions kept beside the current one (the oldest go)."""


def set_kernel_dir(path) -> Path | None:
    """Keep `persistent_kernel` modules under `path` (None turns it off). `enable_compilation_cache`
    calls it; without JAX's compilation cache the modules would still be compiled on every run."""
    global _KERNEL_DIR
    _LOADED.clear()
    _FOLDER.clear()
    _KERNEL_DIR = None if path is None else Path(os.fspath(path))
    return _KERNEL_DIR


@functools.cache
def _fingerprint() -> str:
    """sqjax's source, the JAX version and the platform: what a kernel's module depends on besides its
    arguments."""
    from importlib.metadata import version

    import jax

    h = hashlib.sha256()
    for f in sorted(Path(__file__).parent.glob("*.py")):
        h.update(f.name.encode() + b"\0" + f.read_bytes())
    device = jax.devices()[0]
    h.update(repr((jax.__version__, version("jaxlib"), device.platform, device.device_kind)).encode())
    return h.hexdigest()[:20]


_FOLDER: dict = {}
"""The kernel folder's path once `_folder` has made it (a file-system call per kernel call saved)."""


def _folder() -> Path | None:
    """This fingerprint's folder (created once per process and kernel folder; older fingerprints
    beyond `_KEEP_VERSIONS` removed)."""
    if _KERNEL_DIR is None:
        return None
    if _KERNEL_DIR in _FOLDER:
        return _FOLDER[_KERNEL_DIR]
    folder = _KERNEL_DIR / _fingerprint()
    if not folder.is_dir():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            others = sorted(
                (d for d in _KERNEL_DIR.iterdir() if d.is_dir() and d != folder), key=lambda d: d.stat().st_mtime
            )
            for old in others[: max(0, len(others) - _KEEP_VERSIONS)]:
                shutil.rmtree(old, ignore_errors=True)
        except OSError:
            return None
    _FOLDER[_KERNEL_DIR] = folder
    return folder


_MAP_SHARE = 0.75
"""Share of the process's memory-map limit (`vm.max_map_count`) at which compiled kernels are let go."""
_SEEN: set = set()
"""Kernel signatures called in this process since the last release (a new one may compile or load)."""


def _map_count() -> tuple[int, int] | None:
    """(memory maps of this process, the kernel's limit on them), or None where /proc does not tell."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f), limit
    except (OSError, ValueError):
        return None


def release_if_crowded() -> bool:
    """Let go of every compiled kernel of the process (JAX's in-memory caches and the loaded modules)
    when its memory maps near the limit, and say whether it did.

    Each compiled CPU kernel maps about 1,000 regions of memory (the deformable fit's 2,500: one per
    JIT-linked section), never released while the kernel is cached, and Linux allows a process
    `vm.max_map_count` (65,530 by default). A notebook that fits batches of many sizes would reach it
    after 25-60 kernels, and XLA then aborts the process ("LLVM ERROR: Unable to allocate section
    memory"). Released kernels come back from the compilation cache when they are called again."""
    count = _map_count()
    if count is None or count[0] < _MAP_SHARE * count[1]:
        return False
    import gc

    import jax

    _LOADED.clear()
    _SEEN.clear()
    jax.clear_caches()
    gc.collect()
    return True


def persistent_kernel(fn, name: str | None = None):
    """`fn` (a jitted function of arrays, `None`s and option modules) whose traced and lowered form is
    kept on disk while the kernel folder is set (`enable_compilation_cache`). The arrays among the
    arguments' leaves are the module's inputs; everything else (option fields, Python scalars, the
    tree, the number of devices) is part of the key, and `name` (default: `fn`'s) tells kernels of
    the same arguments apart. Kernels split over the CPU devices (`parallel.sharded_kernel`) are kept
    too: they load for the same device count. Calls under a JAX transformation (tracers among the
    arguments), and any kernel that cannot be exported or loaded, run `fn` itself."""
    import jax
    import numpy as np

    if name is None:
        name = f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', getattr(fn, '__name__', ''))}"
    # the arguments are scanned for tracers here once: a `kernel_jit` is called through its jitted form
    jitted = fn.jitted if isinstance(fn, kernel_jit) else (lambda top=True: fn)

    arrays = (jax.Array, np.ndarray, np.generic)
    keys: dict = {}  # signature -> key: the reprs and the hash once per signature, not per call

    def key_of(leaves, tree, dynamic, x64) -> str:
        spec = (
            name,
            x64,
            jax.device_count(),
            repr(tree),
            [(v.shape, str(v.dtype)) if i in dynamic else repr(v) for i, v in enumerate(leaves)],
        )
        return hashlib.sha256(repr(spec).encode()).hexdigest()[:32]

    @functools.wraps(fn, updated=())
    def call(*args):
        leaves, tree = jax.tree.flatten(args)
        if any(isinstance(v, jax.core.Tracer) for v in leaves):  # pyright: ignore[reportAttributeAccessIssue]
            return jitted(False)(*args)
        folder = _folder()
        dynamic = [i for i, v in enumerate(leaves) if isinstance(v, arrays)]  # a handful: a list suffices
        inputs = [leaves[i] for i in dynamic]
        x64 = jax.dtypes.canonicalize_dtype(np.float64) == np.float64  # changes what constants trace to
        # a float static leaf by its repr: -0.0 == 0.0, yet they trace to different constants
        sig = tuple(
            (v.shape, v.dtype) if i in dynamic else (type(v), repr(v) if isinstance(v, float) else v)
            for i, v in enumerate(leaves)
        )
        try:
            key = keys.get((x64, tree, sig))
        except TypeError:  # an unhashable static leaf: its key from the reprs, every call
            key, sig = key_of(leaves, tree, dynamic, x64), None
        if key is None:
            key = keys[(x64, tree, sig)] = key_of(leaves, tree, dynamic, x64)
        if key not in _SEEN:  # a kernel new to the process (or released) compiles or loads: room for it
            release_if_crowded()
            _SEEN.add(key)
        if folder is None:
            return jitted()(*args)
        if key not in _LOADED:
            options = fn.options() if isinstance(fn, kernel_jit) else {}
            _LOADED[key] = _load(folder / f"{key}.jaxexport", options) or _export(
                fn, leaves, tree, dynamic, inputs, folder / f"{key}.jaxexport", options
            )
        kernel = _LOADED[key]
        return jitted()(*args) if kernel is None else kernel(*inputs)

    return call


def _load(path: Path, options: dict):
    import jax

    try:
        blob = path.read_bytes()
    except OSError:
        return None
    try:
        return _callable(jax.export.deserialize(bytearray(blob)), options)
    except Exception:  # a corrupt or foreign file: export it again
        return None


def _callable(exported, options: dict):
    """The jitted call of an exported module. One split over the devices (`nr_devices` > 1, the
    split inside it) runs on all of them, its inputs and outputs placed whole on each (a copy per
    device, which the split slices): the traced kernel's results bit for bit (tests/test_vmap.py),
    and its time within the machine's drift (six mOSD scenes on two devices, 2026-12-08: 17.9 and
    19.4 s against 18.0 and 18.3 s traced)."""
    import jax

    from .parallel import device_mesh

    kw = with_options(options)
    if exported.nr_devices > 1:  # the same count as here: it is part of the key
        whole = jax.sharding.NamedSharding(device_mesh(), jax.sharding.PartitionSpec())
        kw.update(in_shardings=whole, out_shardings=whole)
    return jax.jit(exported.call, **kw)


def _export(fn, leaves, tree, dynamic, inputs, path: Path, options: dict):
    import jax

    def flat(*arrays):
        full = list(leaves)
        for i, a in zip(dynamic, arrays):
            full[i] = a
        return fn(*jax.tree.unflatten(tree, full))

    try:
        exported = jax.export.export(jax.jit(flat), platforms=(jax.default_backend(),))(*inputs)
        blob = exported.serialize()
    except Exception:  # not exportable (a host callback, a missing serializer): trace as usual
        return None
    try:  # atomic: a concurrent process (a Dask worker) reads a whole file or none
        with tempfile.NamedTemporaryFile(dir=path.parent, delete=False, suffix=".tmp") as f:
            f.write(blob)
        os.replace(f.name, path)
    except OSError:
        pass
    return _callable(exported, options)
