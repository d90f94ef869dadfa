"""The superquadric: parameters, inside-outside function (eq. 5), residual (eq. 7), distances (eq. 10).

Every function here is pure `jax.numpy` for one superquadric and points of shape `(..., 3)`; use
`jax.vmap` for batches. Powers `|x / a| ** (2 / e)` are evaluated in the log domain,
`exp((2 / e) * (log|x| - log a))`, with `log|x|` taken of a safe operand (|x| floored at 1e-10 a in
float32, 1e-20 a in float64), so values and gradients are finite for every finite input (at the centre,
on the axes, far away, e down to 0.1). The public functions are jitted: called eagerly, each compiles
once per input shape (not once per primitive), and inside another jit they are inlined.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import rotation as so3

EPSILON_RANGE = (0.1, 1.9)
"""Range the shape exponents e1, e2 are kept in."""


def _tiny(dtype):
    return jnp.finfo(dtype).tiny


def _log_cap(dtype):
    # F is capped at exp(cap): far beyond any data (|x / a| ~ 1e4 in float32) yet f**2 cannot overflow.
    return 20.0 if jnp.dtype(dtype) == jnp.float32 else 60.0


def _check_fields(**fields):
    """Host-side checks of `Superquadric.create`'s concrete arguments; a ValueError names the field."""

    def concrete(v):
        return v is not None and not any(
            isinstance(x, jax.core.Tracer)  # pyright: ignore[reportAttributeAccessIssue]
            for x in jax.tree.leaves(v)
        )

    vals = {k: np.asarray(v, np.float64) for k, v in fields.items() if concrete(v)}
    last = {"size": 3, "epsilon": 2, "euler": 3, "translation": 3, "taper": 2, "bend": 2}
    for name, v in vals.items():
        if name in last and (v.ndim == 0 or v.shape[-1] != last[name]):
            raise ValueError(f"Superquadric.create: {name} must have a last axis of {last[name]}, got shape {v.shape}")
        if name == "rotation" and v.shape[-2:] != (3, 3):
            raise ValueError(f"Superquadric.create: rotation must be (..., 3, 3), got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"Superquadric.create: {name} must be finite, got {v.tolist()}")
    if "size" in vals and not np.all(vals["size"] > 0):
        raise ValueError(f"Superquadric.create: size must be > 0, got {vals['size'].tolist()}")
    if "epsilon" in vals and not np.all(vals["epsilon"] > 0):
        raise ValueError(f"Superquadric.create: epsilon must be > 0, got {vals['epsilon'].tolist()}")
    if "taper" in vals and not np.all(np.abs(vals["taper"]) <= 1.0):
        raise ValueError(f"Superquadric.create: taper must lie in [-1, 1], got {vals['taper'].tolist()}")
    if "bend" in vals and not np.all(vals["bend"][..., 0] >= 0):
        raise ValueError(f"Superquadric.create: bend curvature k must be >= 0, got {vals['bend'].tolist()}")
    if "rotation" in vals:
        R = vals["rotation"]
        err = np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)))
        if err > 1e-3 or not np.all(np.linalg.det(R) > 0):
            raise ValueError(
                f"Superquadric.create: rotation must be orthonormal with det +1 "
                f"(max |R^T R - I| = {err:.3g}, det = {np.linalg.det(R).tolist()})"
            )


