"""Recovery of superquadrics (Solina & Bajcsy): batched Levenberg–Marquardt on each point's distance to
the surface (or, as an option, the paper's size-weighted residual, eq. 7; see `FitOptions.residual`).

One jit-compiled call fits K padded point sets `(K, N, 3)` with masks `(K, N)`, every problem and every
starting candidate side by side (`jax.vmap`), for a fixed number of LM steps. The residual and
its derivatives come from autodiff of the per-point function in the model frame (`jax.value_and_grad`,
coordinates held as three `(N,)` arrays so that XLA vectorises over points); the pose is chained by
hand (translation: `g`, rotation: `g x x`) and J^T J is one `(P, N) @ (N, P)` product. Problems are
processed a few at a time (`lax.map` over chunks of the batch) so that the points and every
intermediate stay in cache through all LM steps. Gradients of the fitted parameters with respect
to the points use the implicit function theorem at the optimum (`optimistix.ImplicitAdjoint`), never
differentiation through the iterations.
"""

from __future__ import annotations

import dataclasses
import enum
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from . import rotation as so3
from .cache import persistent_kernel
from .superquadric import (
    EPSILON_RANGE,
    Superquadric,
    deformed_distance,
    distance,
    distance_from_log,
    log_inside_outside_and_gradient,
    log_inside_outside_xyz,
    unbend,
    untaper,
)

MIN_POINTS = 11
"""Fewest valid points a problem may have (one per parameter)."""

RESIDUALS = ("distance", "size_weighted")
"""What LM minimises (see `FitOptions.residual`)."""

STARTS = ("moments", "rim", "quadric")
"""Initial-estimate families, each giving three axis assignments (see `FitOptions.starts`)."""


