"""The Levenberg–Marquardt recovery of one superquadric (Solina & Bajcsy), as the fitter runs it.

Pure `jax.numpy` on one problem: points (3, N) in normalised coordinates with a mask (N,), an LM state
(log a, e, R, t, d) (`chart.unpack`). The residual of each point (`residual_point`, see
`FitOptions.residual`) and its derivatives come from autodiff of a per-point function in the model
frame (coordinates held as three (N,) arrays so that XLA vectorises over points); the pose columns of
the Jacobian are chained by hand (translation: g, rotation: g x x), and J^T J is one (P, N) @ (N, P)
product. `levenberg_marquardt` runs a fixed number of steps (shape-stable under jit and vmap).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from . import rotation as so3
from .chart import DEFORMATION, EPSILON, LOG_SIZE, ROTATION, TRANSLATION, clip_deformation
from .deformation import unbend, untaper
from .superquadric import (
    frame_distance,
    log_inside_outside,
    log_inside_outside_and_gradient,
    signed_distance_from_log,
    size_weighted_residual,
)


def _log_f_point(x, y, z, la, e, d, deform: bool):
    """log F (eq. 5) of one model-frame point (x, y, z), undeformed first when `deform`."""
    p = jnp.stack([x, y, z])
    if deform:
        p = untaper(unbend(p, d[2:4]), d[0:2], jnp.exp(la[2:3]))
    return log_inside_outside(p, la, e)


def residual_point(x, y, z, la, e, d, deform: bool, kind: str = "distance"):
    """The residual of one model-frame point (x, y, z), see `FitOptions.residual`.

    `"distance"`: the signed first-order distance of the root form F^(1/2),
    (F^(1/2) - 1) / |grad F^(1/2)| = 2 (1 - F^(-1/2)) / |grad log F|, exact on the faces of a box and
    on a sphere (inside and outside); `"size_weighted"`: the paper's f = sqrt(a1 a2 a3) (F - 1) (eq. 7).
    """
    if kind == "size_weighted":
        return size_weighted_residual(_log_f_point(x, y, z, la, e, d, deform), la)
    p = jnp.stack([x, y, z])
    if deform:  # the distance in the undeformed frame over the stretch of the undeforming map
        return frame_distance(p, la, e, d[0:2], d[2:4])
    lf, log_gn, _ = log_inside_outside_and_gradient(p, la, e)
    return signed_distance_from_log(lf, log_gn)


def model_frame(state, points):
    """points (3, N) world -> model-frame coordinates x, y, z, each (N,)."""
    _, _, R, t, _ = state
    x = R.T @ (points - t[:, None])
    return x[0], x[1], x[2]


def point_fn(opts, argnums=None):
    """The per-point residual of `opts` vmapped over points x, y, z (N,) (shape parameters shared):
    (x, y, z, la, e, d) -> r (N,); with `argnums`, -> (r, gradients with respect to those arguments)."""
    f = functools.partial(residual_point, deform=opts.deform, kind=opts.residual)
    g = f if argnums is None else jax.value_and_grad(f, argnums=argnums)
    return jax.vmap(g, in_axes=(0, 0, 0, None, None, None))


def _normal_equations(state, points, mask, opts, weight=None):
    """Cost, J^T J and J^T r in the local chart [dla, de, dw (rotation), du (model-frame shift), dd].

    `points` is `(3, N)`, `mask` `(N,)`. One vmapped reverse-mode pass gives the residual and its
    gradient with respect to the model-frame point and the shape parameters; the pose columns follow
    from the chain rule (x' = exp(-dw) (x + du)).
    """
    la, e, _, _, d = state
    x, y, z = model_frame(state, points)
    argnums = (0, 1, 2, 3, 4, 5) if opts.deform else (0, 1, 2, 3, 4)
    r, grads = point_fn(opts, argnums)(x, y, z, la, e, d)
    gx, gy, gz, gla, ge = grads[:5]
    rows = [
        gla[:, 0],
        gla[:, 1],
        gla[:, 2],
        ge[:, 0],
        ge[:, 1],
        gy * z - gz * y,
        gz * x - gx * z,
        gx * y - gy * x,  # rotation: g x x
        gx,
        gy,
        gz,
    ]  # model-frame shift
    if opts.deform:
        rows += [grads[5][:, i] for i in range(4)]
    w = mask.astype(points.dtype) if weight is None else jnp.where(mask, jnp.sqrt(weight), 0.0)
    J = jnp.stack(rows) * w
    r = r * w
    return jnp.sum(r * r), J @ J.T, J @ r


def cost_of(state, points, mask, opts, weight=None):
    la, e, _, _, d = state
    x, y, z = model_frame(state, points)
    r: jax.Array = point_fn(opts)(x, y, z, la, e, d)  # pyright: ignore[reportAssignmentType]  (no argnums)
    r2 = r * r if weight is None else weight * r * r
    return jnp.sum(jnp.where(mask, r2, 0.0))


def point_distances(state, points, mask, opts):
    """First-order distance |r| / |grad_x r| of every point (N,) (eq. 10 for the size-weighted residual),
    in the units of `points` (0 where masked)."""
    la, e, _, _, d = state
    x, y, z = model_frame(state, points)
    r, (gx, gy, gz) = point_fn(opts, (0, 1, 2))(x, y, z, la, e, d)
    fin = jnp.finfo(points.dtype)
    g = jnp.sqrt(gx * gx + gy * gy + gz * gz)
    dist = jnp.minimum(jnp.abs(r) / jnp.maximum(g, jnp.sqrt(fin.tiny)), fin.max**0.25)
    return jnp.where(mask, dist, 0.0)


_LM_LAMBDA0, _LM_DOWN, _LM_UP = 1e-2, 0.3, 4.0
"""Initial damping (relative to diag J^T J) and its factors after a kept / a rejected step."""


def _damped_solve(A, b):
    """Solve the damped normal equations (symmetric positive definite) by Cholesky; NaN if not PD."""
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A), b)


def _log_size_bound(R, t, points, mask):
    """Largest log half-sizes (3,) of a model with pose (R, t) over points (3, N): the farthest point
    along each model axis, times 1 + 2 / sqrt(n) (about a point spacing; see `FitOptions.residual`)."""
    loc = R.T @ (points - t[:, None])
    n = jnp.maximum(jnp.sum(mask), 1).astype(points.dtype)
    far = jnp.max(jnp.where(mask[None], jnp.abs(loc), 0.0), axis=1)
    return jnp.log(far * (1.0 + 2.0 / jnp.sqrt(n)) + jnp.finfo(points.dtype).tiny)


def capped(la, R, t, points, mask, opts):
    """Log half-sizes la (3,) within `_log_size_bound` at pose (R, t) where `opts.size_bound` holds."""
    if opts.size_bound is False:
        return la
    return jnp.where(opts.size_bound, jnp.minimum(la, _log_size_bound(R, t, points, mask)), la)


def _bounded(state, points, mask, opts):
    """`state` with its sizes within `_log_size_bound` at its own pose (with `opts.size_bound`) and its
    deformation in its valid range (a start too: bent starts are estimated, not fitted)."""
    la, e, R, t, d = state
    la = capped(la, R, t, points, mask, opts)
    return la, e, R, t, (clip_deformation(d, la, e) if opts.deform else d)


def _retract(state, step, opts):
    la, e, R, t, d = state
    lo, hi = opts.epsilon_range
    la = la + jnp.clip(step[LOG_SIZE], -1.0, 1.0)
    e = jnp.clip(e + step[EPSILON], lo, hi)
    t = t - R @ step[TRANSLATION]
    R = R @ so3.exp(step[ROTATION])
    if opts.deform:
        d = d + step[DEFORMATION]
        d = d.at[3].set(jnp.remainder(d[3] + jnp.pi, 2 * jnp.pi) - jnp.pi)  # periodic; the range: `_bounded`
    return la, e, R, t, d


def levenberg_marquardt(state, points, mask, opts, num_steps, weight=None):
    """Fixed-step LM from `state`; returns (state, cost, converged). One residual+Jacobian pass a step.

    Marquardt's scaling (damping proportional to diag J^T J) makes the step invariant to the units of
    each parameter; a trial is kept only if it lowers the cost, and the damping falls after a kept step
    and rises after a rejected one. The loop evaluates a pending trial per iteration (the start itself
    first, against an infinite cost), so the residual and its Jacobian appear once in the program.
    """
    dtype = points.dtype
    P = opts.num_params
    tiny = jnp.finfo(dtype).tiny

    def body(_, carry):
        state, cost, JTJ, JTr, lam, rel, trial = carry
        ncost, nJTJ, nJTr = _normal_equations(trial, points, mask, opts, weight)
        ok = jnp.isfinite(ncost) & (ncost < cost)
        rel = jnp.where(ok & jnp.isfinite(cost), (cost - ncost) / jnp.maximum(cost, tiny), jnp.where(ok, 1.0, 0.0))
        lam = jnp.where(jnp.isfinite(cost), jnp.clip(jnp.where(ok, lam * _LM_DOWN, lam * _LM_UP), 1e-9, 1e9), lam)
        pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(ok, u, v), a, b)
        state, cost, JTJ, JTr = pick((trial, ncost, nJTJ, nJTr), (state, cost, JTJ, JTr))
        diag = jnp.diagonal(JTJ)
        damp = lam * (diag + 1e-9 * jnp.max(diag) + tiny)
        step = _damped_solve(JTJ + jnp.diag(damp), -JTr)
        step = jnp.where(jnp.isfinite(step), step, 0.0)
        return state, cost, JTJ, JTr, lam, rel, _bounded(_retract(state, step, opts), points, mask, opts)

    zeros = jnp.zeros((P, P), dtype)
    init = (
        state,
        jnp.asarray(jnp.inf, dtype),
        zeros,
        zeros[0],
        jnp.asarray(_LM_LAMBDA0, dtype),
        jnp.asarray(1.0, dtype),
        _bounded(state, points, mask, opts),
    )
    state, cost, _, _, lam, rel, _ = jax.lax.fori_loop(0, num_steps + 1, body, init)
    # Converged: the last steps stopped paying (a rejected step with a large damping, or a tiny gain).
    converged = jnp.isfinite(cost) & ((rel < 1e-4) | (lam > 1e3))
    return state, cost, converged