class Superquadric(eqx.Module):
    """A superquadric in general position, optionally tapered and bent (Solina & Bajcsy 1990).

    Fields (leading batch axes allowed, all the same):

    - `size`: `(..., 3)` half-axes a1, a2, a3 > 0, in the units of the points.
    - `epsilon`: `(..., 2)` shape exponents e1 (north-south, along z), e2 (east-west, in xy).
    - `rotation`: `(..., 3, 3)` matrix whose columns are the model axes in world coordinates.
    - `translation`: `(..., 3)` model centre in world coordinates.
    - `taper`: `(..., 2)` tapering Kx, Ky along z, in [-1, 1]; zero for none.
    - `bend`: `(..., 2)` bending curvature k >= 0 (1 / units) and direction angle alpha (rad); k = 0 for none.
    """

    size: jax.Array
    epsilon: jax.Array
    rotation: jax.Array
    translation: jax.Array
    taper: jax.Array
    bend: jax.Array

    @classmethod
    def create(
        cls,
        size,
        epsilon=(1.0, 1.0),
        *,
        rotation=None,
        euler=None,
        translation=(0.0, 0.0, 0.0),
        taper=(0.0, 0.0),
        bend=(0.0, 0.0),
        dtype=jnp.float32,
    ) -> Superquadric:
        """Build from plain values; `euler` = ZYZ angles (phi, theta, psi) as in the paper, or `rotation`.

        Concrete values are checked (a `ValueError` names the field): sizes finite and > 0, exponents
        finite and > 0, a rotation orthonormal with det +1 (to 1e-3), everything finite, taper in
        [-1, 1], bending curvature >= 0. Traced values (under jit / grad) are not checked.
        """
        _check_fields(
            size=size, epsilon=epsilon, rotation=rotation, euler=euler, translation=translation, taper=taper, bend=bend
        )
        size = jnp.asarray(size, dtype)
        batch = size.shape[:-1]
        if rotation is None:
            rotation = so3.from_euler(jnp.asarray(euler if euler is not None else (0.0, 0.0, 0.0), dtype))
        f = lambda v, n: jnp.broadcast_to(jnp.asarray(v, dtype), batch + (n,))
        return cls(
            size,
            f(epsilon, 2),
            jnp.broadcast_to(jnp.asarray(rotation, dtype), batch + (3, 3)),
            f(translation, 3),
            f(taper, 2),
            f(bend, 2),
        )

    @property
    def euler(self) -> jax.Array:
        """ZYZ Euler angles (phi, theta, psi), `(..., 3)` rad."""
        return so3.to_euler(self.rotation)

    @property
    def volume(self) -> jax.Array:
        """Volume of the undeformed solid, `(...)`: 2 a1 a2 a3 e1 e2 B(e1/2 + 1, e1) B(e2/2, e2/2)."""
        e1, e2 = self.epsilon[..., 0], self.epsilon[..., 1]
        lb = lambda x, y: jax.scipy.special.gammaln(x) + jax.scipy.special.gammaln(y) - jax.scipy.special.gammaln(x + y)
        return 2.0 * jnp.prod(self.size, -1) * e1 * e2 * jnp.exp(lb(e1 / 2 + 1, e1) + lb(e2 / 2, e2 / 2))

    def to_dict(self) -> dict:
        """Plain JSON-ready dict of one superquadric (see README, "models.json")."""
        r = np.asarray(self.rotation, float)
        return {
            "size": np.asarray(self.size, float).tolist(),
            "epsilon": np.asarray(self.epsilon, float).tolist(),
            "rotation": r.tolist(),
            "euler_zyz": np.asarray(self.euler, float).tolist(),
            "translation": np.asarray(self.translation, float).tolist(),
            "taper": np.asarray(self.taper, float).tolist(),
            "bend": np.asarray(self.bend, float).tolist(),
        }


# ----------------------------------------------------------------------------------------------------
# deformations (model frame)


def _safe_div(num, den):
    tiny = 1e-6 if den.dtype == jnp.float32 else 1e-12
    den = jnp.where(jnp.abs(den) < tiny, jnp.where(den < 0, -tiny, tiny), den)
    return num / den


def untaper(x, taper, a3):
    """Inverse tapering: deformed model-frame points (..., 3) -> undeformed."""
    kz = x[..., 2:3] / a3
    fx = taper[..., 0:1] * kz + 1.0
    fy = taper[..., 1:2] * kz + 1.0
    return jnp.concatenate([_safe_div(x[..., 0:1], fx), _safe_div(x[..., 1:2], fy), x[..., 2:3]], -1)


def taper_points(x, taper, a3):
    """Forward tapering of model-frame points (..., 3)."""
    kz = x[..., 2:3] / a3
    return jnp.concatenate(
        [x[..., 0:1] * (taper[..., 0:1] * kz + 1.0), x[..., 1:2] * (taper[..., 1:2] * kz + 1.0), x[..., 2:3]], -1
    )


def _atan_ratio(q):
    """atan(q) / q, with its series below |q| = 1e-2 (safe operand: no 0 / 0 in either branch)."""
    small = jnp.abs(q) < 1e-2
    qs = jnp.where(small, 1.0, q)
    q2 = q * q
    return jnp.where(small, 1.0 - q2 / 3.0 + q2 * q2 / 5.0, jnp.arctan(qs) / qs)