class FitOptions(eqx.Module):
    """How the Levenberg–Marquardt recovery runs; every field is static (a compile-cache key).

    - `max_steps`: LM steps per candidate (the paper: ~15 suffice). The switched candidates get half.
    - `multistart`: start from every family in `starts` (three axis assignments each) and every pair in
      `epsilon_starts`, then try the two "switched" solutions (EMS) of the best; keep the lowest cost.
      Without it only the first moment ellipsoid is used. Ignored when `init` is given.
    - `starts`: initial-estimate families: `"moments"` (central second moments, the paper's start),
      `"rim"` (one-view hypothesis: the centre lies behind the visible surface, at the rim end of the
      least-spread moment axis), `"quadric"` (centre and axes of an algebraic least-squares quadric).
    - `epsilon_starts`: starting exponent pairs (e1, e2); the paper starts from the ellipsoid (1, 1).
    - `screen_points`: the multistart stages run on this many of the points (evenly strided), then the
      winner takes `max_steps // 2` more steps on all of them; `None` runs every stage on all points.
    - `deform`: also fit tapering (Kx, Ky) and bending (k, alpha), kept only where they pay: the
      undeformed model is fitted too, the deformed one also from its optimum (nested models), and
      the 4 parameters stay only if the description gets shorter (BIC, `_deformation_pays`); else
      the result is the undeformed fit with zero deformation. The residual of a deformed model is
      its distance in world units (`superquadric.deformed_distance`). Measured (`benchmarks/fit.py
      --suites deform`, 100 problems each, 2026-12-02): undeformed views |taper| < 0.05 in 97% of
      fits, k a < 0.05 in 99%, none on a bound (before both changes: 50%, 66%, 9%); tapered truths
      median IoU 0.971, bent 0.964 (before: 0.903, 0.900; gross failures 38% -> 2%, 25% -> 5%).
    - `epsilon_range`: bounds of the exponents e1, e2 (projection after each step).
    - `residual`: what LM minimises the squares of. `"distance"` (default): each point's signed
      first-order distance to the surface through the root form of F (`_residual_point`), so every
      face weighs its points' errors alike. `"size_weighted"`: the paper's eq. 7,
      f = sqrt(a1 a2 a3) (F - 1). Near a face normal to axis i, f ~ 2 sqrt(a1 a2 a3) / a_i times the
      distance: the errors on the broad face of a slab cost less as the slab thickens, so a slab seen
      face-on comes out 1.5-2.6x too thick with a cost 30-50% below the truth's (issue 14), and a
      table top explains a third of its points. Measured on the same problems (`benchmarks/fit.py`):
      see RESULTS.md.
    - `size_bound`: bound each half-size of the model by the farthest point along that axis (times
      1 + 2 / sqrt(n), about a point spacing): one view of a centrally symmetric solid holds one of
      the two extreme points of every axis, and without the bound the distance residual explains an
      open surface (a table) by a sheet of any lateral size. On in `fit()`; off in segmentation,
      whose growth step finds a part's extent by admitting the points a model extrapolates to (a
      model that hugs its region never grows across an exactly planar surface). A Python bool is
      compiled in; a boolean array scalar (`np.asarray(True)`) is traced, so bounded and unbounded
      fits share one compiled kernel (segmentation's refits do: `_Runner.fit`).
    - `robust`: after the least-squares fit, `robust_rounds` rounds of iteratively reweighted LM
      (`max_steps // 2` steps each, all points): Tukey's biweight of each point's eq. 10 distance d
      with the scale from the data, `w = (1 - (d / (c s))^2)^2` for d < c s, else 0, c = 4.685,
      s = 1.4826 median(d) (the MAD about the surface, floored at 1e-4 of the rms radius of the points).
      The weights multiply the squared residuals (eq. 9) of the next round and are returned in
      `Fit.weight`. Off by default (the segmentation's kernel calls and `fit()`).
    """

    max_steps: int = eqx.field(static=True, default=15)
    multistart: bool = eqx.field(static=True, default=True)
    starts: tuple[str, ...] = eqx.field(static=True, default=STARTS)
    epsilon_starts: tuple[tuple[float, float], ...] = eqx.field(static=True, default=((1.0, 1.0), (1.6, 1.6)))
    screen_points: int | None = eqx.field(static=True, default=256)
    deform: bool = eqx.field(static=True, default=False)
    epsilon_range: tuple[float, float] = eqx.field(static=True, default=EPSILON_RANGE)
    robust: bool = eqx.field(static=True, default=False)
    residual: str = eqx.field(static=True, default="distance")
    size_bound: bool | jax.Array | np.ndarray = True
    robust_rounds: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if int(self.max_steps) < 1:
            raise ValueError(f"FitOptions.max_steps must be >= 1, got {self.max_steps}")
        unknown = set(self.starts) - set(STARTS)
        if not self.starts or unknown:
            raise ValueError(f"FitOptions.starts must be a non-empty subset of {STARTS}, got {self.starts}")
        lo, hi = self.epsilon_range
        if not 0.0 < lo < hi:
            raise ValueError(f"FitOptions.epsilon_range must satisfy 0 < lo < hi, got {self.epsilon_range}")
        if self.screen_points is not None and int(self.screen_points) < 4 * MIN_POINTS:
            raise ValueError(f"FitOptions.screen_points must be None or >= {4 * MIN_POINTS}, got {self.screen_points}")
        if self.residual not in RESIDUALS:
            raise ValueError(f"FitOptions.residual must be one of {RESIDUALS}, got {self.residual!r}")
        if int(self.robust_rounds) < 1:
            raise ValueError(f"FitOptions.robust_rounds must be >= 1, got {self.robust_rounds}")
        if not isinstance(self.size_bound, bool) and (
            jnp.shape(self.size_bound) != () or jnp.result_type(self.size_bound) != jnp.bool_
        ):
            raise ValueError(f"FitOptions.size_bound must be a bool or a boolean scalar array, got {self.size_bound!r}")
        if not self.epsilon_starts or any(len(e) != 2 for e in self.epsilon_starts):
            raise ValueError(f"FitOptions.epsilon_starts must be pairs (e1, e2), got {self.epsilon_starts}")

    @property
    def num_params(self) -> int:
        return 15 if self.deform else 11

    @property
    def num_candidates(self) -> int:
        """Starting candidates per problem in the first stage (without `init`)."""
        return 3 * len(self.starts) * len(self.epsilon_starts) if self.multistart else 1

    def point_iterations(self, n: int) -> int:
        """Residual-and-Jacobian evaluations of one problem padded to `n` points (points x steps x candidates)."""
        if not self.multistart:
            return (self.max_steps + 1) * n
        half = max(self.max_steps // 2, 1)
        m = n if self.screen_points is None else min(n, self.screen_points)
        screen = (self.num_candidates * (self.max_steps + 1) + 2 * (half + 1)) * m
        return screen + ((half + 1) * n if m < n else 0)


class Status(enum.IntFlag):
    """Quality flags of one fit, combined bitwise in `Fit.status` (0 = `OK`). Data, never an exception.

    - `MAX_STEPS`: the last LM steps still lowered the cost (not converged in `max_steps`).
    - `BOUND_ACTIVE`: an exponent (or a tapering / bending parameter) sits on its bound.
    - `LARGE_RESIDUAL`: the median eq. 10 distance exceeds 3x the given `noise` (without one: 2 % of
      the mean size of the model).
    - `DEGENERATE`: the points are identical or collinear, or the warm start is not finite / positive.
    - `TOO_FEW_POINTS`: fewer than `MIN_POINTS` valid points (only under tracing; on the host it raises).
    - `NONFINITE`: the cost or a parameter came out non-finite (replaced by the start).
    - `FAR_POINTS`: points farther than `far_factor` x the median radius from the median centre were
      dropped (a depth pixel at 1e30, say); their weight is 0.
    """

    OK = 0
    MAX_STEPS = 1
    BOUND_ACTIVE = 2
    LARGE_RESIDUAL = 4
    DEGENERATE = 8
    TOO_FEW_POINTS = 16
    NONFINITE = 32
    FAR_POINTS = 64

    @classmethod
    def describe(cls, code) -> str:
        """Human-readable names of the flags set in one status code, e.g. "MAX_STEPS|BOUND_ACTIVE"."""
        code = int(code)
        return "OK" if code == 0 else "|".join(f.name for f in cls if f.value and code & f.value)  # pyright: ignore[reportCallIssue, reportArgumentType]  (members have names)


_FAILED = Status.DEGENERATE | Status.TOO_FEW_POINTS | Status.NONFINITE
"""Flags under which `converged` is False whatever the LM steps did."""


class Fit(eqx.Module):
    """Result of `fit`. Leading axis K present when the input was batched.

    - `superquadric`: the recovered models (sizes and translation in the units of the points).
    - `cost`: `(K,)` G = sum of squared residuals (`FitOptions.residual`: distances by default, in squared
      units of the points; eq. 9 with `"size_weighted"`), each times its `weight`.
    - `distance`: `(K, N)` eq. 10 distance of every point to its model (0 where masked out).
    - `converged`: `(K,)` bool, the last LM steps no longer reduced the cost (relative 1e-4), all is
      finite and the input was not degenerate (see `status`).
    - `num_points`: `(K,)` valid points used.
    - `weight`: `(K, N)` robust weight of every point in [0, 1] (0: treated as an outlier or masked
      out; all 1 without `robust`).
    - `status`: `(K,)` int32, `Status` flags (0 = OK); `Status.describe(code)` names them.
    """

    superquadric: Superquadric
    cost: jax.Array
    distance: jax.Array
    converged: jax.Array
    num_points: jax.Array
    weight: jax.Array
    status: jax.Array


# ----------------------------------------------------------------------------------------------------
# parameters: the global chart theta = [log a (3), e (2), rotation vector (3), t (3), (Kx, Ky, k, alpha)]
# and the LM state (log a, e, R, t, d) whose rotation is updated on the manifold, R <- R exp(dw).


def _split(theta, opts):
    d = theta[11:15] if opts.deform else jnp.zeros(4, theta.dtype)
    return theta[0:3], theta[3:5], so3.exp(theta[5:8]), theta[8:11], d


def _join(la, e, R, t, d, opts):
    parts = [la, e, so3.log(R), t] + ([d] if opts.deform else [])
    return jnp.concatenate(parts)


def _project(theta, opts):
    lo, hi = opts.epsilon_range
    theta = theta.at[3:5].set(jnp.clip(theta[3:5], lo, hi))
    if opts.deform:
        theta = theta.at[11:13].set(jnp.clip(theta[11:13], -1.0, 1.0)).at[13].set(jnp.maximum(theta[13], 0.0))
    return theta


def to_superquadric(theta, opts: FitOptions | None = None) -> Superquadric:
    """Parameter vector `(..., P)` of the global chart -> `Superquadric` (P = 11, or 15 with deformations)."""
    opts = opts if opts is not None else FitOptions(deform=theta.shape[-1] == 15)
    if theta.ndim > 1:
        return jax.vmap(lambda t: to_superquadric(t, opts))(theta)
    la, e, R, t, d = _split(theta, opts)
    return Superquadric(jnp.exp(la), e, R, t, d[0:2], d[2:4])


# ----------------------------------------------------------------------------------------------------
# the per-point residual in the model frame and its structured Jacobian


def _log_f_point(x, y, z, la, e, d, deform: bool):
    """log F (eq. 5) of one model-frame point (x, y, z), undeformed first when `deform`."""
    if deform:
        p = untaper(unbend(jnp.stack([x, y, z]), d[2:4]), d[0:2], jnp.exp(la[2:3]))
        x, y, z = p[0], p[1], p[2]
    return log_inside_outside_xyz(x, y, z, la, e)


def _residual_point(x, y, z, la, e, d, deform: bool, kind: str = "distance"):
    """The residual of one model-frame point (x, y, z), see `FitOptions.residual`.

    `"distance"`: the signed first-order distance of the root form F^(1/2),
    (F^(1/2) - 1) / |grad F^(1/2)| = 2 (1 - F^(-1/2)) / |grad log F|, exact on the faces of a box and
    on a sphere (inside and outside); `"size_weighted"`: the paper's f = sqrt(a1 a2 a3) (F - 1) (eq. 7).
    """
    if kind == "size_weighted":
        return jnp.exp(0.5 * (la[0] + la[1] + la[2])) * jnp.expm1(_log_f_point(x, y, z, la, e, d, deform))
    p = jnp.stack([x, y, z])
    if deform:  # the distance in the undeformed frame over the stretch of the undeforming map
        return deformed_distance(p, la, e, d[0:2], d[2:4])
    lf, log_gn, _ = log_inside_outside_and_gradient(p, la, e)
    return distance_from_log(lf, log_gn)


def _model_frame(state, points):
    """points (3, N) world -> model-frame coordinates x, y, z, each (N,)."""
    _, _, R, t, _ = state
    x = R.T @ (points - t[:, None])
    return x[0], x[1], x[2]


def _point_fn(opts, argnums=None):
    """The per-point residual of `opts` vmapped over points x, y, z (N,) (shape parameters shared):
    (x, y, z, la, e, d) -> r (N,); with `argnums`, -> (r, gradients with respect to those arguments)."""
    f = functools.partial(_residual_point, deform=opts.deform, kind=opts.residual)
    g = f if argnums is None else jax.value_and_grad(f, argnums=argnums)
    return jax.vmap(g, in_axes=(0, 0, 0, None, None, None))


def _normal_equations(state, points, mask, opts, weight=None):
    """Cost, J^T J and J^T r in the local chart [dla, de, dw (rotation), du (model-frame shift), dd].

    `points` is `(3, N)`, `mask` `(N,)`. One vmapped reverse-mode pass gives the residual and its
    gradient with respect to the model-frame point and the shape parameters; the pose columns follow
    from the chain rule (x' = exp(-dw) (x + du)).
    """
    la, e, _, _, d = state
    x, y, z = _model_frame(state, points)
    argnums = (0, 1, 2, 3, 4, 5) if opts.deform else (0, 1, 2, 3, 4)
    r, grads = _point_fn(opts, argnums)(x, y, z, la, e, d)
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


def _cost(state, points, mask, opts, weight=None):
    la, e, _, _, d = state
    x, y, z = _model_frame(state, points)
    r: jax.Array = _point_fn(opts)(x, y, z, la, e, d)  # pyright: ignore[reportAssignmentType]  (no argnums)
    r2 = r * r if weight is None else weight * r * r
    return jnp.sum(jnp.where(mask, r2, 0.0))


def _point_distances(state, points, mask, opts):
    """First-order distance |r| / |grad_x r| of every point (N,) (eq. 10 for the size-weighted residual),
    in the units of `points` (0 where masked)."""
    la, e, _, _, d = state
    x, y, z = _model_frame(state, points)
    r, (gx, gy, gz) = _point_fn(opts, (0, 1, 2))(x, y, z, la, e, d)
    fin = jnp.finfo(points.dtype)
    g = jnp.sqrt(gx * gx + gy * gy + gz * gz)
    dist = jnp.minimum(jnp.abs(r) / jnp.maximum(g, jnp.sqrt(fin.tiny)), fin.max**0.25)
    return jnp.where(mask, dist, 0.0)


def _masked_median(v, mask):
    """Lower median of the entries of v (N,) where mask; 0 when none."""
    s = jnp.sort(jnp.where(mask, v, jnp.inf))
    k = jnp.maximum(jnp.sum(mask) - 1, 0) // 2
    return jnp.where(jnp.any(mask), s[k], 0.0)


_TUKEY_C, _MAD_TO_SIGMA, _SCALE_FLOOR = 4.685, 1.4826, 1e-4


def _robust_weights(state, points, mask, opts, widen=1.0):
    """Tukey biweight of the eq. 10 distances with the MAD scale (normalised points: rms radius 1),
    the scale widened by `widen` (graduated: wide first, so a poor start does not lock inliers out)."""
    d = _point_distances(state, points, mask, opts)
    s = widen * jnp.maximum(_MAD_TO_SIGMA * _masked_median(d, mask), _SCALE_FLOOR)
    u = d / (_TUKEY_C * s)
    return jnp.where(mask & (u < 1.0), (1.0 - u * u) ** 2, 0.0)


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


def _capped(la, R, t, points, mask, opts):
    """Log half-sizes la (3,) within `_log_size_bound` at pose (R, t) where `opts.size_bound` holds."""
    if opts.size_bound is False:
        return la
    return jnp.where(opts.size_bound, jnp.minimum(la, _log_size_bound(R, t, points, mask)), la)


def _bounded(state, points, mask, opts):
    """`state` with its sizes within `_log_size_bound` at its own pose (with `opts.size_bound`)."""
    la, e, R, t, d = state
    return _capped(la, R, t, points, mask, opts), e, R, t, d


def _retract(state, step, opts):
    la, e, R, t, d = state
    lo, hi = opts.epsilon_range
    la = la + jnp.clip(step[0:3], -1.0, 1.0)
    e = jnp.clip(e + step[3:5], lo, hi)
    t = t - R @ step[8:11]
    R = R @ so3.exp(step[5:8])
    if opts.deform:
        d = d + step[11:15]
        alpha = jnp.remainder(d[3] + jnp.pi, 2 * jnp.pi) - jnp.pi  # the bending angle is periodic
        d = jnp.stack([jnp.clip(d[0], -1.0, 1.0), jnp.clip(d[1], -1.0, 1.0), jnp.maximum(d[2], 0.0), alpha])
    return la, e, R, t, d


def _levenberg_marquardt(state, points, mask, opts, num_steps, weight=None):
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


# ----------------------------------------------------------------------------------------------------
# initial estimates (points (3, N) normalised: centroid 0, rms radius 1)

_PERMS = ((0, 1, 2), (1, 2, 0), (2, 0, 1))  # cyclic: the rotation keeps det +1


def _take(x, idx, axis: int = 0):
    """x gathered at static indices along `axis` (plain slices: no index arrays, any x64 setting)."""
    return jnp.stack([jnp.take(x, i, axis) for i in idx], axis)


def _moment_frame(points, mask):
    """Centroid, right-handed eigenvectors of the covariance (ascending variance), local coordinates."""
    w = mask.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    c = jnp.sum(points * w, 1) / n
    q = (points - c[:, None]) * w
    _, V = jnp.linalg.eigh(q @ q.T / n)
    V = V * jnp.where(jnp.linalg.det(V) < 0, -1.0, 1.0)
    return c, V, V.T @ (points - c[:, None])


def _extent(local, mask):
    big = jnp.finfo(local.dtype).max / 4
    lo = jnp.min(jnp.where(mask, local, big), 1)
    hi = jnp.max(jnp.where(mask, local, -big), 1)
    return lo, hi


def _three(centre, V, half, dtype):
    """The three axis assignments (which eigenvector becomes the model z axis) of one ellipsoid start."""
    half = jnp.maximum(half, 1e-3 * jnp.max(half) + jnp.finfo(dtype).eps)
    return (
        jnp.stack([jnp.log(_take(half, p)) for p in _PERMS]),
        jnp.ones((3, 2), dtype),
        jnp.stack([_take(V, p, 1) for p in _PERMS]),
        jnp.broadcast_to(centre, (3, 3)),
        jnp.zeros((3, 4), dtype),
    )


def _moment_starts(points, mask):
    """The paper's start: the ellipsoid of the bounding box in the frame of the central second moments."""
    c, V, local = _moment_frame(points, mask)
    lo, hi = _extent(local, mask)
    return _three(c + V @ ((lo + hi) / 2), V, (hi - lo) / 2, points.dtype)


def _rim_starts(points, mask):
    """One-view start: the visible surface is the front half, so the centre lies at its rim.

    Along the least-spread moment axis (the viewing direction for a half shell) the rim points lie
    behind the apex; the sign comes from the covariance of that coordinate with the squared distance
    from the axis. The centre is put at the rim end and the size along that axis is the full extent.
    """
    c, V, local = _moment_frame(points, mask)
    lo, hi = _extent(local, mask)
    w = mask.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    u = local[0]
    rho2 = local[1] ** 2 + local[2] ** 2
    cov = jnp.sum(w * (u - jnp.sum(w * u) / n) * (rho2 - jnp.sum(w * rho2) / n))
    mid = ((lo + hi) / 2).at[0].set(jnp.where(cov > 0, hi[0], lo[0]))
    half = ((hi - lo) / 2).at[0].set(hi[0] - lo[0])
    return _three(c + V @ mid, V, half, points.dtype)


def _quadric_starts(points, mask):
    """Centre and axes of the algebraic least-squares quadric x^T M x + 2 g^T x = 1 when it is an ellipsoid.

    Uses the curvature of a partial view, which moments cannot; half-sizes are the extents of the points
    about that centre. Falls back to the moment start where the quadric is not a bounded ellipsoid.
    """
    dtype = points.dtype
    w = mask.astype(dtype)
    x, y, z = points
    D = jnp.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z]) * w
    A = D @ D.T
    A = A + (1e-6 * jnp.trace(A) / 9 + jnp.finfo(dtype).tiny) * jnp.eye(9, dtype=dtype)
    v = jnp.linalg.solve(A, D @ w)
    M = jnp.stack([jnp.stack([v[0], v[3], v[4]]), jnp.stack([v[3], v[1], v[5]]), jnp.stack([v[4], v[5], v[2]])])
    lam, V = jnp.linalg.eigh(M)
    V = V * jnp.where(jnp.linalg.det(V) < 0, -1.0, 1.0)
    c = -(V @ ((V.T @ v[6:9]) / jnp.where(lam > 0, lam, 1.0)))
    ok = (lam[0] > 1e-3 * lam[2]) & jnp.all(jnp.isfinite(c)) & (jnp.sum(c * c) < 9.0)
    local = jnp.abs(V.T @ (points - c[:, None]))
    half = jnp.max(jnp.where(mask, local, 0.0), 1)
    quad = _three(c, V, half, dtype)
    moment = _moment_starts(points, mask)
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), quad, moment)


