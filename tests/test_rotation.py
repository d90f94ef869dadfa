"""Rotations: exp/log and ZYZ Euler round trips on random and near-singular samples; finite gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sqjax import rotation as so3

from helpers import finite_difference_jvp

exp, log, from_euler, to_euler = (jax.jit(f) for f in (so3.exp, so3.log, so3.from_euler, so3.to_euler))


def _random_vectors(n, angles, seed=0):
    rng = np.random.default_rng(seed)
    axis = rng.standard_normal((n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return jnp.asarray(axis * np.asarray(angles)[:, None], jnp.float32)


def _check_rotation(R, atol=2e-6):
    R = np.asarray(R, float)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=atol)
    assert np.allclose(np.linalg.det(R), 1.0, atol=atol)


ANGLES = {
    "random": np.random.default_rng(1).uniform(0, np.pi, 200),
    "near zero": np.geomspace(1e-12, 1e-2, 50),
    "zero": np.zeros(3),
    "near pi": np.pi - np.geomspace(1e-6, 1e-2, 50),
}


@pytest.mark.parametrize("kind", ANGLES)
def test_exp_log_round_trip(kind):
    w = _random_vectors(len(ANGLES[kind]), ANGLES[kind])
    R = exp(w)
    _check_rotation(R)
    w2 = log(R)
    # log returns the angle in [0, pi]: compare rotations, and the vectors where the angle is not ~pi
    assert np.allclose(np.asarray(exp(w2)), np.asarray(R), atol=3e-6)
    if kind != "near pi":
        assert np.allclose(np.asarray(w2), np.asarray(w), atol=3e-6)
    else:
        assert np.allclose(np.linalg.norm(np.asarray(w2), axis=-1), ANGLES[kind], atol=2e-3)


def test_log_exactly_pi():
    for axis in np.eye(3):
        R = exp(jnp.asarray(np.pi * axis, jnp.float32))
        w = np.asarray(log(R))
        assert np.linalg.norm(w) == pytest.approx(np.pi, abs=1e-5)
        assert np.allclose(np.abs(w), np.pi * axis, atol=1e-5)


def test_exp_matches_rodrigues_float64():
    with jax.enable_x64(True):
        w = np.array([0.3, -1.2, 0.7])
        t = np.linalg.norm(w)
        k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / t
        ref = np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k
        assert np.allclose(np.asarray(so3.exp(jnp.asarray(w))), ref, atol=1e-14)
        assert np.allclose(np.asarray(so3.log(jnp.asarray(ref))), w, atol=1e-12)


@pytest.mark.parametrize(
    "angles",
    [
        (0.3, 1.2, -2.0),
        (-2.9, 0.1, 2.5),
        (1.0, np.pi / 2, 0.0),
        (0.4, 0.0, 0.3),  # gimbal lock theta = 0: only phi + psi is defined
        (0.4, np.pi, 0.3),  # gimbal lock theta = pi: only phi - psi is defined
        (0.0, 1e-7, 0.0),
    ],
)
def test_euler_round_trip(angles):
    R = from_euler(jnp.asarray(angles, jnp.float32))
    _check_rotation(R)
    e = np.asarray(to_euler(R))
    assert 0.0 <= e[1] <= np.pi
    assert np.allclose(np.asarray(from_euler(jnp.asarray(e))), np.asarray(R), atol=3e-6)
    if 1e-3 < angles[1] < np.pi - 1e-3:
        assert np.allclose(e, angles, atol=1e-5)
    elif angles[1] < 1e-3:
        assert e[2] == 0.0


def test_euler_round_trip_random():
    rng = np.random.default_rng(2)
    ang = np.stack(
        [rng.uniform(-np.pi, np.pi, 500), rng.uniform(0.01, np.pi - 0.01, 500), rng.uniform(-np.pi, np.pi, 500)], -1
    )
    R = from_euler(jnp.asarray(ang, jnp.float32))
    assert np.allclose(np.asarray(to_euler(R)), ang, atol=2e-4)
    assert np.allclose(np.asarray(from_euler(to_euler(R))), np.asarray(R), atol=3e-6)


def test_paper_convention_zyz():
    """R = Rz(phi) Ry(theta) Rz(psi): the model z axis is (cos phi sin theta, sin phi sin theta, cos theta)."""
    phi, theta, psi = 0.7, 0.4, -1.3
    R = np.asarray(so3.from_euler(jnp.array([phi, theta, psi])))
    assert np.allclose(R[:, 2], [np.cos(phi) * np.sin(theta), np.sin(phi) * np.sin(theta), np.cos(theta)], atol=1e-6)


@pytest.mark.parametrize(
    "fn, x",
    [
        (so3.exp, jnp.zeros(3)),
        (so3.exp, jnp.array([1e-9, -2e-9, 0.0])),
        (so3.exp, jnp.array([0.0, 0.0, np.pi])),
        (so3.log, jnp.eye(3)),
        (so3.log, so3.exp(jnp.array([1e-4, 0.0, 0.0]))),
        (so3.log, so3.exp(jnp.array([np.pi, 0.0, 0.0]))),
        (so3.log, so3.exp(jnp.array([0.0, np.pi - 1e-3, 0.0]))),
        (so3.to_euler, jnp.eye(3)),
        (so3.to_euler, so3.from_euler(jnp.array([0.3, np.pi, 0.2]))),
        (so3.to_euler, so3.from_euler(jnp.array([0.3, 0.8, 0.2]))),
        (so3.from_euler, jnp.zeros(3)),
    ],
)
def test_gradients_finite(fn, x):
    J = jax.jit(jax.jacobian(fn))(x)
    assert bool(jnp.all(jnp.isfinite(J)))
    if fn is so3.exp and not np.any(np.asarray(x)):
        # d exp(w) / dw at 0 is the generator: d/dw_i (exp(w) v) = e_i x v
        assert np.allclose(np.asarray(J[..., 0]), np.asarray(so3.skew(jnp.array([1.0, 0.0, 0.0]))))


def test_exp_log_jacobians_inverse_at_identity():
    J_exp = jax.jit(jax.jacobian(so3.exp))(jnp.zeros(3)).reshape(9, 3)
    J_log = jax.jit(jax.jacobian(so3.log))(jnp.eye(3)).reshape(3, 9)
    assert np.allclose(np.asarray(J_log @ J_exp), np.eye(3), atol=1e-6)


def test_gradient_matches_finite_differences():
    with jax.enable_x64(True):
        w = jnp.array([0.4, -0.9, 1.7])
        f = lambda v: jnp.sum(so3.log(so3.exp(v) @ so3.exp(jnp.array([0.1, 0.2, -0.3]))) ** 2)
        g = np.asarray(jax.jit(jax.grad(f))(w))
        fj = jax.jit(f)
        fd = np.array([finite_difference_jvp(fj, w, e, h=1e-6 / 1.7) for e in np.eye(3)])  # step 1e-6
        assert np.allclose(g, fd, rtol=1e-6, atol=1e-8)