def unbend(x, bend):
    """Inverse bending (curvature k, angle alpha), exact for every k >= 0 and stable as k -> 0.

    The inverse of `bend_points`: with r the coordinate in the bending plane and w = 1 - k r, the
    bent angle is g = atan2(k Z, w) and z = g / k, written as z = (Z / w) atan(q) / q, q = k Z / w,
    while w > 0 (its series near q = 0 keeps every k, however small), plain atan2 / k beyond the
    bending centre; the in-plane shift is k Z^2 / (sqrt((k Z)^2 + w^2) + w). (..., 3) -> (..., 3).
    """
    k, alpha = bend[..., 0:1], bend[..., 1:2]
    ca, sa = jnp.cos(alpha), jnp.sin(alpha)
    X, Y, Z = x[..., 0:1], x[..., 1:2], x[..., 2:3]
    r = X * ca + Y * sa  # projection on the bending plane
    w = 1.0 - k * r
    kz = k * Z
    front = w > 0
    ws = jnp.where(front, w, 1.0)
    q = kz / ws
    ks = jnp.where(front, 1.0, k)  # k != 0 wherever w <= 0
    z = jnp.where(front, (Z / ws) * _atan_ratio(q), jnp.arctan2(kz, w) / ks)
    den = jnp.sqrt(kz * kz + w * w) + w
    tiny = 1e-12 if x.dtype == jnp.float32 else 1e-30
    shift = k * Z * Z / jnp.maximum(den, tiny)
    return jnp.concatenate([X - ca * shift, Y - sa * shift, z], -1)


def bend_points(x, bend):
    """Forward bending of model-frame points (..., 3) (Solina & Bajcsy), exact for every k >= 0.

    With g = k z: the in-plane offset (1/k - r)(1 - cos g) = (1 - k r) k z^2 (1 - cos g) / g^2 and
    the new z = (1 - k r) z sin(g) / g, through `jnp.sinc` (no threshold on k, no 0 / 0).
    """
    k, alpha = bend[..., 0:1], bend[..., 1:2]
    ca, sa = jnp.cos(alpha), jnp.sin(alpha)
    r = x[..., 0:1] * ca + x[..., 1:2] * sa
    z = x[..., 2:3]
    g = k * z
    one_m_kr = 1.0 - k * r
    half = jnp.sinc(g / (2 * jnp.pi))  # sin(g / 2) / (g / 2)
    dR = one_m_kr * k * z * z * 0.5 * half * half  # (1 - k r)(1 - cos g) / k
    Z = one_m_kr * z * jnp.sinc(g / jnp.pi)  # (1 - k r) sin(g) / k
    return jnp.concatenate([x[..., 0:1] + ca * dR, x[..., 1:2] + sa * dR, Z], -1)


@jax.jit
def to_model_frame(sq: Superquadric, points):
    """World points (..., 3) -> undeformed model-frame points (..., 3): R^T (p - t), unbend, untaper."""
    x = (points - sq.translation) @ sq.rotation
    x = unbend(x, sq.bend)
    return untaper(x, sq.taper, sq.size[..., 2:3])


@jax.jit
def to_world_frame(sq: Superquadric, x):
    """Undeformed model-frame points (..., 3) -> world points: taper, bend, R x + t."""
    x = taper_points(x, sq.taper, sq.size[..., 2:3])
    x = bend_points(x, sq.bend)
    return x @ jnp.swapaxes(sq.rotation, -1, -2) + sq.translation


# ----------------------------------------------------------------------------------------------------
# the inside-outside function and what is built on it


@jax.custom_jvp
def _logaddexp(a, b):
    """log(exp(a) + exp(b)) for finite a, b; its JVP reuses the forward exponential (no NaN, no overflow)."""
    return jnp.maximum(a, b) + jnp.log1p(jnp.exp(-jnp.abs(a - b)))


@_logaddexp.defjvp
def _logaddexp_jvp(primals, tangents):
    a, b = primals
    ta, tb = tangents
    q = jnp.exp(-jnp.abs(a - b))
    out = jnp.maximum(a, b) + jnp.log1p(q)
    w_big = 1.0 / (1.0 + q)  # weight of the larger argument, in [1/2, 1]
    wa = jnp.where(a >= b, w_big, 1.0 - w_big)
    return out, wa * ta + (1.0 - wa) * tb


def _ratio_floor(dtype) -> float:
    # |x / a| below this counts as this: its power is far below the rounding of F near the surface,
    # and 1 / |x| (and its square, in second derivatives) stays finite.
    return 1e-10 if jnp.dtype(dtype) == jnp.float32 else 1e-20


