"""The superquadric of the paper (section 2): parameters, the inside-outside function F (eq. 5), the
size-weighted residual (eq. 7) and the distance to the surface (eq. 10).

One core computes log F from the model-frame coordinates as two log-sum-exps (`_log_f_terms`); the
value (`log_inside_outside`), its gradient in closed form (`log_inside_outside_and_gradient`), eq. 7,
eq. 10 and the signed distance the fitter minimises are all built on it. Powers `|x / a| ** (2 / e)`
are evaluated in the log domain, `exp((2 / e) * (log|x| - log a))`, with `log|x|` taken of a safe
operand (|x| floored at a tiny fraction of a, `numerics.eps("ratio")`), so values and gradients are
finite for every finite input (at the centre, on the axes, far away, e down to 0.1). The public
functions of a `Superquadric` are jitted: called eagerly, each compiles once per input shape, and
inside another jit they are inlined. The core also runs in numpy (`xp=np`, float64) for the scene
renderer.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import rotation as so3
from .cache import kernel_jit
from .deformation import bend_points, taper_points, unbend, untaper
from .numerics import eps, is_real, to_device

EPSILON_RANGE = (0.1, 1.9)
"""Range the shape exponents e1, e2 are kept in."""


def _check_fields(dtype=jnp.float32, **fields):
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
    info = jnp.finfo(dtype)
    if "size" in vals and not np.all((vals["size"] >= info.tiny) & (vals["size"] <= info.max)):
        # below the smallest normal number a size is flushed to 0 on CPU (then log a = -inf)
        raise ValueError(
            f"Superquadric.create: size must lie in [{float(info.tiny):.3g}, {float(info.max):.3g}] in "
            f"{jnp.dtype(dtype).name}, got {vals['size'].tolist()}"
        )
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

        Concrete values are checked (a `ValueError` names the field): sizes finite and normal numbers of
        `dtype` (float32: 1.2e-38 .. 3.4e38), exponents
        finite and > 0, a rotation orthonormal with det +1 (to 1e-3), everything finite, taper in
        [-1, 1], bending curvature >= 0. Traced values (under jit / grad) are not checked.
        """
        _check_fields(
            dtype,
            size=size,
            epsilon=epsilon,
            rotation=rotation,
            euler=euler,
            translation=translation,
            taper=taper,
            bend=bend,
        )
        size = to_device(size, dtype)
        batch = size.shape[:-1]
        if rotation is None:
            rotation = so3.from_euler(to_device(euler if euler is not None else (0.0, 0.0, 0.0), dtype))
        f = lambda v, n: jnp.broadcast_to(to_device(v, dtype), batch + (n,))
        return cls(
            size,
            f(epsilon, 2),
            jnp.broadcast_to(to_device(rotation, dtype), batch + (3, 3)),
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

    def __getitem__(self, index) -> Superquadric:
        """The superquadric(s) at `index` of a batch (every field indexed along its batch axes, the
        leading axes of `size` but its last). Raises IndexError, as numpy does, for a single superquadric
        (no batch axis), for more indices than batch axes and for a concrete integer index out of range
        (JAX alone would clamp it and return the last model)."""
        batch = np.shape(self.size)[:-1]
        if not batch:
            raise IndexError("a single Superquadric has no batch axis to index (its size has shape (3,))")
        items = index if isinstance(index, tuple) else (index,)
        if len(items) > len(batch) or any(i is None or i is Ellipsis for i in items):
            raise IndexError(f"Superquadric: index {index!r} does not fit its batch shape {batch}")
        for i, n in zip(items, batch):
            if isinstance(i, jax.core.Tracer) or isinstance(i, slice):  # pyright: ignore[reportAttributeAccessIssue]
                continue
            i = np.asarray(i)
            if i.dtype.kind in "iu" and i.size and not (-n <= i.min() and i.max() < n):
                raise IndexError(f"Superquadric: index {i.tolist()} is out of range for a batch of {n}")
        return jax.tree.map(lambda v: v[index], self)

    def __len__(self) -> int:
        """The number of models along the first batch axis; a TypeError for a single superquadric."""
        batch = np.shape(self.size)[:-1]
        if not batch:
            raise TypeError("a single Superquadric has no len(): it is one model, not a batch")
        return batch[0]

    def __iter__(self):
        """The models along the first batch axis (`sq[0]`, `sq[1]`, ...), with numpy fields sliced from one
        transfer to the host; a TypeError for a single superquadric, which Python would otherwise iterate
        as empty (through `__getitem__`)."""
        n = len(self)
        host = jax.tree.map(np.asarray, self)
        return (jax.tree.map(lambda v, i=i: v[i], host) for i in range(n))

    def __bool__(self) -> bool:
        return True  # a model is a model: not "empty" through __len__

    def unbatch(self) -> list[Superquadric]:
        """A batched superquadric (fields `(K, ...)`) -> K single ones, whose fields are numpy slices of one
        transfer to the host (a device array per field and model would cost more than the rest of a
        segmentation's bookkeeping); a single one -> [it]."""
        if np.ndim(self.size) == 1:
            return [self]
        if np.ndim(self.size) != 2:
            raise ValueError(f"Superquadric.unbatch: expected one batch axis, got size of shape {np.shape(self.size)}")
        return list(self)

    @classmethod
    def from_dict(cls, d: dict) -> Superquadric:
        """A `Superquadric` from one entry of `models.json` `parts` (or `Superquadric.to_dict()` / `sqjax fit
        --json` output): `size`, `epsilon`, `rotation` (else `euler_zyz`), `translation`, `taper`, `bend`;
        other keys (label, colour, error, ...) are ignored."""
        if not isinstance(d, dict):
            raise ValueError(f"a superquadric must be a JSON object, got {type(d).__name__}")
        if "size" not in d:
            raise ValueError(f"a superquadric needs 'size' (keys: {', '.join(sorted(d)) or 'none'})")
        try:
            arr = {
                k: np.asarray(d[k], np.float64)
                for k in ("size", "epsilon", "rotation", "euler_zyz", "translation", "taper", "bend")
                if d.get(k) is not None
            }
        except (TypeError, ValueError) as e:
            raise ValueError(f"a superquadric's parameters must be numbers ({e})") from None
        shapes = {
            "size": (3,),
            "epsilon": (2,),
            "rotation": (3, 3),
            "euler_zyz": (3,),
            "translation": (3,),
            "taper": (2,),
            "bend": (2,),
        }
        for k, v in arr.items():
            if v.shape != shapes[k] or not np.isfinite(v).all():
                raise ValueError(f"superquadric '{k}' must be {shapes[k]} finite numbers, got {d[k]!r}")
        kw = {k: arr[k] for k in ("epsilon", "translation", "taper", "bend") if k in arr}
        if "rotation" in arr:
            kw["rotation"] = arr["rotation"]
        elif "euler_zyz" in arr:
            kw["euler"] = arr["euler_zyz"]
        return cls.create(arr["size"], **kw)


@kernel_jit
def to_model_frame(sq: Superquadric, points):
    """World points (..., 3) -> undeformed model-frame points (..., 3): R^T (p - t), unbend, untaper."""
    x = _rotate_into(points - sq.translation, sq.rotation)
    x = unbend(x, sq.bend)
    return untaper(x, sq.taper, sq.size[..., 2:3])


@kernel_jit
def to_world_frame(sq: Superquadric, x):
    """Undeformed model-frame points (..., 3) -> world points: taper, bend, R x + t."""
    return world_points(sq, x)


def world_points(sq: Superquadric, x, xp=jnp):
    """`to_world_frame` unjitted; with `xp=numpy` (and numpy fields) on the host, for meshes of any size."""
    x = taper_points(x, sq.taper, sq.size[..., 2:3], xp=xp)
    x = bend_points(x, sq.bend, xp=xp)
    return _rotate_into(x, xp.swapaxes(sq.rotation, -1, -2), xp) + sq.translation


def _rotate_into(v, R, xp=jnp):
    """R^T v of vectors v (..., 3) in the frame of rotations R (3, 3) or a batch (..., 3, 3) that
    broadcasts against them (a matrix product would pair a batch's vectors with every model); one
    model's is the matrix product it always was."""
    return v @ R if xp.ndim(R) == 2 else xp.einsum("...i,...ij->...j", v, R)


# ----------------------------------------------------------------------------------------------------
# eq. 5 and its gradient: one core


def _log_ratio(c, log_a, xp=jnp):
    """log |c / a| on a safe operand: |c| floored at a tiny fraction of a before the logarithm."""
    thr = xp.exp(log_a) * eps("ratio", c.dtype)
    ac = xp.abs(c)
    return xp.log(xp.where(ac > thr, ac, thr)) - log_a


def _log_f_terms(lr, e1, e2, xp=jnp):
    """The two log-sum-exps of eq. 5 from the log ratios lr (..., 3) = log |x_i / a_i| and the exponents.

    With A, B, C = (2 / e2) log|x / a1|, (2 / e2) log|y / a2|, (2 / e1) log|z / a3|: s = lse(A, B),
    u = (e2 / e1) s and t = lse(u, C), so that log F = e1 t. Returns (A, B, C, s, u, t). (The callers
    take e1, e2 out of epsilon once, so that autodiff sums each exponent's cotangents in one order.)"""
    A, B, C = lr[..., 0] * (2.0 / e2), lr[..., 1] * (2.0 / e2), lr[..., 2] * (2.0 / e1)
    s = xp.logaddexp(A, B)
    u = s * (e2 / e1)
    t = xp.logaddexp(u, C)
    return A, B, C, s, u, t


def log_inside_outside(x, log_size, epsilon, xp=jnp):
    """log F (eq. 5) of model-frame points x (..., 3); `log_size` (..., 3) and `epsilon` (..., 2)
    broadcast against them.

    `F = ((|x/a1|^(2/e2) + |y/a2|^(2/e2))^(e2/e1) + |z/a3|^(2/e1))^e1`, < 0 inside, 0 on the surface.
    Finite with finite gradients for every finite input; capped far outside the model
    (`numerics.eps("log_f_cap")`), so that (F - 1)^2 cannot overflow. `xp=np`: the same in numpy.
    """
    e1, e2 = epsilon[..., 0], epsilon[..., 1]
    _, _, _, _, _, t = _log_f_terms(_log_ratio(x, log_size, xp), e1, e2, xp)
    return xp.minimum(e1 * t, eps("log_f_cap", x.dtype))


def log_inside_outside_and_gradient(x, log_size, epsilon):
    """log F (eq. 5, not capped) of model-frame points x (..., 3), log |grad log F| (...) and the unit
    gradient (..., 3) (the outward normal, model frame), in closed form.

    With w the softmax weights of the two log-sum-exps of `_log_f_terms`: d log F / dx =
    2 w_t w_s / x, d / dy = 2 w_t (1 - w_s) / y, d / dz = 2 (1 - w_t) / z. Everything stays in logs on
    the safe operand of `_log_ratio`, so all three are finite at the centre, on the axes and far away.
    For kernels that need no autodiff of F itself (eq. 10 distances, the fitter's signed distance).
    """
    e1, e2 = epsilon[..., 0], epsilon[..., 1]
    lr = _log_ratio(x, log_size)
    A, B, C, s, u, t = _log_f_terms(lr, e1, e2)
    log_g = jnp.stack([u - t + A - s, u - t + B - s, C - t], -1) - (lr + log_size) + jnp.log(2.0)
    log_gnorm = 0.5 * jax.scipy.special.logsumexp(2.0 * log_g, axis=-1)
    normal = jnp.where(x < 0, -1.0, 1.0) * jnp.exp(log_g - log_gnorm[..., None])
    return e1 * t, log_gnorm, normal


def size_weighted_residual(log_f, log_size):
    """The paper's residual f = sqrt(a1 a2 a3) (F - 1) (eq. 7) from log F (...) and log sizes (..., 3)."""
    return jnp.exp(0.5 * jnp.sum(log_size, -1)) * jnp.expm1(log_f)


def distance_from_log(log_f, log_grad_norm):
    """Eq. 10, |F - 1| / |grad F| = |1 - 1 / F| / |grad log F|, from log F and log |grad log F|: no
    power of F is formed. Safe operands on both branches (|1 - 1 / F| in logs, inside and outside; 0
    on the surface), capped at e^30, so the value and its gradients are finite for every finite input.
    """
    lf = jnp.where(log_f == 0.0, 1e-30, log_f)  # safe operand: F = 1 gives d = 0 below
    log_num = jnp.where(
        lf < 0,
        -lf + jnp.log(-jnp.expm1(jnp.minimum(lf, -1e-30))),
        jnp.log(-jnp.expm1(-jnp.maximum(lf, 1e-30))),
    )  # log |1 - 1/F|
    return jnp.where(log_f == 0.0, 0.0, jnp.exp(jnp.minimum(log_num - log_grad_norm, 30.0)))


def signed_distance_from_log(log_f, log_grad_norm):
    """Signed first-order distance of the root form F^(1/2) to its level 1, from log F and
    log |grad log F|: (F^(1/2) - 1) / |grad F^(1/2)| = 2 (1 - F^(-1/2)) / |grad log F|, negative inside.

    Exact along the normal of a box's face and of a sphere, where F^(1/2) is linear in the distance
    (|z / a3|, |x| / a); eq. 10's (F - 1) / |grad F| is not (it halves distances far outside a face
    and inflates them inside, so a fit to it prefers models that are too small). log F is floored at
    `numerics.eps("log_f_floor")` (within ~1e-9 a of the centre), so the value stays finite."""
    lo = eps("log_f_floor", log_f.dtype)
    return -2.0 * jnp.expm1(-0.5 * jnp.maximum(log_f, lo)) * jnp.exp(-log_grad_norm)


def frame_distance(x, log_size, epsilon, taper, bend, of_logs=signed_distance_from_log):
    """A first-order distance (`of_logs`: `signed_distance_from_log` or eq. 10's `distance_from_log`)
    of one rotated model-frame point x (3,) to a model that may be tapered and bent, in the units of x.

    The distance is first found in the undeformed frame, d_u, then divided by the stretch of the
    undeforming map along the normal, |J^T n| (J its Jacobian at x, n the unit normal there): to first
    order the world distance is d_u / |grad_x d_u| (1 without deformation). Without it a strong bend
    or taper squeezes the undeformed frame, and a fit could shrink its residuals below the noise by
    deforming (a flat sheet bent to k = 10^3 does)."""
    undeform = lambda q: untaper(unbend(q, bend), taper, jnp.exp(log_size[2:3]))
    u, pullback = jax.vjp(undeform, x)
    log_f, log_gn, normal = log_inside_outside_and_gradient(u, log_size, epsilon)
    (g,) = pullback(normal)
    stretch = jnp.sqrt(jnp.sum(g * g) + jnp.finfo(x.dtype).tiny)
    return of_logs(log_f, log_gn) / jnp.maximum(stretch, 1e-3)


def _per_point(fn, sq: Superquadric, points):
    """`fn(x, log_size, epsilon, taper, bend)` of one rotated model-frame point, over points (..., 3)."""
    x = _rotate_into(points - sq.translation, sq.rotation)
    batch = jnp.broadcast_shapes(x.shape[:-1], sq.size.shape[:-1])
    args = [
        jnp.broadcast_to(v, batch + v.shape[-1:]).reshape(-1, v.shape[-1])
        for v in (x, jnp.log(sq.size), sq.epsilon, sq.taper, sq.bend)
    ]
    return jax.vmap(fn)(*args).reshape(batch)


# ----------------------------------------------------------------------------------------------------
# the public functions of a superquadric and world points (..., 3)


def _point_function(fn):
    """A public function of (sq, points) with its arguments checked first: points as an array (nested
    lists of rows too) of real numbers, shape (..., 3); errors that name the function and the problem
    instead of JAX's ("unsupported operand type(s) for -: 'list' and 'DynamicJaxprTracer'")."""
    name = getattr(fn, "__name__", "function")

    @functools.wraps(fn)
    def checked(sq, points):
        if not isinstance(sq, Superquadric):
            raise TypeError(f"{name}: the first argument must be a Superquadric, got {type(sq).__name__}")
        if not isinstance(points, jax.Array):
            try:
                points = np.asarray(points)
            except ValueError as err:  # ragged rows
                raise ValueError(f"{name}: points must be an array of shape (..., 3): {err}") from None
            if not is_real(points.dtype):
                raise ValueError(f"{name}: points must be real numbers, got dtype {points.dtype}")
        if points.ndim == 0 or points.shape[-1] != 3:
            raise ValueError(f"{name}: points must have shape (..., 3), got {tuple(points.shape)}")
        batch = np.shape(sq.size)[:-1]
        try:
            np.broadcast_shapes(tuple(points.shape[:-1]), batch)
        except ValueError:
            raise ValueError(
                f"{name}: points of shape {tuple(points.shape)} do not broadcast against a batch of "
                f"superquadrics of shape {batch}: points (..., 3) pair with the batch along their last "
                f"axes before the 3 (each model's own N points: shape (N, {', '.join(map(str, batch))}, 3)), "
                "or take one model, sq[i]"
            ) from None
        return fn(sq, points)

    return checked


@kernel_jit
def _missing(points, value):
    """`value` (...) with NaN where a point (..., 3) has a NaN or infinite coordinate: a missing point has
    no F and no distance (the safe operands inside would give it a finite one, 2e-20 "inside")."""
    return jnp.where(_nonfinite(points), jnp.nan, value)


def _nonfinite(points):
    return ~jnp.all(jnp.isfinite(points), -1)


@_point_function
def inside_outside(sq: Superquadric, points):
    """F of world points (..., 3) -> (...): < 1 inside, 1 on the surface, > 1 outside (eq. 5); NaN for
    a point with a NaN or infinite coordinate."""
    x = to_model_frame(sq, points)
    return _missing(points, jnp.exp(log_inside_outside(x, jnp.log(sq.size), sq.epsilon)))


@_point_function
@kernel_jit
def contains(sq: Superquadric, points):
    """Inside test, (..., 3) -> bool (...); False for a point with a NaN or infinite coordinate."""
    x = to_model_frame(sq, points)
    return (log_inside_outside(x, jnp.log(sq.size), sq.epsilon) <= 0.0) & ~_nonfinite(points)


@_point_function
@kernel_jit
def residual(sq: Superquadric, points):
    """Size-weighted residual f = sqrt(a1 a2 a3) (F - 1) (eq. 7), (..., 3) -> (...); NaN for a point
    with a NaN or infinite coordinate."""
    log_a = jnp.log(sq.size)
    f = size_weighted_residual(log_inside_outside(to_model_frame(sq, points), log_a, sq.epsilon), log_a)
    return _missing(points, f)


@_point_function
@kernel_jit
def distance(sq: Superquadric, points):
    """Approximate Euclidean distance to the surface, |F - 1| / |grad F| (eq. 10), (..., 3) -> (...).

    Exact on the surface to first order; meant for points near the model (growing, selection). In
    closed form (`distance_from_log`), through the stretch of the deformations (`frame_distance`);
    values and reverse-mode gradients are finite for every finite input."""
    return _missing(points, _per_point(lambda *a: frame_distance(*a, of_logs=distance_from_log), sq, points))


@_point_function
@kernel_jit
def signed_distance(sq: Superquadric, points):
    """The residual `fit` minimises (`FitOptions.residual="distance"`), (..., 3) -> (...): the signed
    first-order distance to the surface through the root form of F (`signed_distance_from_log`),
    negative inside, in the units of the points. Closed-form gradient of log F: finite values and
    gradients for every finite input."""
    return _missing(points, _per_point(frame_distance, sq, points))


def _safe_norm(v):
    """|v| over the last axis, scaled by max |v_i| (no overflow or underflow of the squares), 0 at 0
    with a finite (zero) gradient there. The scale is a constant to autodiff (|v| = m |v / m| for any
    m), so no m^2 is formed in the gradient either."""
    m = jax.lax.stop_gradient(jnp.max(jnp.abs(v), -1, keepdims=True))
    nz = m > 0
    ms = jnp.where(nz, m, 1.0)
    s2 = jnp.sum((v / ms) ** 2, -1)
    return jnp.where(nz[..., 0], m[..., 0] * jnp.sqrt(jnp.where(nz[..., 0], s2, 1.0)), 0.0)


@_point_function
@kernel_jit
def radial_distance(sq: Superquadric, points):
    """Distance along the ray from the model centre, |x| |1 - F^(-1/2)| in the model frame, (..., 3) -> (...).

    |x| is a scaled norm (no overflow of |x|^2 beyond 1.8e19 in float32)."""
    x = to_model_frame(sq, points)
    logF = log_inside_outside(x, jnp.log(sq.size), sq.epsilon)
    return _missing(points, _safe_norm(x) * jnp.abs(-jnp.expm1(-0.5 * logF)))