_START_FNS = {"moments": _moment_starts, "rim": _rim_starts, "quadric": _quadric_starts}


def _initial_states(points, mask, opts):
    """All first-stage candidates, stacked: (C, ...) with C = 3 * len(starts) * len(epsilon_starts)."""
    families = [_START_FNS[name](points, mask) for name in opts.starts]
    base = jax.tree.map(lambda *a: jnp.concatenate(a), *families)
    out = []
    for e1, e2 in opts.epsilon_starts:
        la, e, R, t, d = base
        out.append((la, jnp.broadcast_to(jnp.asarray([e1, e2], points.dtype), e.shape), R, t, d))
    return jax.tree.map(lambda *a: jnp.concatenate(a), *out)


def _switched(state):
    """The two EMS 'switching' alternatives of a solution: the x or the y axis becomes z."""
    la, e, R, t, d = state
    # x -> z: columns (z, y, -x); y -> z: columns (x, z, -y); sizes follow, exponents swap.
    Rx = jnp.stack([R[:, 2], R[:, 1], -R[:, 0]], 1)
    Ry = jnp.stack([R[:, 0], R[:, 2], -R[:, 1]], 1)
    las = jnp.stack([_take(la, (2, 1, 0)), _take(la, (0, 2, 1))])
    es = jnp.stack([e[::-1], e[::-1]])
    return las, es, jnp.stack([Rx, Ry]), jnp.stack([t, t]), jnp.stack([d, d])