def _log_ratio(c, log_a):
    """log |c / a| on a safe operand: |c| floored at a tiny fraction of a before the logarithm."""
    thr = jnp.exp(log_a) * _ratio_floor(c.dtype)
    ac = jnp.abs(c)
    return jnp.log(jnp.where(ac > thr, ac, thr)) - log_a


def log_inside_outside_xyz(x, y, z, log_size, epsilon):
    """log F (eq. 5) of model-frame coordinates given as three arrays of one shape (the kernel form).

    `log_size[..., i]` and `epsilon[..., j]` broadcast against the coordinates. Two log-sum-exps of
    `(2 / e) (log|x| - log a)`, with `|x|` floored at a tiny fraction of `a` *before* the logarithm
    (a safe operand: no infinite derivative of any order), so values, gradients and Hessians are
    finite for every finite input; capped far outside the model.
    """
    e1, e2 = epsilon[..., 0], epsilon[..., 1]
    lx = _log_ratio(x, log_size[..., 0])
    ly = _log_ratio(y, log_size[..., 1])
    lz = _log_ratio(z, log_size[..., 2])
    s = _logaddexp(lx * (2.0 / e2), ly * (2.0 / e2))
    t = _logaddexp(s * (e2 / e1), lz * (2.0 / e1))
    return jnp.minimum(e1 * t, _log_cap(x.dtype))


def log_inside_outside_local(x, log_size, epsilon):
    """log F (eq. 5) of model-frame points x (..., 3), for log sizes (3,) and exponents (2,).

    `F = ((|x/a1|^(2/e2) + |y/a2|^(2/e2))^(e2/e1) + |z/a3|^(2/e1))^e1`, computed as two log-sum-exps.
    Finite with finite gradients for every finite input; capped at a value far outside any model.
    """
    return log_inside_outside_xyz(x[..., 0], x[..., 1], x[..., 2], log_size, epsilon)


def log_inside_outside_and_gradient(x, log_size, epsilon):
    """log F (eq. 5) of model-frame points x (..., 3), log |grad log F| (...) and the unit gradient
    (..., 3) (the outward normal direction, model frame), in closed form.

    `log_size` (..., 3) and `epsilon` (..., 2) broadcast against the points. With A, B, C the terms
    (2 / e2) log|x / a1|, (2 / e2) log|y / a2|, (2 / e1) log|z / a3|, s = lse(A, B) and
    t = lse(e2 / e1 s, C): d log F / dx = 2 w_t w_s / x, d / dy = 2 w_t (1 - w_s) / y,
    d / dz = 2 (1 - w_t) / z, with w the softmax weights of the two log-sum-exps. Everything stays in
    logs on the safe operand of `log_inside_outside_xyz`, so all three are finite at the centre, on
    the axes and far away. For kernels that need no autodiff (the eq. 10 distances of segmentation).
    """
    e1, e2 = epsilon[..., 0], epsilon[..., 1]
    lr = _log_ratio(x, log_size)
    A, B, C = lr[..., 0] * (2.0 / e2), lr[..., 1] * (2.0 / e2), lr[..., 2] * (2.0 / e1)
    s = jnp.logaddexp(A, B)
    u = s * (e2 / e1)
    t = jnp.logaddexp(u, C)
    log_g = jnp.stack([u - t + A - s, u - t + B - s, C - t], -1) - (lr + log_size) + jnp.log(2.0)
    log_gnorm = 0.5 * jax.scipy.special.logsumexp(2.0 * log_g, axis=-1)
    normal = jnp.where(x < 0, -1.0, 1.0) * jnp.exp(log_g - log_gnorm[..., None])
    return e1 * t, log_gnorm, normal


@jax.jit
def inside_outside(sq: Superquadric, points):
    """F of world points (..., 3) -> (...): < 1 inside, 1 on the surface, > 1 outside."""
    x = to_model_frame(sq, points)
    return jnp.exp(log_inside_outside_local(x, jnp.log(sq.size), sq.epsilon))


@jax.jit
def contains(sq: Superquadric, points):
    """Inside test, (..., 3) -> bool (...)."""
    x = to_model_frame(sq, points)
    return log_inside_outside_local(x, jnp.log(sq.size), sq.epsilon) <= 0.0


@jax.jit
def residual(sq: Superquadric, points):
    """Size-weighted residual f = sqrt(a1 a2 a3) (F - 1) (eq. 7), (..., 3) -> (...)."""
    x = to_model_frame(sq, points)
    log_a = jnp.log(sq.size)
    log_f = log_inside_outside_local(x, log_a, sq.epsilon)
    return jnp.exp(0.5 * jnp.sum(log_a, -1)) * jnp.expm1(log_f)


