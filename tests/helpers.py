"""The tests' zoo: problems with known answers, references written independently of the library, a
finite-difference helper, and the real data (`data_path`, which skips when it is absent).

Every test file takes these from here instead of defining its own copy.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import numpy as np
import pytest

from sqjax.cache import CPU_COMPILER_OPTIONS, cpu_options, with_options
from sqjax.mesh import sample_surface
from sqjax.superquadric import Superquadric

_ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("SQJAX_DATA", _ROOT.parent / "shared" / "data"))


def data_path(*parts) -> Path:
    """Path into the real test data (``../shared/data`` beside the clone, or $SQJAX_DATA); skips when absent."""
    p = DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real test data not found at {p} (set SQJAX_DATA to the shared/data folder)")
    return p


# ----------------------------------------------------------------------------------------------------
# problems with known answers


def random_rotation(rng) -> np.ndarray:
    """Uniform random rotation matrix (3, 3) (from a normalised Gaussian quaternion)."""
    q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_problem(rng, n=200, noise=0.01):
    """A random superquadric (sizes 0.5-2, exponents 0.2-1.8, random pose) and n points (n, 3) of one
    view of it, with noise `noise` times its mean size: ((size, eps, R, t), points)."""
    size, eps = rng.uniform(0.5, 2.0, 3), rng.uniform(0.2, 1.8, 2)
    R, t = random_rotation(rng), rng.uniform(-1, 1, 3)
    sq = Superquadric.create(size, eps, rotation=R, translation=t)
    view = rng.standard_normal(3)
    view = t + 10 * view / np.linalg.norm(view)
    pts = sample_surface(sq, n, seed=int(rng.integers(2**31)), noise=noise * size.mean(), viewpoint=view)
    return (size, eps, R, t), pts


def one_view_batch(K, n, seed=0) -> np.ndarray:
    """K one-view problems (K, n, 3) of random superquadrics (exponents 0.3-1.7, noise 0.01)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(K):
        sq = Superquadric.create(
            rng.uniform(0.5, 2.0, 3),
            rng.uniform(0.3, 1.7, 2),
            euler=rng.uniform(-3, 3, 3),
            translation=rng.uniform(-1, 1, 3),
        )
        view = np.asarray(sq.translation) + 10 * rng.standard_normal(3)
        out.append(sample_surface(sq, n, seed=int(rng.integers(1000)), noise=0.01, viewpoint=view))
    return np.stack(out)


def params(sq, k=None):
    """(size, epsilon, rotation, translation) of a `Superquadric` as numpy float64, problem k of a batch."""
    get = (lambda v: np.asarray(v, float)) if k is None else (lambda v: np.asarray(v[k], float))
    return get(sq.size), get(sq.epsilon), get(sq.rotation), get(sq.translation)


# ----------------------------------------------------------------------------------------------------
# references independent of the library


def inside(p, model) -> np.ndarray:
    """Eq. 5 written out in numpy: world points (n, 3) inside `model` = (size, eps, R, t) -> bool (n,)."""
    size, (e1, e2), R, t = model
    x = np.abs((p - t) @ R / size)
    with np.errstate(all="ignore"):
        F = ((x[:, 0] ** (2 / e2) + x[:, 1] ** (2 / e2)) ** (e2 / e1) + x[:, 2] ** (2 / e1)) ** e1
    return F <= 1.0


def volume_iou(a, b, n=40_000, seed=0) -> float:
    """Monte Carlo volume IoU of two models (size, eps, R, t) in the union of their bounding boxes."""
    rng = np.random.default_rng(seed)
    boxes = [np.abs(m[2]) @ m[0] for m in (a, b)]
    lo = np.minimum(a[3] - boxes[0], b[3] - boxes[1])
    hi = np.maximum(a[3] + boxes[0], b[3] + boxes[1])
    p = lo + (hi - lo) * rng.random((n, 3))
    ia, ib = inside(p, a), inside(p, b)
    return (ia & ib).sum() / max((ia | ib).sum(), 1)


def matched_axes(R_true, R_fit):
    """Permutation perm with fitted axis perm[i] closest to true axis i (the axis-permutation symmetry)."""
    dots = np.abs(R_true.T @ R_fit)
    return max(itertools.permutations(range(3)), key=lambda p: sum(dots[i, p[i]] for i in range(3)))


QUICK_XLA = {
    **CPU_COMPILER_OPTIONS,
    "xla_backend_optimization_level": 0,
    "xla_llvm_disable_expensive_passes": True,
}
"""XLA options for a test's one-off program, compiled once and run once (a gradient through a whole
deformed fit): the kernels' own (`sqjax.cache.CPU_COMPILER_OPTIONS`) and the cheapest optimisation.
The deformed-fit gradient compiled in 46 s instead of 104 s (2026-12-07, jaxlib 0.10.2); what the test
asserts is the derivative, not its speed."""


def quick_jit(fn):
    """`jax.jit(fn)` compiled with `QUICK_XLA` on CPU where this XLA knows the options
    (`sqjax.cache.cpu_options`), else plainly."""
    import jax

    return jax.jit(fn, **with_options(cpu_options(QUICK_XLA)))


def finite_difference_jvp(f, x, v, h=1e-5):
    """Central difference of f at x along v, (f(x + h v) - f(x - h v)) / 2h, with the step scaled by
    the size of x (h relative to max(1, |x|_inf)); numpy arrays in and out."""
    step = h * max(1.0, float(np.max(np.abs(np.asarray(x)))))
    return (np.asarray(f(x + step * v)) - np.asarray(f(x - step * v))) / (2 * step)


# ----------------------------------------------------------------------------------------------------
# real scenes


def mosd_truth(labels) -> np.ndarray:
    """mOSD truth regions: label // 10 per object, the table (labels 1-9) one region, 0 invalid."""
    labels = np.asarray(labels)
    return np.where(labels >= 10, labels // 10, np.where(labels > 0, 1, 0)).astype(np.int32)


def mosd_image(name: str):
    """mOSD scene `name` at 160 x 120 and its truth (`mosd_truth`); skips when ../shared/data is absent."""
    from sqjax.formats import read_range_image

    folder = "learn" if name.startswith("learn") else "test"
    image = read_range_image(data_path("mosd", folder, f"{name}.pcd")).subsample(4)
    return image, mosd_truth(image.labels)


# ----------------------------------------------------------------------------------------------------
# compile counts


def compiled_variants(fn) -> int:
    """How many compiled variants (input shapes, dtypes, static options) a jitted kernel holds: a
    `jax.jit` function, an `equinox.filter_jit` one, or either wrapped by `cache.persistent_kernel`."""
    fn = getattr(fn, "__wrapped__", fn) if not hasattr(fn, "_cache_size") and not hasattr(fn, "_cached") else fn
    jitted = getattr(fn, "_cached", fn)
    return int(jitted._cache_size())