def _best(states, costs, convs, scores=None):
    """The candidate of lowest `scores` (default: the costs); non-finite ones never win."""
    scores = costs if scores is None else scores
    i = jnp.argmin(jnp.where(jnp.isfinite(scores) & jnp.isfinite(costs), scores, jnp.inf))
    return jax.tree.map(lambda v: v[i], states), costs[i], convs[i]


def _reweighted(state, points, mask, opts):
    """`robust_rounds` rounds of IRLS from `state`: Tukey weights from the current model, then LM.

    (A graduated scale, wide first, was tried: it lets the outliers pull the early rounds and made
    the 10 % outlier test worse, median IoU 0.64 against 0.77.)"""
    steps = max(opts.max_steps // 2, 1)

    def body(_, carry):
        state, _, _, _ = carry
        weight = _robust_weights(state, points, mask, opts)
        state, cost, conv = _levenberg_marquardt(state, points, mask, opts, steps, weight)
        return state, cost, conv, weight

    dtype = points.dtype
    init = (state, jnp.asarray(jnp.inf, dtype), jnp.asarray(False), mask.astype(dtype))
    return jax.lax.fori_loop(0, opts.robust_rounds, body, init)


def _robust_scores(states, points, mask, opts):
    """Truncated eq. 9 cost of each candidate (C,), one truncation for all: the comparison of `robust` starts.

    Per point min(f^2, (c s grad f)^2): the size-weighted squared residual of a point within c s of the
    surface (its eq. 10 distance d = |f| / |grad f|), a constant of the model beyond, with c = 4.685 and
    s the smallest MAD scale of the candidates (the noise as the best of them sees it)."""

    def per_point(state):
        la, e, _, _, d = state
        x, y, z = _model_frame(state, points)
        r, (gx, gy, gz) = _point_fn(opts, (0, 1, 2))(x, y, z, la, e, d)
        return r * r, gx * gx + gy * gy + gz * gz

    f2, g2 = jax.vmap(per_point)(states)
    dist = jax.vmap(lambda s: _point_distances(s, points, mask, opts))(states)
    sig = jnp.min(jax.vmap(lambda d: _masked_median(d, mask))(dist))
    tau2 = (_TUKEY_C * jnp.maximum(_MAD_TO_SIGMA * sig, _SCALE_FLOOR)) ** 2
    return jnp.sum(jnp.where(mask, jnp.minimum(f2, tau2 * g2), 0.0), -1)


# ----------------------------------------------------------------------------------------------------
# one problem, normalised coordinates, with implicit differentiation


def _subsample(points, mask, n: int):
    """`n` of the valid points, evenly strided through them in their given order: (3, n), (n,).

    All of them (and padding) when there are at most `n`. Used to screen the starting candidates.
    """
    order = jnp.argsort(~mask, stable=True)  # valid points first, order kept
    nv = jnp.sum(mask)
    i = jnp.arange(n)
    j = jnp.where(nv <= n, i, (i * nv) // n)
    idx = order[j]
    return points[:, idx], mask[idx] & (j < nv)


def _multistart(points, mask, opts):
    """Every start for `max_steps` and the two switched forms of the best for half as many, on a
    subsample of `screen_points`; then the winner for `max_steps // 2` more on all the points.

    With `robust`, every candidate also gets the IRLS rounds on the subsample and the candidates are
    compared by their truncated cost (`_robust_scores`); the finish on all points is left to `_solve`'s
    reweighting."""
    N = points.shape[1]
    n_sub = N if opts.screen_points is None else min(N, opts.screen_points)
    sub_pts, sub_mask = _subsample(points, mask, n_sub) if n_sub < N else (points, mask)
    half = max(opts.max_steps // 2, 1)

    def run(states, n):
        out = jax.vmap(lambda s: _levenberg_marquardt(s, sub_pts, sub_mask, opts, n))(states)
        if opts.robust:
            out = jax.vmap(lambda s: _reweighted(s, sub_pts, sub_mask, opts)[:3])(out[0])
        return out

    def pick(out):
        scores = _robust_scores(out[0], sub_pts, sub_mask, opts) if opts.robust else None
        return _best(*out, scores=scores)

    best = pick(run(_initial_states(points, mask, opts), opts.max_steps))
    second = run(_switched(best[0]), half)
    best = pick(jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), best, second))
    if n_sub == N or opts.robust:
        return best
    return _levenberg_marquardt(best[0], points, mask, opts, half)


def _solve(inputs):
    points, mask, theta0, opts, _ = inputs  # the adjoint appends a while-loop implementation
    if theta0 is not None:
        state, cost, conv = _levenberg_marquardt(_split(theta0, opts), points, mask, opts, opts.max_steps)
    elif opts.multistart:
        state, cost, conv = _multistart(points, mask, opts)
    else:
        first = jax.tree.map(lambda v: v[0], _moment_starts(points, mask))
        state, cost, conv = _levenberg_marquardt(first, points, mask, opts, opts.max_steps)
    weight = mask.astype(points.dtype)
    if opts.robust:
        state, cost, conv, weight = _reweighted(state, points, mask, opts)
    return _join(*state, opts=opts), (cost, conv, weight)


def _stationarity(theta, aux, inputs):
    """Projected-gradient optimality condition; zero at a (bound-constrained) minimum of G.

    With `robust`, of the weighted G with the final weights held fixed (aux)."""
    points, mask, _, opts, _ = inputs
    weight = aux[2] if opts.robust else None
    grad = jax.grad(lambda th: _cost(_split(th, opts), points, mask, opts, weight))(theta)
    _, _, R, t, _ = _split(theta, opts)
    step = _project(theta - grad, opts)
    step = step.at[0:3].set(_capped(step[0:3], R, t, points, mask, opts))
    return theta - step


def _deformation_pays(cost_deformed, cost_plain, n):
    """Whether the 4 deformation parameters earn their place (`FitOptions.deform`): the description
    length of the points, n/2 log(cost / n) for Gaussian residuals plus 1/2 log n per parameter (the
    BIC, a two-part code), is shorter with them: n log(cost_plain / cost_deformed) > 4 log n. On an
    undeformed shape the 4 extra parameters lower the cost by about 4 noise variances (a chi-square
    with 4 degrees of freedom), far below 4 log n."""
    tiny = jnp.finfo(cost_plain.dtype).tiny
    gain = n * (jnp.log(jnp.maximum(cost_plain, tiny)) - jnp.log(jnp.maximum(cost_deformed, tiny)))
    return jnp.isfinite(cost_deformed) & (gain > 4.0 * jnp.log(n))


def _fit_one(points, mask, theta0, opts: FitOptions):
    """Fit one padded problem; points (N, 3) with mask (N,); theta0 (P,) or None (original units)."""
    dtype = points.dtype
    w = mask.astype(dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    centre = jnp.sum(jnp.where(mask[:, None], points, 0.0), 0) / n
    centred = jnp.where(mask[:, None], points - centre, 0.0)
    scale = jnp.sqrt(jnp.sum(centred * centred) / n + jnp.finfo(dtype).tiny)
    scale = jnp.where(scale > 0, scale, 1.0)
    pn = (centred / scale).T
    if theta0 is not None:  # original units -> normalised chart
        theta0 = theta0.at[0:3].add(-jnp.log(scale)).at[8:11].set((theta0[8:11] - centre) / scale)
        if opts.deform:
            theta0 = theta0.at[13].multiply(scale)
    adjoint = optx.ImplicitAdjoint(lx.AutoLinearSolver(well_posed=False))  # SVD: a sphere's pose is not unique
    theta, (cost, conv, weight) = adjoint.apply(_solve, _stationarity, (pn, mask, theta0, opts), frozenset())
    if opts.deform:  # deformations only where they pay for themselves: nested models
        plain = dataclasses.replace(opts, deform=False)
        th0 = None if theta0 is None else theta0[: plain.num_params]
        theta_u, aux_u = adjoint.apply(_solve, _stationarity, (pn, mask, th0, plain), frozenset())
        # the deformed model also starts from the undeformed optimum (zero deformation), so that its
        # gain over it measures what the 4 parameters add, not a better local minimum
        flat = jnp.concatenate([theta_u, jnp.zeros(4, dtype)])
        nested = adjoint.apply(_solve, _stationarity, (pn, mask, jax.lax.stop_gradient(flat), opts), frozenset())
        choose = lambda flag, a, b: jax.tree.map(lambda u, v: jnp.where(flag, u, v), a, b)
        theta, (cost, conv, weight) = choose(nested[1][0] < cost, nested, (theta, (cost, conv, weight)))
        theta, (cost, conv, weight) = choose(
            _deformation_pays(cost, aux_u[0], n), (theta, (cost, conv, weight)), (flat, aux_u)
        )
    theta = theta.at[0:3].add(jnp.log(scale)).at[8:11].set(theta[8:11] * scale + centre)
    if opts.deform:
        theta = theta.at[13].divide(scale)
    cost = cost * scale ** (3 if opts.residual == "size_weighted" else 2)  # f ~ sqrt(a1 a2 a3); d ~ length
    sq = to_superquadric(theta, opts)
    dist = jnp.where(mask, distance(sq, points), 0.0)
    return theta, cost, conv, dist, weight


_CHUNK_POINTS = 4096
"""On CPU, problems are fitted `max(1, _CHUNK_POINTS // N)` at a time (all candidates side by side)."""


def _map_problems(points, mask, theta0, opts):
    """`_fit_one` over the leading axis: one vmap on accelerators; on CPU a loop over small chunks.

    A chunk's points and every intermediate of its LM steps then stay in cache, which on CPU is worth
    more than the width of one huge vmap.
    """
    K, N = points.shape[:2]
    if jax.default_backend() != "cpu":
        return jax.vmap(_fit_one, in_axes=(0, 0, None if theta0 is None else 0, None))(points, mask, theta0, opts)
    chunk = min(K, max(1, _CHUNK_POINTS // N))
    return jax.lax.map(lambda a: _fit_one(a[0], a[1], a[2], opts), (points, mask, theta0), batch_size=chunk)


_BATCHES = (1, 4, 16, 32, 64)
"""Problems per call of `fit_padded` on an accelerator (`call_size`)."""


def call_size(K: int, N: int) -> int:
    """Problems per call of `fit_padded` for K problems of N (padded) points, for callers whose K moves
    from call to call (segmentation's refits), so that each (N, options) compiles few kernels. On CPU,
    which fits a call's problems `max(1, _CHUNK_POINTS // N)` at a time anyway, that chunk whatever K
    (several calls for more): one kernel. A single problem then pays for a chunk, which measured less
    than the kernel it saves (mOSD at 160 x 120, 7 scenes, 2026-12-02: steady-state time within 2%,
    compile 79 -> 55 s). On an accelerator, which fits them side by side, the next of `_BATCHES`
    (calls of 64 beyond): five."""
    if jax.default_backend() == "cpu":
        return max(1, _CHUNK_POINTS // N)
    return next((b for b in _BATCHES if b >= K), _BATCHES[-1])


@persistent_kernel
@eqx.filter_jit
def fit_padded(points, mask, theta0, opts: FitOptions):
    """The batch kernel: points (K, N, 3), mask (K, N), theta0 (K, P) or None -> theta, cost, converged, distance.

    One compiled call per (K, N, dtype, options); `fit` pads to power-of-two buckets to keep that set
    small. `theta` is the global chart [log a, e, rotation vector, t, (Kx, Ky, k, alpha)]. With the
    compilation cache on, its lowered form is kept on disk too (`cache.persistent_kernel`).
    """
    return _map_problems(points, mask, theta0, opts)[:4]


def _init_theta(init, opts):
    """Warm-start fields (size, epsilon, rotation, translation, taper, bend), batched -> theta0 (K, P) and
    a (K,) flag of the valid ones; invalid ones (non-finite, size <= 0) are replaced by a unit sphere."""
    size, eps, R, t, taper, bend = init
    ok = (
        jnp.all(jnp.isfinite(size) & (size > 0), -1)
        & jnp.all(jnp.isfinite(eps), -1)
        & jnp.all(jnp.isfinite(R), (-2, -1))
        & jnp.all(jnp.isfinite(t), -1)
    )
    if opts.deform:
        ok = ok & jnp.all(jnp.isfinite(taper), -1) & jnp.all(jnp.isfinite(bend), -1)
    lo, hi = opts.epsilon_range
    safe = lambda v, d: jnp.where(ok.reshape(ok.shape + (1,) * (v.ndim - 1)), v, d)
    size = safe(size, 1.0)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=R.dtype), R.shape)
    parts = [jnp.log(size), jnp.clip(safe(eps, 1.0), lo, hi), so3.log(safe(R, eye)), safe(t, 0.0)]
    if opts.deform:
        parts += [safe(taper, 0.0), safe(bend, 0.0)]
    return jnp.concatenate(parts, -1), ok


def _fit_problems(points, mask, init, opts):
    """Everything `fit` needs from the device in one traced function: (sq fields, cost, conv, dist, weight, init_ok)."""
    theta0, init_ok = (None, jnp.ones(points.shape[:1], bool)) if init is None else _init_theta(init, opts)
    theta, cost, conv, dist, weight = _map_problems(points, mask, theta0, opts)
    sq = to_superquadric(theta, opts)
    return (sq.size, sq.epsilon, sq.rotation, sq.translation, sq.taper, sq.bend), cost, conv, dist, weight, init_ok


_fit_kernel = persistent_kernel(eqx.filter_jit(_fit_problems))
"""The kernel `fit` calls: one compile per (padded K, padded N, dtype, options, init or not)."""


@eqx.filter_jit
def _fit_sharded(points, mask, init, opts: FitOptions):
    """`_fit_kernel` with the problems split over every local CPU device (one `shard_map` block each)."""
    mesh = jax.sharding.Mesh(np.array(jax.local_devices()), ("k",))
    spec = jax.sharding.PartitionSpec("k")
    body = lambda p, m, i: _fit_problems(p, m, i, opts)
    return jax.shard_map(
        body, mesh=mesh, in_specs=(spec, spec, None if init is None else spec), out_specs=spec, check_vma=False
    )(points, mask, init)


def _use_devices(K: int) -> bool:
    """Several local CPU devices (`XLA_FLAGS=--xla_force_host_platform_device_count=<cores>`) dividing K."""
    devices = jax.local_devices()
    return len(devices) > 1 and K % len(devices) == 0 and devices[0].platform == "cpu"


# ----------------------------------------------------------------------------------------------------
# the user-facing entry point: host checks, robust centring and padding in numpy before anything is
# traced (one compile per bucket); the same steps in jax.numpy when the input is traced (differentiable)


def bucket(n: int, minimum: int = 32) -> int:
    """Padded size for n: the next power of two, at least `minimum`."""
    return max(minimum, 1 << max(int(n) - 1, 0).bit_length())


def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)  # pyright: ignore[reportAttributeAccessIssue]  (jax imports jax.core)


def _nanmedian(xp, v, axis):
    if xp is np:
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN problems are caught elsewhere
                return np.nanmedian(v, axis=axis)
    return jnp.nanmedian(v, axis=axis)


def _robust_centre(xp, points, mask, far_factor):
    """Median centre (K, 3) of the valid points, the points about it, and the mask without far points.

    A point is far when its distance from the centre exceeds `far_factor` x the median distance
    (None: none is). Masked-out rows become 0 before any arithmetic (no NaN reaches a gradient).
    """
    centre = _nanmedian(xp, xp.where(mask[..., None], points, xp.nan), 1)
    centre = xp.where(xp.isfinite(centre), centre, 0.0)
    rel = xp.where(mask[..., None], points, 0.0) - xp.where(mask[..., None], centre[:, None], 0.0)
    far = xp.zeros(mask.shape, bool)
    if far_factor is not None:
        q = jax.lax.stop_gradient(rel) if xp is jnp else rel
        r = xp.sqrt(xp.sum(q * q, -1))
        med = _nanmedian(xp, xp.where(mask, r, xp.nan), 1)
        far = mask & ~(r <= far_factor * xp.where(xp.isfinite(med), med, 0.0)[:, None])
        far = far & (xp.sum(mask, -1) >= 2 * MIN_POINTS)[:, None]
    mask = mask & ~far
    return centre, xp.where(mask[..., None], rel, 0.0), mask, xp.any(far, -1)


def _degenerate(xp, rel, mask):
    """(K,) True where the valid points are identical or collinear (second moment of rank < 2)."""
    q = jax.lax.stop_gradient(rel) if xp is jnp else rel
    w = mask.astype(q.dtype)[..., None]
    n = xp.maximum(xp.sum(w, 1), 1.0)
    c = xp.sum(q * w, 1) / n
    d = (q - c[:, None]) * w
    cov = xp.einsum("kni,knj->kij", d, d) / n[..., None]
    ev = xp.linalg.eigvalsh(cov)
    return ~(ev[:, 1] > 1e-6 * ev[:, 2])


def _init_fields(xp, init, K, dtype, centre, deform):
    """Warm start -> batched fields (K, ...) in the centred frame; on the host, checks that name the field."""
    fields = {
        "size": init.size,
        "epsilon": init.epsilon,
        "rotation": init.rotation,
        "translation": init.translation,
        "taper": init.taper,
        "bend": init.bend,
    }
    fields = {k: (np.asarray(v, np.float64) if xp is np else v) for k, v in fields.items()}
    single = fields["size"].ndim == 1
    if single:
        fields = {k: v[None] for k, v in fields.items()}
    if fields["size"].shape[0] not in (1, K):
        raise ValueError(f"fit: init holds {fields['size'].shape[0]} models for {K} problems")
    if xp is np:
        for name, v in fields.items():
            if (deform or name not in ("taper", "bend")) and not np.all(np.isfinite(v)):
                raise ValueError(f"fit: init.{name} must be finite, got {v.tolist()}")
        if not np.all(fields["size"] > 0):
            raise ValueError(f"fit: init.size must be > 0, got {fields['size'].tolist()}")
    fields = {k: xp.broadcast_to(v, (K,) + v.shape[1:]) for k, v in fields.items()}
    fields["translation"] = fields["translation"] - centre
    return tuple(fields[k].astype(dtype) for k in ("size", "epsilon", "rotation", "translation", "taper", "bend"))


def _status(xp, opts, size, eps, taper, cost, conv, dist, mask, degenerate, init_ok, finite, far, noise):
    """Per-problem `Status` flags (K,) int32 from the kernel outputs (numpy on the host, jnp when traced)."""
    n = xp.sum(mask, -1)
    lo, hi = opts.epsilon_range
    tol = 1e-3 * (hi - lo)
    bound = xp.any((eps <= lo + tol) | (eps >= hi - tol), -1)
    if opts.deform:
        bound = bound | xp.any(xp.abs(taper) >= 1.0 - 1e-3, -1)
    med = _nanmedian(xp, xp.where(mask, dist, xp.nan), 1)
    limit = 3.0 * noise if noise is not None else 0.02 * xp.mean(size, -1)
    flags = [
        (~conv, Status.MAX_STEPS),
        (bound, Status.BOUND_ACTIVE),
        (med > limit, Status.LARGE_RESIDUAL),
        (degenerate | ~init_ok, Status.DEGENERATE),
        (n < MIN_POINTS, Status.TOO_FEW_POINTS),
        (~finite, Status.NONFINITE),
        (far, Status.FAR_POINTS),
    ]
    status = xp.zeros(n.shape, xp.int32)
    for cond, flag in flags:
        status = status | xp.where(cond, int(flag), 0).astype(xp.int32)
    return status


def fit(
    points,
    mask=None,
    *,
    init: Superquadric | None = None,
    options: FitOptions | None = None,
    dtype=None,
    noise: float | None = None,
    far_factor: float | None = 100.0,
    **kw,
) -> Fit:
    """Recover superquadrics from one point set `(N, 3)` or many `(K, N, 3)` (Solina & Bajcsy).

    **Arguments:**

    - `points`: `(N, 3)` or `(K, N, 3)` coordinates (any length unit). Rows that are NaN/inf, or
      masked out, are ignored (missing data), under tracing too.
    - `mask`: `(N,)` / `(K, N)` bool, True for points to use. Default: all finite rows.
    - `init`: warm start (a `Superquadric`, batched like the problems); skips the multistart.
    - `options`: a `FitOptions`; or keyword arguments (`max_steps=`, `multistart=`, `deform=`,
      `robust=` ...) that build one. `robust=True` turns on the outlier weights (see `FitOptions`);
      it is off by default: on clean data it cost one gross failure in 64 and 3x the time (see
      benchmarks/fit.py --suites outliers), which the issue's condition for a default excludes.
    - `dtype`: `jnp.float32` (default) or `jnp.float64` (needs `jax.config.update("jax_enable_x64", True)`).
    - `noise`: expected noise (std, units of the points), only for the `LARGE_RESIDUAL` flag.
    - `far_factor`: points farther from the median centre than this many median radii are dropped
      and flagged (`Status.FAR_POINTS`); None keeps all.

    **Returns:** a `Fit` (parameters, cost, per-point distances and weights `(K, N)`, converged flags, status).

    The points are centred on their median in float64 on the host (numpy) before the cast to `dtype`,
    so far-away coordinates lose nothing to float32; then padded (numpy) to power-of-two buckets (N at
    least 128), so one compile serves every N of a bucket. Differentiable with respect to `points` (implicit
    differentiation at the optimum; the same steps in jax.numpy). When JAX has several CPU devices
    (`XLA_FLAGS=--xla_force_host_platform_device_count=2`) and they divide the padded batch, the
    problems are split between them (same kernel per problem, so the same results).
    """
    if options is not None and kw:
        raise TypeError(f"fit: pass either options= or keyword options, not both (got {sorted(kw)})")
    if options is None:
        options = FitOptions(**kw)
    traced = any(_is_traced(v) for v in jax.tree.leaves((points, mask, init)))
    xp = jnp if traced else np
    dtype = jnp.dtype(dtype or (points.dtype if _is_traced(points) else jnp.float32))
    if dtype not in (jnp.float32, jnp.float64):
        raise ValueError(f"fit: dtype must be float32 or float64, got {dtype}")
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:  # pyright: ignore[reportAttributeAccessIssue]
        raise ValueError("fit: float64 requested but JAX x64 is off; call jax.config.update('jax_enable_x64', True)")
    if far_factor is not None and not far_factor > 1.0:
        raise ValueError(f"fit: far_factor must be > 1 or None, got {far_factor}")
    if not _is_traced(points):
        points = np.asarray(points)
        if not np.issubdtype(points.dtype, np.number):
            raise ValueError(f"fit: points must be numeric, got dtype {points.dtype}")
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(f"fit: points must have shape (N, 3) or (K, N, 3), got {tuple(points.shape)}")
    single = points.ndim == 2
    if single:
        points = points[None]
    K, N = points.shape[:2]
    if K == 0 or N == 0:
        raise ValueError(f"fit: empty point set, shape {tuple(points.shape)}")
    if mask is not None:
        mask = mask.astype(bool) if _is_traced(mask) else np.asarray(mask).astype(bool)
        mask = mask[None] if single else mask
        if tuple(mask.shape) != (K, N):
            expected = (N,) if single else (K, N)
            got = tuple(mask.shape[1:]) if single else tuple(mask.shape)
            raise ValueError(f"fit: mask shape {got} does not match the points, expected {expected}")
    # centring precision: float64 on the host; under tracing the input's own dtype (then cast)
    points = (
        points.astype(np.float64)
        if xp is np
        else (jnp.asarray(points) if jnp.issubdtype(points.dtype, jnp.floating) else jnp.asarray(points, dtype))
    )
    finite = xp.all(xp.isfinite(points), -1)
    mask = finite if mask is None else (xp.asarray(mask) & finite)
    if xp is np:
        counts = mask.sum(-1)
        bad = np.nonzero(counts < MIN_POINTS)[0]
        if bad.size:
            which = "" if single else f"problem {int(bad[0])} has "
            raise ValueError(
                f"fit: too few valid (finite, unmasked) points: {which}{int(counts[bad[0]])}, "
                f"at least {MIN_POINTS} are needed (one per parameter)"
            )
    centre, rel, mask, far = _robust_centre(xp, points, mask, far_factor)
    degenerate = _degenerate(xp, rel, mask)
    Kb, Nb = bucket(K, 1), bucket(N, 128)  # small problems share one kernel: padding 128 points costs ~nothing
    pts = xp.pad(rel.astype(dtype), ((0, Kb - K), (0, Nb - N), (0, 0)))
    msk = xp.pad(mask, ((0, Kb - K), (0, Nb - N)))
    fields = None if init is None else _init_fields(xp, init, K, dtype, centre, options.deform)
    if Kb > K:  # pad the batch with copies of problem 0, dropped below
        rep = lambda v: xp.concatenate([v[:K], xp.repeat(v[:1], Kb - K, 0)])
        pts, msk = rep(pts), rep(msk)
        fields = None if fields is None else tuple(rep(v) for v in fields)
    kernel = _fit_sharded if xp is np and _use_devices(Kb) else _fit_kernel
    out = kernel(pts, msk, fields, options)
    if xp is np:  # crop in numpy: no small compiled ops per shape
        out = jax.tree.map(np.asarray, out)
    sqf, cost, conv, dist, weight, init_ok = jax.tree.map(lambda v: v[:K], out)
    dist, weight, msk = dist[:, :N], weight[:, :N], msk[:K, :N]
    size, eps, R, t, taper, bend = sqf
    t = t.astype(centre.dtype) + centre
    finite_out = xp.isfinite(cost) & xp.all(xp.isfinite(size), -1) & xp.all(xp.isfinite(t), -1)
    finite_out = finite_out & xp.all(xp.isfinite(eps), -1) & xp.all(xp.isfinite(R), (-2, -1))
    status = _status(xp, options, size, eps, taper, cost, conv, dist, msk, degenerate, init_ok, finite_out, far, noise)
    converged = conv & ((status & int(_FAILED)) == 0)
    # never hand out NaN: a non-finite fit is replaced by the moment-free unit sphere at the centre
    keep = lambda v, d: xp.where(finite_out.reshape((K,) + (1,) * (v.ndim - 1)), v, d)
    sq = Superquadric(
        keep(size, 1.0), keep(eps, 1.0), keep(R, xp.eye(3, dtype=R.dtype)), keep(t, centre).astype(dtype), taper, bend
    )
    cost = xp.where(finite_out, cost, xp.inf)
    dist = xp.where(finite_out[:, None] & msk, dist, 0.0)
    weight = xp.where(msk, weight, 0.0)
    res = Fit(  # pyright: ignore[reportArgumentType]  (numpy off-trace)
        sq,
        cost,  # pyright: ignore[reportArgumentType]
        dist,  # pyright: ignore[reportArgumentType]
        converged,
        xp.sum(msk, -1).astype(xp.int32),  # pyright: ignore[reportArgumentType]
        weight.astype(dtype),  # pyright: ignore[reportArgumentType]
        status,
    )
    if single:
        res = jax.tree.map(lambda v: v[0], res)
    # device_put, not jnp.asarray: the latter compiles a small "stage" op for every new shape
    return jax.tree.map(lambda v: jax.device_put(np.asarray(v)), res) if xp is np else res
