"""Transformation consistency of the fitter: batch == loop, jit == no jit, one trace per bucket, devices."""

import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import sqjax.initial as initial
import sqjax.lm as lm
import sqjax.padding as padding
import sqjax.solver as solver
from sqjax.fitting import FitOptions, fit

from helpers import one_view_batch


def _same_fit(a, b, rtol=1e-4):
    """Same cost and the same per-point distances (both independent of how the model is parametrised).

    Batched and single kernels may round differently in the last bit; LM then ends a few ulps apart.
    """
    assert np.allclose(np.asarray(a.cost), np.asarray(b.cost), rtol=rtol)
    assert np.allclose(np.asarray(a.distance), np.asarray(b.distance), rtol=rtol, atol=2e-4)


def test_batch_equals_loop_of_single_fits():
    # K = 30 is padded to 32 (and N = 200 to 256: the kernel test_fitting.py compiles too)
    pts = one_view_batch(30, 200)
    batched = fit(pts)
    for k in range(0, 30, 6):
        single = fit(pts[k])
        assert single.cost.shape == () and single.superquadric.size.shape == (3,)
        _same_fit(jax.tree.map(lambda v, k=k: v[k], batched), single)


def test_jit_equals_no_jit():
    """The LM kernel's normal equations (cost, J^T J, J^T r) compiled and run op by op."""
    pts = jnp.asarray(one_view_batch(1, 24, seed=1)[0].T, jnp.float32)
    mask = jnp.arange(24) < 20
    opts = FitOptions(multistart=False)

    def run(p, m):
        start = jax.tree.map(lambda v: v[1], initial.moment_starts(p, m))
        return lm._normal_equations(start, p, m, opts)

    jitted = jax.jit(run)(pts, mask)
    with jax.disable_jit():
        eager = run(pts, mask)
    for a, b in zip(jitted, eager, strict=True):
        assert np.allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)


def test_kernel_traces_once_per_bucket(monkeypatch):
    counted = eqx.debug.assert_max_traces(solver.map_problems, max_traces=None)
    monkeypatch.setattr(solver, "map_problems", counted)
    opts = FitOptions(max_steps=2, multistart=False)  # a fresh compile-cache key for this test
    pts = one_view_batch(2, 100, seed=2)
    for n in (40, 50, 64):  # growth steps inside one bucket (128): one trace
        fit(pts[:, :n], options=opts)
    fit(pts[:, :60], mask=np.broadcast_to(np.arange(60) < 50, (2, 60)), options=opts)
    assert eqx.debug.get_num_traces(counted) == 1


def test_a_screened_multistart_serves_n_from_129_to_1024_with_one_kernel(monkeypatch):
    """Issue 14 (a user's loop over N): the multistart's work is its screening on 256 points, so every
    N from 129 to 4 x 256 pads to 1024 rows (`padding.fit_points`) and traces one kernel, where
    powers of two traced three (256, 512, 1024). Warm starts and unscreened fits keep powers of two."""
    assert [padding.fit_points(n, 256) for n in (100, 128, 129, 300, 1024, 1025)] == [128] * 2 + [1024] * 3 + [2048]
    assert [padding.fit_points(n, None) for n in (129, 300, 1024)] == [256, 512, 1024]
    counted = eqx.debug.assert_max_traces(solver.map_problems, max_traces=None)
    monkeypatch.setattr(solver, "map_problems", counted)
    opts = FitOptions(max_steps=2, epsilon_starts=((1.0, 1.0),))  # a fresh compile-cache key for this test
    pts = one_view_batch(1, 1000, seed=3)[0]
    for n in (130, 300, 700, 1000):
        r = fit(pts[:n], options=opts)
        assert r.distance.shape == (n,) and int(r.num_points) == n
    assert eqx.debug.get_num_traces(counted) == 1


