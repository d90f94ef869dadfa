"""Global deformations of a superquadric's model frame (Solina & Bajcsy 1990): tapering along z
(Kx, Ky) and bending (curvature k, angle alpha), forward and inverse, exact and finite for every
parameter in range. Pure `jax.numpy` on points `(..., 3)`.

The paper's experiments use none; `FitOptions.deform` fits them and keeps them only where they pay.
"""

from __future__ import annotations

import jax.numpy as jnp

from .numerics import eps


def _safe_div(num, den):
    tiny = eps("divisor", den.dtype)
    den = jnp.where(jnp.abs(den) < tiny, jnp.where(den < 0, -tiny, tiny), den)
    return num / den


def untaper(x, taper, a3):
    """Inverse tapering: deformed model-frame points (..., 3) -> undeformed."""
    kz = x[..., 2:3] / a3
    fx = taper[..., 0:1] * kz + 1.0
    fy = taper[..., 1:2] * kz + 1.0
    return jnp.concatenate([_safe_div(x[..., 0:1], fx), _safe_div(x[..., 1:2], fy), x[..., 2:3]], -1)


def taper_points(x, taper, a3, xp=jnp):
    """Forward tapering of model-frame points (..., 3) (`xp=numpy` for host meshes)."""
    kz = x[..., 2:3] / a3
    return xp.concatenate(
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
    shift = k * Z * Z / jnp.maximum(den, eps("bend", x.dtype))
    return jnp.concatenate([X - ca * shift, Y - sa * shift, z], -1)


def max_curvature(log_size, e2, taper, alpha, xp=jnp):
    """The largest bending curvature k (...,) that keeps a model one-to-one: its valid range is
    0 <= k <= `max_curvature`, from log half-sizes (..., 3), the exponent e2 (...,), the tapering
    (..., 2) and the bending angle alpha (...,).

    Bending moves a point at distance r along the bending plane onto a circle of radius 1/k - r
    (`bend_points`): the solid folds onto itself where k r reaches 1, so k r_max < 1, r_max being the
    farthest reach of the tapered cross-section towards the bending plane; and its two ends pass each
    other where the bent angle k a3 reaches pi. The cross-section |x / a1|^(2/e2) + |y / a2|^(2/e2) <= 1
    reaches r_max = (|a1 cos alpha|^p + |a2 sin alpha|^p)^(1/p) in the direction alpha (its support
    function, the dual norm: p = 2 / (2 - e2)); with tapering, a1 (1 + |Kx|) and a2 (1 + |Ky|) stand for
    a1 and a2, the widest tapered extents taken together: an upper bound of the reach (tight without
    tapering), so that within the range the solid never folds. Beyond it the fitted "bend" is another
    shape: k -> inf sweeps the cross-section round an axis (a solid of revolution), which fits a ring
    or a curved limb better than any bent superquadric does."""
    a = xp.exp(log_size)
    # e2 >= 2 (a star-shaped cross-section) reaches farthest at a vertex on an axis: the max, which
    # p = 100 gives within 1% from above (p stays finite for any e2 a user's epsilon_range allows)
    p = 2.0 / (2.0 - xp.minimum(e2, 1.98))
    tiny = xp.finfo(a.dtype).tiny
    u = xp.abs(a[..., 0] * (1.0 + xp.abs(taper[..., 0])) * xp.cos(alpha)) + tiny
    v = xp.abs(a[..., 1] * (1.0 + xp.abs(taper[..., 1])) * xp.sin(alpha)) + tiny
    big = xp.maximum(u, v)  # scaled out: (u / big)^p <= 1, no overflow for any p
    reach = big * ((u / big) ** p + (v / big) ** p) ** (1.0 / p)
    return xp.minimum(1.0 / reach, xp.pi / a[..., 2])


def bend_points(x, bend, xp=jnp):
    """Forward bending of model-frame points (..., 3) (Solina & Bajcsy), exact for every k >= 0.

    With g = k z: the in-plane offset (1/k - r)(1 - cos g) = (1 - k r) k z^2 (1 - cos g) / g^2 and
    the new z = (1 - k r) z sin(g) / g, through `sinc` (no threshold on k, no 0 / 0). `xp=numpy` for
    host meshes.
    """
    k, alpha = bend[..., 0:1], bend[..., 1:2]
    ca, sa = xp.cos(alpha), xp.sin(alpha)
    r = x[..., 0:1] * ca + x[..., 1:2] * sa
    z = x[..., 2:3]
    g = k * z
    one_m_kr = 1.0 - k * r
    half = xp.sinc(g / (2 * xp.pi))  # sin(g / 2) / (g / 2)
    dR = one_m_kr * k * z * z * 0.5 * half * half  # (1 - k r)(1 - cos g) / k
    Z = one_m_kr * z * xp.sinc(g / xp.pi)  # (1 - k r) sin(g) / k
    return xp.concatenate([x[..., 0:1] + ca * dR, x[..., 1:2] + sa * dR, Z], -1)
