"""Derivatives of fitted parameters with respect to the points (implicit function theorem at the optimum)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sqjax.fitting import FitOptions, fit
from sqjax.mesh import sample_surface
from sqjax.superquadric import Superquadric

from helpers import finite_difference_jvp, quick_jit

TRUTH = dict(size=(1.0, 0.7, 1.3), epsilon=(0.6, 1.3), euler=(0.3, 1.1, -0.8), translation=(0.2, -0.1, 0.4))
TIGHT = FitOptions(max_steps=40, multistart=False)  # from a warm start: converged to rounding in float64


def _points(n=60, seed=0, noise=0.02):
    sq = Superquadric.create(**TRUTH)
    return sample_surface(sq, n, seed=seed, noise=noise)


def _fitted(points):
    """(size, translation, epsilon) of the tight fit from the truth, as one vector (8,)."""
    init = Superquadric.create(**TRUTH, dtype=points.dtype)
    sq = fit(points, init=init, options=TIGHT).superquadric
    return jnp.concatenate([sq.size, sq.translation, sq.epsilon])


_fitted_jit = jax.jit(_fitted)
_jvp_jit = jax.jit(lambda q, t: jax.jvp(_fitted, (q,), (t,)))


@pytest.fixture(scope="module")
def x64():
    with jax.enable_x64(True):
        yield


@pytest.mark.slow
def test_jvp_matches_finite_differences_of_refits(x64):
    p = jnp.asarray(_points(), jnp.float64)
    rng = np.random.default_rng(1)
    fitted = _fitted_jit
    theta = np.asarray(fitted(p))
    assert np.all(theta[6:] > 0.15) and np.all(theta[6:] < 1.85)  # exponents inside the bounds
    for _ in range(2):
        v = jnp.asarray(rng.standard_normal(p.shape))
        _, tangent = _jvp_jit(p, v)
        fd = finite_difference_jvp(fitted, p, v)
        err = np.linalg.norm(np.asarray(tangent) - fd) / np.linalg.norm(fd)
        assert err < 1e-3, (err, np.asarray(tangent), fd)


@pytest.mark.slow
def test_reverse_mode_matches_forward_mode(x64):
    p = jnp.asarray(_points(seed=2), jnp.float64)
    rng = np.random.default_rng(3)
    w = jnp.asarray(rng.standard_normal(8))
    v = jnp.asarray(rng.standard_normal(p.shape))
    grad = jax.jit(jax.grad(lambda q: jnp.dot(w, _fitted(q))))(p)  # reverse: one VJP
    _, tangent = _jvp_jit(p, v)  # forward: one JVP
    assert float(jnp.sum(grad * v)) == pytest.approx(float(jnp.dot(w, tangent)), rel=1e-8)


@pytest.mark.slow
def test_grad_of_loss_under_jit_and_vmap():
    """A warm-started float32 fit (as in a differentiable pipeline) inside jit(vmap(grad(...))): finite,
    and the exact identities of an equivariant fit: d size / d(scaling) = size, d centre / d(shift) = I.

    The derivative comes from the optimality condition alone, so it is the same for every way of
    finding the optimum (multistart or warm start)."""
    pts = jnp.asarray(np.stack([_points(n=100, seed=s, noise=0.01) for s in (4, 5)]), jnp.float32)

    w = jnp.array([1.0, 2.0, 3.0, 0.5, -1.0, 1.5])

    init = Superquadric.create(**TRUTH)

    def loss(q):
        sq = fit(q, init=init, max_steps=15, multistart=False).superquadric
        out = jnp.concatenate([sq.size, sq.translation])
        return jnp.dot(w, out), out

    (values, out), grads = jax.jit(jax.vmap(jax.value_and_grad(loss, has_aux=True)))(pts)
    assert grads.shape == pts.shape and bool(jnp.all(jnp.isfinite(grads)))
    for k in range(2):
        # scaling the points about the origin scales sizes and centre: grad . p = loss
        assert float(jnp.sum(grads[k] * pts[k])) == pytest.approx(float(values[k]), rel=2e-3)
        # shifting all points by c shifts the centre by c: sum over points of d loss / d p = w_centre
        assert np.allclose(np.asarray(jnp.sum(grads[k], 0)), np.asarray(w[3:]), atol=2e-3)


@pytest.mark.slow
def test_deformed_fit_gradient_matches_finite_differences(x64):
    """`deform=True` picks its fit among rounds of bent and tapered starts (`solver.fit_one`, a scan over
    `DEFORMED_ROUNDS`): the derivative of the fitted shape with respect to the points, by reverse mode
    through that choice, matches central finite differences of whole refits within 1e-3. The shape is
    read as the signed distances of fixed probe points to the fitted surface, which do not depend on how
    it is parametrised (a tapered model with x and y swapped and its tapers negated is the same solid,
    and refits at nearby points may return either). The fits start from the moments alone
    (`multistart=False`: the same rounds and choice in a smaller program, 5.9 MB of StableHLO against
    6.8) and the gradient compiles with `QUICK_XLA`: with the multistart and XLA's defaults the test
    took 220 s of a cold run, now 80-100 s."""
    from sqjax.superquadric import signed_distance

    sq = Superquadric.create((0.5, 0.7, 1.5), (0.5, 0.8), taper=(0.4, -0.3))
    p = jnp.asarray(sample_surface(sq, 300, seed=1, noise=0.005), jnp.float64)
    probes = jnp.asarray(np.random.default_rng(4).uniform(-1.2, 1.2, (16, 3)) * [0.6, 0.8, 1.6])

    options = FitOptions(deform=True, multistart=False)

    def shape(q):
        return signed_distance(fit(q, options=options, dtype=jnp.float64).superquadric, probes)

    np.testing.assert_allclose(
        np.abs(fit(p, options=options, dtype=jnp.float64).superquadric.taper), [0.4, 0.3], atol=0.02
    )
    w = jnp.asarray(np.random.default_rng(5).standard_normal(16))
    v = jnp.asarray(np.random.default_rng(6).standard_normal(p.shape))
    grad = quick_jit(jax.grad(lambda q: jnp.dot(w, shape(q))))(p)
    fd = float(jnp.dot(w, finite_difference_jvp(shape, p, v)))
    assert np.all(np.isfinite(np.asarray(grad)))
    assert float(jnp.sum(grad * v)) == pytest.approx(fd, rel=1e-3)


def test_a_batch_with_an_empty_problem_differentiates():
    """A batch whose second problem has no valid point this iteration (all masked, or all NaN): the
    gradient of the first problem's volume is finite and the first problem's own. It raised lineax's
    "non-finite input" for the whole batch (the empty fit was NaN inside the implicit adjoint)."""
    pts = np.asarray(_points(200, noise=0.01), np.float32)
    batch = jnp.asarray(np.stack([pts, pts + 3.0]))
    mask = np.ones((2, 200), bool)
    mask[1] = False
    opts = FitOptions(multistart=False, max_steps=20)
    alone = quick_jit(jax.grad(lambda p: fit(p, options=opts).superquadric.volume))(jnp.asarray(pts))
    g_masked = quick_jit(jax.grad(lambda p: fit(p, mask, options=opts).superquadric.volume[0]))(batch)
    g_nan = quick_jit(jax.grad(lambda p: fit(p, options=opts).superquadric.volume[0]))(batch.at[1].set(jnp.nan))
    for g in (g_masked, g_nan):
        assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.max(jnp.abs(g[1]))) == 0.0
        np.testing.assert_allclose(g[0], alone, rtol=1e-3, atol=1e-3 * float(jnp.max(jnp.abs(alone))))
    res = quick_jit(lambda p: fit(p, mask, options=opts))(batch)
    assert not bool(res.converged[1]) and int(res.status[1]) != 0  # still flagged: too few points