def _safe_norm(v):
    """|v| over the last axis, scaled by max |v_i| (no overflow or underflow of the squares), 0 at 0
    with a finite (zero) gradient there. The scale is a constant to autodiff (|v| = m |v / m| for any
    m), so no m^2 is formed in the gradient either."""
    m = jax.lax.stop_gradient(jnp.max(jnp.abs(v), -1, keepdims=True))
    nz = m > 0
    ms = jnp.where(nz, m, 1.0)
    s2 = jnp.sum((v / ms) ** 2, -1)
    return jnp.where(nz[..., 0], m[..., 0] * jnp.sqrt(jnp.where(nz[..., 0], s2, 1.0)), 0.0)


@jax.jit
def distance(sq: Superquadric, points):
    """Approximate Euclidean distance to the surface, |f| / ||grad_p f|| (eq. 10), (..., 3) -> (...).

    Exact on the surface to first order; meant for points near the model (growing, selection).
    Computed in the log domain, |F - 1| / |grad F| = |1 - 1 / F| / |grad log F|: no power of F is
    formed, the norm is scaled, log F is floored at -20 (float32; -40 float64: within ~1e-9 a of the
    centre, where eq. 10 means nothing anyway) and |grad log F| at 1e-18 (beyond the cap of F, far
    outside), so values and reverse-mode gradients are finite for every finite input.
    """
    log_a = jnp.log(sq.size)
    lo, gfloor = (-20.0, 1e-18) if points.dtype == jnp.float32 else (-40.0, 1e-150)

    def log_F(p):
        return log_inside_outside_local(to_model_frame(sq, p), log_a, sq.epsilon)

    flat = points.reshape(-1, 3)
    lf, g = jax.vmap(jax.value_and_grad(log_F))(flat)
    gn = _safe_norm(g)
    d = jnp.abs(jnp.expm1(-jnp.maximum(lf, lo))) / jnp.where(gn > gfloor, gn, gfloor)
    return d.reshape(points.shape[:-1])


def distance_from_log(log_f, log_grad_norm):
    """Signed first-order distance of the root form F^(1/2) to its level 1, from log F and log |grad log F|:
    (F^(1/2) - 1) / |grad F^(1/2)| = 2 (1 - F^(-1/2)) / |grad log F|, negative inside.

    Exact along the normal of a box's face and of a sphere, where F^(1/2) is linear in the distance
    (|z / a3|, |x| / a); eq. 10's (F - 1) / |grad F| is not (it halves distances far outside a face
    and inflates them inside, so a fit to it prefers models that are too small). log F is floored at
    -20 (float32; -40 float64: within ~1e-9 a of the centre), so the value stays finite."""
    lo = -20.0 if log_f.dtype == jnp.float32 else -40.0
    return -2.0 * jnp.expm1(-0.5 * jnp.maximum(log_f, lo)) * jnp.exp(-log_grad_norm)


def deformed_distance(x, log_size, epsilon, taper, bend):
    """Signed first-order distance (`distance_from_log`) of one rotated model-frame point x (3,) to a
    tapered and bent model, in the units of x.

    The distance is first found in the undeformed frame, d_u, then divided by the stretch of the
    undeforming map along the normal, |J^T n| (J its Jacobian at x, n the unit normal there): to first
    order the world distance is d_u / |grad_x d_u|. Without it a strong bend or taper squeezes the
    undeformed frame, and a fit could shrink its residuals below the noise by deforming (a flat sheet
    bent to k = 10^3 does)."""
    undeform = lambda q: untaper(unbend(q, bend), taper, jnp.exp(log_size[2:3]))
    u, pullback = jax.vjp(undeform, x)
    log_f, log_gn, normal = log_inside_outside_and_gradient(u, log_size, epsilon)
    (g,) = pullback(normal)
    stretch = jnp.sqrt(jnp.sum(g * g) + jnp.finfo(x.dtype).tiny)
    return distance_from_log(log_f, log_gn) / jnp.maximum(stretch, 1e-3)


