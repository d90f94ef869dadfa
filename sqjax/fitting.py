"""Recovery of superquadrics (Solina & Bajcsy): batched Levenberg–Marquardt on the size-weighted residual.

One jit-compiled call fits K padded point sets `(K, N, 3)` with masks `(K, N)`, every problem and every
starting candidate side by side (`jax.vmap`), for a fixed number of LM steps. Derivatives of the
residual come from autodiff of the per-point function in the model frame; the pose is chained by hand
(translation: `-R g`, rotation: `g x x`), which keeps the Jacobian cheap. Gradients of the fitted
parameters with respect to the points use the implicit function theorem at the optimum
(`optimistix.implicit_jvp`), never differentiation through the iterations.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from . import rotation as so3
from .superquadric import EPSILON_RANGE, Superquadric, distance, log_inside_outside_local, untaper, unbend

MIN_POINTS = 11
"""Fewest valid points a problem may have (one per parameter)."""


class FitOptions(eqx.Module):
    """How the Levenberg–Marquardt recovery runs; every field is static (a compile-cache key).

    - `max_steps`: LM steps per candidate (the paper: ~15 suffice).
    - `multistart`: start from the three axis assignments of the moment ellipsoid, then try the two
      "switched" solutions (EMS) of the best; keep the lowest cost. Ignored when `init` is given.
    - `deform`: also fit tapering (Kx, Ky) and bending (k, alpha).
    - `epsilon_range`: bounds of the exponents e1, e2 (projection after each step).
    """

    max_steps: int = eqx.field(static=True, default=20)
    multistart: bool = eqx.field(static=True, default=True)
    deform: bool = eqx.field(static=True, default=False)
    epsilon_range: tuple[float, float] = eqx.field(static=True, default=EPSILON_RANGE)

    @property
    def num_params(self) -> int:
        return 15 if self.deform else 11


class Fit(eqx.Module):
    """Result of `fit`. Leading axis K present when the input was batched.

    - `superquadric`: the recovered models (sizes and translation in the units of the points).
    - `cost`: `(K,)` G = sum of squared size-weighted residuals (eq. 9).
    - `distance`: `(K, N)` eq. 10 distance of every point to its model (0 where masked out).
    - `converged`: `(K,)` bool, the last LM steps no longer reduced the cost (relative 1e-4) and all is finite.
    - `num_points`: `(K,)` valid points used.
    """

    superquadric: Superquadric
    cost: jax.Array
    distance: jax.Array
    converged: jax.Array
    num_points: jax.Array


# ----------------------------------------------------------------------------------------------------
# parameters: the global chart theta = [log a (3), e (2), rotation vector (3), t (3), (Kx, Ky, k, alpha)]


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


def to_superquadric(theta, opts: FitOptions = FitOptions()) -> Superquadric:
    """Parameter vector `(..., P)` of the global chart -> `Superquadric`."""
    if theta.ndim > 1:
        return jax.vmap(lambda t: to_superquadric(t, opts))(theta)
    la, e, R, t, d = _split(theta, opts)
    return Superquadric(jnp.exp(la), e, R, t, d[0:2], d[2:4])


# ----------------------------------------------------------------------------------------------------
# the per-point residual in the model frame and its structured Jacobian


def _phi(x, la, e, d, deform: bool):
    """Size-weighted residual f (eq. 7) of one model-frame point x (3,)."""
    if deform:
        x = untaper(unbend(x, d[2:4]), d[0:2], jnp.exp(la[2]))
    logF = log_inside_outside_local(x, la, e)
    return jnp.exp(0.5 * jnp.sum(la)) * jnp.expm1(logF)


def _normal_equations(state, points, mask, opts):
    """Cost, J^T J and J^T r in the local chart [dla, de, dw (rotation), du (model-frame shift), dd]."""
    la, e, R, t, d = state
    x = (points - t) @ R
    val_grad = jax.vmap(jax.value_and_grad(_phi, argnums=(0, 1, 2, 3)), in_axes=(0, None, None, None, None))
    r, (gx, gla, ge, gd) = val_grad(x, la, e, d, opts.deform)
    cols = [gla, ge, jnp.cross(gx, x), gx] + ([gd] if opts.deform else [])
    w = mask.astype(points.dtype)
    r = jnp.where(mask, r, 0.0)
    J = jnp.concatenate(cols, -1) * w[:, None]
    J = jnp.where(jnp.isfinite(J), J, 0.0)
    cost = jnp.sum(r * r)
    return cost, J.T @ J, J.T @ r


def _cost(state, points, mask, opts):
    la, e, R, t, d = state
    x = (points - t) @ R
    r = jax.vmap(_phi, in_axes=(0, None, None, None, None))(x, la, e, d, opts.deform)
    return jnp.sum(jnp.where(mask, r * r, 0.0))


def _retract(state, step, opts):
    la, e, R, t, d = state
    lo, hi = opts.epsilon_range
    la = la + jnp.clip(step[0:3], -1.0, 1.0)
    e = jnp.clip(e + step[3:5], lo, hi)
    t = t - R @ step[8:11]
    R = R @ so3.exp(step[5:8])
    if opts.deform:
        d = d + step[11:15]
        d = d.at[0:2].set(jnp.clip(d[0:2], -1.0, 1.0)).at[2].set(jnp.maximum(d[2], 0.0))
    return la, e, R, t, d


def _levenberg_marquardt(state, points, mask, opts, num_steps):
    """Fixed-step LM from `state`; returns (state, cost, converged). One residual+Jacobian pass a step."""
    P = opts.num_params
    cost, JTJ, JTr = _normal_equations(state, points, mask, opts)

    def body(_, carry):
        state, cost, JTJ, JTr, lam, rel = carry
        diag = jnp.diagonal(JTJ)
        damp = lam * (diag + 1e-9 * jnp.max(diag) + jnp.finfo(diag.dtype).tiny)
        step = jnp.linalg.solve(JTJ + jnp.diag(damp), -JTr)
        step = jnp.where(jnp.isfinite(step), step, 0.0)
        new = _retract(state, step, opts)
        ncost, nJTJ, nJTr = _normal_equations(new, points, mask, opts)
        ok = jnp.isfinite(ncost) & (ncost < cost)
        pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(ok, u, v), a, b)  # noqa: E731
        rel = jnp.where(ok, (cost - ncost) / jnp.maximum(cost, jnp.finfo(cost.dtype).tiny), 0.0)
        lam = jnp.clip(jnp.where(ok, lam * 0.3, lam * 4.0), 1e-9, 1e9)
        state, cost, JTJ, JTr = pick((new, ncost, nJTJ, nJTr), (state, cost, JTJ, JTr))
        return state, cost, JTJ, JTr, lam, rel

    init = (state, cost, JTJ, JTr, jnp.asarray(1e-2, points.dtype), jnp.asarray(1.0, points.dtype))
    state, cost, _, _, lam, rel = jax.lax.fori_loop(0, num_steps, body, init)
    del P
    # Converged: the last steps stopped paying (a rejected step with a large damping, or a tiny gain).
    converged = jnp.isfinite(cost) & ((rel < 1e-4) | (lam > 1e3))
    return state, cost, converged


# ----------------------------------------------------------------------------------------------------
# initial estimates


def _moment_candidates(points, mask):
    """Ellipsoid starts from central second moments: (3, state) for the three choices of the z axis."""
    w = mask.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    c = jnp.sum(points * w[:, None], 0) / n
    q = (points - c) * w[:, None]
    cov = q.T @ q / n
    _, V = jnp.linalg.eigh(cov)
    V = V * jnp.where(jnp.linalg.det(V) < 0, -1.0, 1.0)          # right-handed
    local = (points - c) @ V
    big = jnp.finfo(points.dtype).max / 4
    lo = jnp.min(jnp.where(mask[:, None], local, big), 0)
    hi = jnp.max(jnp.where(mask[:, None], local, -big), 0)
    centre = c + V @ ((lo + hi) / 2)
    half = jnp.maximum((hi - lo) / 2, 1e-3 * jnp.max(hi - lo) + jnp.finfo(points.dtype).eps)
    perms = jnp.array([[0, 1, 2], [1, 2, 0], [2, 0, 1]])          # cyclic: det stays +1
    Rs = V[:, perms].transpose(1, 0, 2)
    la = jnp.log(half[perms])
    e = jnp.ones((3, 2), points.dtype)
    return la, e, Rs, jnp.broadcast_to(centre, (3, 3)), jnp.zeros((3, 4), points.dtype)


def _switched(state):
    """The two EMS 'switching' alternatives of a solution: the x or the y axis becomes z."""
    la, e, R, t, d = state
    # x -> z: columns (z, y, -x); y -> z: columns (x, z, -y); sizes follow, exponents swap.
    Rx = jnp.stack([R[:, 2], R[:, 1], -R[:, 0]], 1)
    Ry = jnp.stack([R[:, 0], R[:, 2], -R[:, 1]], 1)
    las = jnp.stack([la[jnp.array([2, 1, 0])], la[jnp.array([0, 2, 1])]])
    es = jnp.stack([e[::-1], e[::-1]])
    return las, es, jnp.stack([Rx, Ry]), jnp.stack([t, t]), jnp.stack([d, d])


def _best(states, costs):
    i = jnp.argmin(jnp.where(jnp.isfinite(costs), costs, jnp.inf))
    return jax.tree.map(lambda v: v[i], states), i


# ----------------------------------------------------------------------------------------------------
# one problem, normalised coordinates, with implicit differentiation


def _solve(inputs):
    points, mask, theta0, opts, _ = inputs   # the adjoint appends a while-loop implementation
    lm = jax.vmap(lambda s: _levenberg_marquardt(s, points, mask, opts, opts.max_steps))
    if theta0 is not None:
        state, cost, conv = _levenberg_marquardt(_split(theta0, opts), points, mask, opts, opts.max_steps)
    elif opts.multistart:
        states, costs, convs = lm(_moment_candidates(points, mask))
        best, i = _best(states, costs)
        states2, costs2, convs2 = jax.vmap(
            lambda s: _levenberg_marquardt(s, points, mask, opts, max(opts.max_steps // 2, 1)))(_switched(best))
        allstates = jax.tree.map(lambda a, b: jnp.concatenate([a[i][None], b]), states, states2)
        allcosts = jnp.concatenate([costs[i][None], costs2])
        allconv = jnp.concatenate([convs[i][None], convs2])
        state, j = _best(allstates, allcosts)
        cost, conv = allcosts[j], allconv[j]
    else:
        cands = _moment_candidates(points, mask)
        state, cost, conv = _levenberg_marquardt(jax.tree.map(lambda v: v[0], cands), points, mask, opts, opts.max_steps)
    return _join(*state, opts), (cost, conv)


def _stationarity(theta, _aux, inputs):
    """Projected-gradient optimality condition; zero at a (bound-constrained) minimum of G."""
    points, mask, _, opts, _ = inputs
    grad = jax.grad(lambda th: _cost(_split(th, opts), points, mask, opts))(theta)
    return theta - _project(theta - grad, opts)


def _fit_one(points, mask, theta0, opts: FitOptions):
    """Fit one padded problem; points (N, 3) with mask (N,); theta0 (P,) or None (original units)."""
    dtype = points.dtype
    w = mask.astype(dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    centre = jnp.sum(jnp.where(mask[:, None], points, 0.0), 0) / n
    centred = jnp.where(mask[:, None], points - centre, 0.0)
    scale = jnp.sqrt(jnp.sum(centred * centred) / n + jnp.finfo(dtype).tiny)
    scale = jnp.where(scale > 0, scale, 1.0)
    pn = centred / scale
    if theta0 is not None:   # original units -> normalised chart
        theta0 = theta0.at[0:3].add(-jnp.log(scale)).at[8:11].set((theta0[8:11] - centre) / scale)
        if opts.deform:
            theta0 = theta0.at[13].multiply(scale)
    adjoint = optx.ImplicitAdjoint(lx.AutoLinearSolver(well_posed=False))  # SVD: a sphere's pose is not unique
    theta, (cost, conv) = adjoint.apply(_solve, _stationarity, (pn, mask, theta0, opts), frozenset())
    theta = theta.at[0:3].add(jnp.log(scale)).at[8:11].set(theta[8:11] * scale + centre)
    if opts.deform:
        theta = theta.at[13].divide(scale)
    cost = cost * scale**3   # f scales with sqrt(a1 a2 a3)
    sq = to_superquadric(theta, opts)
    dist = jnp.where(mask, distance(sq, points), 0.0)
    return theta, cost, conv, dist


@eqx.filter_jit
def fit_padded(points, mask, theta0, opts: FitOptions):
    """The batch kernel: points (K, N, 3), mask (K, N), theta0 (K, P) or None -> theta, cost, converged, distance.

    One compiled call per (K, N, dtype, options); `fit` pads to power-of-two buckets to keep that set small.
    """
    in_axes = (0, 0, None if theta0 is None else 0, None)
    return jax.vmap(_fit_one, in_axes=in_axes)(points, mask, theta0, opts)


# ----------------------------------------------------------------------------------------------------
# the user-facing entry point (host checks and padding; differentiable when given JAX arrays)


def bucket(n: int, minimum: int = 32) -> int:
    """Padded size for n: the next power of two, at least `minimum`."""
    return max(minimum, 1 << max(int(n) - 1, 0).bit_length())


def _is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def fit(points, mask=None, *, init: Superquadric | None = None, options: FitOptions | None = None,
        dtype=None, **kw) -> Fit:
    """Recover superquadrics from one point set `(N, 3)` or many `(K, N, 3)` (Solina & Bajcsy).

    **Arguments:**

    - `points`: `(N, 3)` or `(K, N, 3)` coordinates (any length unit). Rows that are NaN/inf, or
      masked out, are ignored (missing data).
    - `mask`: `(N,)` / `(K, N)` bool, True for points to use. Default: all finite rows.
    - `init`: warm start (a `Superquadric`, batched like the problems); skips the moment starts.
    - `options`: a `FitOptions`; keyword arguments (`max_steps=`, `multistart=`, `deform=`) build one.
    - `dtype`: `jnp.float32` (default) or `jnp.float64` (needs `jax.config.update("jax_enable_x64", True)`).

    **Returns:** a `Fit` (parameters, cost, per-point distances `(K, N)`, converged flags).

    Differentiable with respect to `points` (implicit differentiation at the optimum).
    """
    options = options if options is not None else FitOptions(**kw)
    if kw and options is not None and "options" in kw:
        raise TypeError("fit: pass either options= or keyword options, not both")
    dtype = jnp.dtype(dtype or (points.dtype if _is_traced(points) else jnp.float32))
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise ValueError("fit: float64 requested but JAX x64 is off; call jax.config.update('jax_enable_x64', True)")
    if dtype not in (jnp.float32, jnp.float64):
        raise ValueError(f"fit: dtype must be float32 or float64, got {dtype}")
    traced = _is_traced(points)
    if not traced:
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
        mask = np.asarray(mask, bool) if not _is_traced(mask) else mask
        mask = mask[None] if mask.ndim == 1 and single else mask
        if tuple(mask.shape) != (K, N):
            raise ValueError(f"fit: mask shape {tuple(mask.shape)} does not match points {(K, N) if not single else (N,)}")
    if not traced:
        finite = np.isfinite(points).all(-1)
        mask = finite if mask is None else (np.asarray(mask) & finite)
        counts = mask.sum(-1)
        bad = np.nonzero(counts < MIN_POINTS)[0]
        if bad.size:
            raise ValueError(f"fit: too few valid points: problem {int(bad[0])} has {int(counts[bad[0]])}, "
                             f"at least {MIN_POINTS} are needed (one per parameter)")
        points = np.where(mask[..., None], points, 0.0)
    elif mask is None:
        mask = jnp.ones((K, N), bool)
    Kb, Nb = bucket(K, 1), bucket(N)
    pts = jnp.asarray(points, dtype)
    pts = jnp.pad(pts, ((0, 0), (0, Nb - N), (0, 0)))
    msk = jnp.pad(jnp.asarray(mask), ((0, 0), (0, Nb - N)))
    theta0 = None
    if init is not None:
        sq = jax.tree.map(lambda v: jnp.asarray(v, dtype), init)
        sq = jax.tree.map(lambda v: v[None], sq) if sq.size.ndim == 1 else sq
        theta0 = jnp.concatenate([jnp.log(sq.size), sq.epsilon, so3.log(sq.rotation), sq.translation]
                                 + ([sq.taper, sq.bend] if options.deform else []), -1)
        theta0 = jnp.broadcast_to(theta0, (K, theta0.shape[-1]))
    if Kb > K:   # pad the batch with copies of problem 0, dropped below
        rep = lambda v: jnp.concatenate([v, jnp.repeat(v[:1], Kb - K, 0)])  # noqa: E731
        pts, msk = rep(pts), rep(msk)
        theta0 = None if theta0 is None else rep(theta0)
    theta, cost, conv, dist = fit_padded(pts, msk, theta0, options)
    sq = to_superquadric(theta[:K], options)
    out = Fit(sq, cost[:K], dist[:K, :N], conv[:K], jnp.sum(msk[:K], -1))
    return jax.tree.map(lambda v: v[0], out) if single else out
