"""Rotations: the paper's ZYZ Euler angles at the API edge, rotation vectors inside.

All functions are pure `jax.numpy`, NaN-safe (a "safe operand" is formed with `jnp.where` *before*
any singular operation, with a Taylor branch near the singularity), and broadcast over leading axes.
The public ones are jitted (one compile per input shape when called eagerly).
"""

from __future__ import annotations

import jax.numpy as jnp

from .cache import kernel_jit
from .numerics import eps


def skew(w):
    """(..., 3) -> (..., 3, 3) cross-product matrix, `skew(w) @ v == cross(w, v)`."""
    z = jnp.zeros_like(w[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -w[..., 2], w[..., 1]], -1),
            jnp.stack([w[..., 2], z, -w[..., 0]], -1),
            jnp.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


@kernel_jit
def exp(w):
    """Rotation vector (..., 3) [rad] -> rotation matrix (..., 3, 3) (Rodrigues)."""
    t2 = jnp.sum(w * w, -1)[..., None, None]
    small = t2 < eps("rotation", w.dtype)
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 1.0 - t2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / t2s)
    k = skew(w)
    eye = jnp.eye(3, dtype=w.dtype)
    return eye + a * k + b * (k @ k)


def _quaternion(R):
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4) as (w, x, y, z), w >= 0 (Shepperd)."""
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = jnp.stack(
        [
            jnp.stack(
                [1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
            ),
            jnp.stack(
                [
                    R[..., 2, 1] - R[..., 1, 2],
                    1 + m00 - m11 - m22,
                    R[..., 0, 1] + R[..., 1, 0],
                    R[..., 0, 2] + R[..., 2, 0],
                ],
                -1,
            ),
            jnp.stack(
                [
                    R[..., 0, 2] - R[..., 2, 0],
                    R[..., 0, 1] + R[..., 1, 0],
                    1 - m00 + m11 - m22,
                    R[..., 1, 2] + R[..., 2, 1],
                ],
                -1,
            ),
            jnp.stack(
                [
                    R[..., 1, 0] - R[..., 0, 1],
                    R[..., 0, 2] + R[..., 2, 0],
                    R[..., 1, 2] + R[..., 2, 1],
                    1 - m00 - m11 + m22,
                ],
                -1,
            ),
        ],
        -2,
    )
    diag = jnp.stack([tr, m00, m11, m22], -1)
    i = jnp.argmax(diag, -1)
    q = jnp.take_along_axis(cands, i[..., None, None], -2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


@kernel_jit
def log(R):
    """Rotation matrix (..., 3, 3) -> rotation vector (..., 3) with angle in [0, pi].

    Through the unit quaternion (w, v), w >= 0: angle = 2 atan2(|v|, w), with a Taylor branch for small
    |v|; both branches see safe operands, so values and gradients stay finite at 0 and at pi.
    """
    q = _quaternion(R)
    w, v = q[..., 0], q[..., 1:]
    n2 = jnp.sum(v * v, -1)
    small = n2 < eps("rotation", R.dtype)
    n = jnp.sqrt(jnp.where(small, 1.0, n2))
    ws = jnp.where(small, w, 1.0)  # w ~ 1 on the Taylor branch; never 0 there
    taylor = 2.0 / ws - 2.0 * n2 / (3.0 * ws**3)
    scale = jnp.where(small, taylor, 2.0 * jnp.arctan2(n, w) / n)
    return v * scale[..., None]


def _rz(a):
    c, s, z, o = jnp.cos(a), jnp.sin(a), jnp.zeros_like(a), jnp.ones_like(a)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


def _ry(a):
    c, s, z, o = jnp.cos(a), jnp.sin(a), jnp.zeros_like(a), jnp.ones_like(a)
    return jnp.stack([jnp.stack([c, z, s], -1), jnp.stack([z, o, z], -1), jnp.stack([-s, z, c], -1)], -2)


@kernel_jit
def from_euler(angles):
    """ZYZ Euler angles (..., 3) = (phi, theta, psi) [rad] -> R = Rz(phi) Ry(theta) Rz(psi), (..., 3, 3).

    This is the convention of Solina & Bajcsy (1990) and of the paper's eq. 6.
    """
    angles = jnp.asarray(angles)
    return _rz(angles[..., 0]) @ _ry(angles[..., 1]) @ _rz(angles[..., 2])


@kernel_jit
def to_euler(R):
    """Rotation matrix (..., 3, 3) -> ZYZ Euler angles (..., 3), theta in [0, pi].

    At the gimbal lock (theta = 0 or pi) psi is set to 0 and phi carries the whole rotation. Every
    `arctan2` and `sqrt` sees a safe operand on the branch not taken, so gradients are finite
    (zero for psi at the lock, where the angles are not differentiable).
    """
    s2 = R[..., 0, 2] ** 2 + R[..., 1, 2] ** 2
    lock = s2 < eps("rotation", R.dtype) ** 2
    s = jnp.where(lock, 0.0, jnp.sqrt(jnp.where(lock, 1.0, s2)))
    theta = jnp.arctan2(s, R[..., 2, 2])
    safe = lambda x: jnp.where(lock, 1.0, x)
    phi_free = jnp.arctan2(safe(R[..., 1, 2]), safe(R[..., 0, 2]))
    psi_free = jnp.arctan2(safe(R[..., 2, 1]), safe(-R[..., 2, 0]))
    phi_lock = jnp.arctan2(jnp.where(lock, -R[..., 0, 1], 0.0), jnp.where(lock, R[..., 1, 1], 1.0))
    phi = jnp.where(lock, phi_lock, phi_free)
    psi = jnp.where(lock, 0.0, psi_free)
    return jnp.stack([phi, theta, psi], -1)