def test_fit_chunks_divide_the_padded_batch(monkeypatch):
    """`fit`'s kernel fits a power of two of problems at a time (`padding.fit_chunk`): it divides every
    padded K, so the program holds one copy of the fit (a remainder would be a second); within the
    points and candidates a chunk may hold; by the screened points on one device, by N on several."""
    from sqjax import padding, parallel

    for devices in (1, 2):
        monkeypatch.setattr(parallel, "cpu_devices", lambda d=devices: d)
        for K in (1, 2, 8, 32, 64, 256):
            for N in (32, 128, 256, 1024, 4096, 8192):
                for candidates, screened in ((1, N), (18, min(N, 256))):
                    c = padding.fit_chunk(K, N, candidates, screened)
                    sized = screened if devices == 1 else N
                    assert c >= 1 and c & (c - 1) == 0 and K % c == 0, (K, N, c)
                    assert c == 1 or c * sized <= padding.CHUNK_POINTS, (K, N, c)
                    assert c == 1 or c * candidates <= padding.MULTISTART_CANDIDATES, (K, N, c)
                    widest = min(K, padding.CHUNK_POINTS // sized, padding.MULTISTART_CANDIDATES // candidates)
                    assert 2 * c > widest, (K, N, c)


_TWO_DEVICES = textwrap.dedent("""
    import jax, numpy as np, jax.numpy as jnp
    import sqjax.fitting as fitting
    from sqjax.fitting import FitOptions, fit
    import sqjax.parallel as parallel
    assert jax.device_count() == 2 and parallel.splits(4)
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 64, 3)) * np.array([1.0, 0.6, 0.3])
    opts = FitOptions(max_steps=3, multistart=False, robust=True)
    sharded = fit(pts, options=opts)
    parallel.splits = lambda K, at_least=0: False  # the same call on one device
    single = fit(pts, options=opts)
    assert np.array_equal(np.asarray(sharded.cost), np.asarray(single.cost))
    assert np.array_equal(np.asarray(sharded.distance), np.asarray(single.distance))
    assert np.array_equal(np.asarray(sharded.weight), np.asarray(single.weight))
    # segmentation: refits and pair kernels split over the two devices, the same labels as on one
    from sqjax import segment
    from sqjax.scenes import random_scene
    image, _ = random_scene(3, n_parts=(3, 3), shape=(60, 80))
    parallel.splits = lambda K, at_least=0: K % 2 == 0  # every call split, the pair kernels' small ones too
    parallel.cpu_devices = lambda: 2
    split = segment(image, window=6)
    parallel.splits, parallel.cpu_devices = (lambda K, at_least=0: False), (lambda: 1)
    assert np.array_equal(split.labels, segment(image, window=6).labels)
    print("ok")
""")


def test_two_cpu_devices_give_identical_results():
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", _TWO_DEVICES], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


_MULTISTART_TWO_DEVICES = textwrap.dedent("""
    import jax, numpy as np
    import sqjax.parallel as parallel
    from sqjax.fitting import FitOptions, fit
    assert jax.device_count() == 2
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(64, 96, 3)) * np.array([1.0, 0.6, 0.3])
    opts = FitOptions(max_steps=2, robust=False)  # the 18 starting candidates of the multistart
    sharded = fit(pts, options=opts)
    parallel.splits = lambda K, at_least=0: False
    single = fit(pts, options=opts)
    assert np.isfinite(np.asarray(sharded.cost)).all()
    a, b = np.asarray(sharded.cost), np.asarray(single.cost)  # chunked differently: rounding only
    assert np.allclose(a, b, rtol=1e-3, atol=1e-6 * np.max(b)), np.max(np.abs(a - b) / b)
    print("ok")
""")


def test_a_large_multistart_batch_over_two_devices_finishes():
    """64 problems of 18 candidates split over two CPU devices: in one vmap of 32 problems per device
    XLA's runtime waited forever (`padding.MULTISTART_CANDIDATES`); now it finishes, as on one device."""
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    out = subprocess.run(
        [sys.executable, "-c", _MULTISTART_TWO_DEVICES], env=env, capture_output=True, text=True, timeout=180
    )
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


_KEPT_SPLIT_KERNELS = textwrap.dedent("""
    import pathlib, tempfile
    import jax, numpy as np
    from sqjax import cache, parallel, solver
    from sqjax.fitting import FitOptions, fit
    from sqjax.workspace import _pair_distances
    assert jax.device_count() == 2 and parallel.splits(4)
    folder = pathlib.Path(tempfile.mkdtemp())
    cache.set_kernel_dir(folder)
    traces, real = [], solver.map_problems
    solver.map_problems = lambda *a, **k: (traces.append(1), real(*a, **k))[1]
    leaves = lambda out: [np.asarray(v) for v in jax.tree.leaves(out)]
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 64, 3)) * np.array([1.0, 0.6, 0.3])
    opts = FitOptions(max_steps=3, multistart=False)
    first = leaves(fit(pts, options=opts))  # the split fit kernel, exported on its first call
    theta = np.zeros((8, 11), np.float32)
    theta[:, :3], theta[:, 3:5], theta[:, 8:] = np.log(0.5), 1.0, rng.normal(size=(8, 3)) * 0.2
    args = (theta, rng.normal(size=(16, 3)).astype(np.float32), np.tile(np.float32([0, 0, 1]), (16, 1)),
            rng.integers(0, 16, 8).astype(np.int32), np.float32(1.15), np.float32(0.01))
    split = parallel.sharded_kernel(_pair_distances, (True, False, False, True, False, False))
    pairs = leaves(split(*args))
    assert len(traces) == 1 and len(list(folder.rglob("*.jaxexport"))) >= 2
    cache._LOADED.clear()  # a new process: only the disk is left
    jax.clear_caches()
    exports, export = [], cache._export
    cache._export = lambda *a: (exports.append(1), export(*a))[1]
    assert all(np.array_equal(a, b) for a, b in zip(first, leaves(fit(pts, options=opts))))
    assert all(np.array_equal(a, b) for a, b in zip(pairs, leaves(split(*args))))
    assert len(traces) == 1 and not exports, "a kept split kernel was traced again"
    cache.set_kernel_dir(None)  # the kernels as traced: the same results, bit for bit
    assert all(np.array_equal(a, b) for a, b in zip(first, leaves(fit(pts, options=opts))))
    assert all(np.array_equal(a, b) for a, b in zip(pairs, leaves(_pair_distances(*args))))
    print("ok")
""")


def test_kernels_split_over_two_devices_are_kept_and_load_back():
    """With the kernel folder set, the fit and pair kernels split over the CPU devices are exported
    too: a later process loads them without tracing (the command line's several inputs then skip
    5-9 s of tracing per call), and their results are the traced kernels', bit for bit."""
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    run = [sys.executable, "-c", _KEPT_SPLIT_KERNELS]
    out = subprocess.run(run, env=env, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]