@jax.jit
def signed_distance(sq: Superquadric, points):
    """The residual `fit` minimises (`FitOptions.residual="distance"`), (..., 3) -> (...): the signed
    first-order distance to the surface through the root form of F (`distance_from_log`), negative
    inside, in the units of the points; of a deformed model through `deformed_distance`. Closed-form
    gradient of log F: finite values and gradients for every finite input."""
    x = (points - sq.translation) @ sq.rotation
    batch = jnp.broadcast_shapes(x.shape[:-1], sq.size.shape[:-1])
    args = [
        jnp.broadcast_to(v, batch + v.shape[-1:]).reshape(-1, v.shape[-1])
        for v in (x, jnp.log(sq.size), sq.epsilon, sq.taper, sq.bend)
    ]
    return jax.vmap(deformed_distance)(*args).reshape(batch)


@jax.jit
def radial_distance(sq: Superquadric, points):
    """Distance along the ray from the model centre, |x| |1 - F^(-1/2)| in the model frame, (..., 3) -> (...).

    |x| is a scaled norm (no overflow of |x|^2 beyond 1.8e19 in float32)."""
    x = to_model_frame(sq, points)
    logF = log_inside_outside_local(x, jnp.log(sq.size), sq.epsilon)
    n = _safe_norm(x)
    return n * jnp.abs(-jnp.expm1(-0.5 * logF))


# ----------------------------------------------------------------------------------------------------
# surfaces (host side)


def _spow(c, e):
    return np.sign(c) * np.abs(c) ** e


def surface_grid(sq: Superquadric, resolution: int = 48):
    """Parametric surface points, numpy `(resolution, 2 * resolution, 3)` in world coordinates."""
    a = np.asarray(sq.size, float)
    e1, e2 = np.asarray(sq.epsilon, float)
    eta = np.linspace(-np.pi / 2, np.pi / 2, resolution)
    om = np.linspace(-np.pi, np.pi, 2 * resolution, endpoint=False)
    eta, om = np.meshgrid(eta, om, indexing="ij")
    c = np.cos(eta)
    c[[0, -1]] = 0.0  # exact poles, so the mesh closes
    ce, se = _spow(c, e1), _spow(np.sin(eta), e1)
    x = np.stack([a[0] * ce * _spow(np.cos(om), e2), a[1] * ce * _spow(np.sin(om), e2), a[2] * se], -1)
    return np.asarray(to_world_frame(sq, jnp.asarray(x, sq.size.dtype)), float)


def to_trimesh(sq: Superquadric, resolution: int = 48):
    """Closed triangle mesh of one superquadric (`trimesh.Trimesh`), world coordinates."""
    import trimesh

    g = surface_grid(sq, resolution)
    n_eta, n_om = g.shape[:2]
    verts = g.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_eta - 1), np.arange(n_om), indexing="ij")
    a = i * n_om + j
    b = i * n_om + (j + 1) % n_om
    c = (i + 1) * n_om + j
    d = (i + 1) * n_om + (j + 1) % n_om
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    mesh = trimesh.Trimesh(verts, faces, process=True)  # merges the pole vertices
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    mesh.fix_normals()
    return mesh


def sample_surface(sq: Superquadric, n: int, *, seed: int = 0, noise: float = 0.0, viewpoint=None):
    """`n` points (numpy `(n, 3)`) uniform by area on the surface, with Gaussian noise of std `noise`.

    Points are drawn on a fine mesh and moved along the ray from the model centre onto the exact surface
    (F = 1 up to rounding), so no chord error biases them inwards. With `viewpoint` (3,) only the side
    facing that point is sampled (one range-sensor view; self-occlusion of concave shapes is ignored).
    """
    import trimesh

    rng = np.random.default_rng(seed)
    mesh = to_trimesh(sq, 64)
    if viewpoint is not None:
        centres = mesh.triangles_center
        facing = np.einsum("ij,ij->i", mesh.face_normals, np.asarray(viewpoint, float) - centres) > 0
        mesh = mesh.submesh([np.nonzero(facing)[0]], append=True)
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(2**31)))  # pyright: ignore[reportAssignmentType]
    pts = np.asarray(_onto_surface(sq, jnp.asarray(pts, sq.size.dtype)), float)
    return pts + noise * rng.standard_normal((n, 3))


@jax.jit
def _onto_surface(sq: Superquadric, points):
    """Move world points along the ray from the centre (undeformed model frame) onto the surface F = 1."""
    x = to_model_frame(sq, points)
    log_f = log_inside_outside_local(x, jnp.log(sq.size), sq.epsilon)
    return to_world_frame(sq, x * jnp.exp(-0.5 * log_f)[..., None])
