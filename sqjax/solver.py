"""The batched fitter: every start of every problem, side by side, in one jit-compiled call.

One problem (`fit_one`, normalised to centroid 0 and rms radius 1) runs the multistart of `initial`
(screened on a subsample, the EMS switches of the best, a finish on all points), or LM from a warm
start, then the robust rounds (`robust`) and the deformation choice; gradients of the fitted
parameters with respect to the points come from the implicit function theorem at the optimum
(`optimistix.ImplicitAdjoint` on `_stationarity`), never from differentiating the iterations.
`fit_padded` (segmentation's refits) and `fit_kernel` (`fitting.fit`) map it over padded batches of
problems (K, N, 3) with masks (K, N): a vmap on accelerators, a loop over cache-sized chunks on CPU.
Option modules (`fitting.FitOptions`) are static; every array is traced.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .cache import kernel_jit, persistent_kernel
from .chart import (
    BEND,
    DEFORMATION,
    EPSILON,
    LOG_SIZE,
    NUM_DEFORM,
    TRANSLATION,
    from_fields,
    pack,
    project,
    to_superquadric,
    unpack,
)
from .deformation import max_curvature
from .initial import bend_starts, initial_states, moment_starts, switched, taper_starts
from .lm import capped, cost_of, levenberg_marquardt
from .padding import fit_chunk
from .parallel import shard
from .robust import reweighted, robust_scores
from .superquadric import distance


def _best(states, costs, convs, scores=None):
    """The candidate of lowest `scores` (default: the costs); non-finite ones never win."""
    scores = costs if scores is None else scores
    i = jnp.argmin(jnp.where(jnp.isfinite(scores) & jnp.isfinite(costs), scores, jnp.inf))
    return jax.tree.map(lambda v: v[i], states), costs[i], convs[i]


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
    compared by their truncated cost (`robust.robust_scores`); the finish on all points is left to `_solve`'s
    reweighting."""
    N = points.shape[1]
    n_sub = N if opts.screen_points is None else min(N, opts.screen_points)
    sub_pts, sub_mask = _subsample(points, mask, n_sub) if n_sub < N else (points, mask)
    half = max(opts.max_steps // 2, 1)

    def run(states, n):
        out = jax.vmap(lambda s: levenberg_marquardt(s, sub_pts, sub_mask, opts, n))(states)
        if opts.robust:
            out = jax.vmap(lambda s: reweighted(s, sub_pts, sub_mask, opts)[:3])(out[0])
        return out

    def pick(out):
        scores = robust_scores(out[0], sub_pts, sub_mask, opts) if opts.robust else None
        return _best(*out, scores=scores)

    best = pick(run(initial_states(points, mask, opts.starts, opts.epsilon_starts), opts.max_steps))
    second = run(switched(best[0]), half)
    best = pick(jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), best, second))
    if n_sub == N or opts.robust:
        return best
    return levenberg_marquardt(best[0], points, mask, opts, half)


def _solve(inputs):
    points, mask, theta0, opts, _ = inputs  # the adjoint appends a while-loop implementation
    if theta0 is not None and theta0.ndim == 2:  # several warm starts: the best (deformed: off its bounds)
        lm = lambda th: levenberg_marquardt(unpack(th, opts.deform), points, mask, opts, opts.max_steps)
        out = jax.vmap(lm)(theta0)
        scores = None
        if opts.deform:
            ok = jax.vmap(lambda *s: _off_bounds(pack(*s, deform=True)))(*out[0])
            scores = jnp.where(ok, out[1], jnp.inf)
        state, cost, conv = _best(*out, scores=scores)
    elif theta0 is not None:
        state, cost, conv = levenberg_marquardt(unpack(theta0, opts.deform), points, mask, opts, opts.max_steps)
    elif opts.multistart:
        state, cost, conv = _multistart(points, mask, opts)
    else:
        first = jax.tree.map(lambda v: v[0], moment_starts(points, mask))
        state, cost, conv = levenberg_marquardt(first, points, mask, opts, opts.max_steps)
    weight = mask.astype(points.dtype)
    if opts.robust:
        state, cost, conv, weight = reweighted(state, points, mask, opts)
    return pack(*state, deform=opts.deform), (cost, conv, weight)


def _stationarity(theta, aux, inputs):
    """Projected-gradient optimality condition; zero at a (bound-constrained) minimum of G.

    With `robust`, of the weighted G with the final weights held fixed (aux)."""
    points, mask, _, opts, _ = inputs
    weight = aux[2] if opts.robust else None
    grad = jax.grad(lambda th: cost_of(unpack(th, opts.deform), points, mask, opts, weight))(theta)
    _, _, R, t, _ = unpack(theta, opts.deform)
    step = project(theta - grad, opts.epsilon_range, opts.deform)
    step = step.at[LOG_SIZE].set(capped(step[LOG_SIZE], R, t, points, mask, opts))
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


BEND_BRACKET = (0.5, 1.5)
"""`fit_one` also starts the bend along the undeformed fit's own z at these multiples of its estimated
curvature (`initial.bend_starts`, a second-order estimate): a bent start's basin is narrow (from plain
optima 1% apart in cost the same start ended at 0.018 and 0.37). `benchmarks/fit.py --suites deform`
bent truths >= 0.95: 75% -> 78% (other draws 81 -> 82%, 69 -> 71%); bracketing every axis's start
as well: 78%, 83%, 72% for 1.4x the time of this one."""

DEFORMED_ROUNDS = 2
"""Rounds of deformed starts in `fit_one` (a third gained nothing on `benchmarks/fit.py --suites deform`)."""

BOUND_TOLERANCE = 1e-3
"""A deformation within this fraction of its range's end sits on the bound (`_off_bounds`)."""


def _off_bounds(theta):
    """Whether theta's deformation lies inside its valid range (`chart.clip_deformation`), off its
    bounds: one on a bound is not a deformed superquadric the data chose but the edge of the family
    (tapering to a point, a bend folding the solid), and is not kept (issue 14)."""
    d, la, e = theta[DEFORMATION], theta[LOG_SIZE], theta[EPSILON]
    k_max = max_curvature(la, e[1], d[:2], d[3])
    return jnp.all(jnp.abs(d[:2]) < 1.0 - BOUND_TOLERANCE) & (d[2] < (1.0 - BOUND_TOLERANCE) * k_max)


def fit_one(points, mask, theta0, opts, stand_in: bool = False):
    """Fit one padded problem; points (N, 3) with mask (N,); theta0 (P,) or None (original units).
    `stand_in`: a problem with no valid point is solved on the unit sphere (`fit`'s batches may hold
    empty problems; segmentation's never do, and its compiled kernel stays as it was)."""
    dtype = points.dtype
    w = mask.astype(dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    centre = jnp.sum(jnp.where(mask[:, None], points, 0.0), 0) / n
    centred = jnp.where(mask[:, None], points - centre, 0.0)
    scale = jnp.sqrt(jnp.sum(centred * centred) / n + jnp.finfo(dtype).tiny)
    scale = jnp.where(scale > 0, scale, 1.0)
    pn = (centred / scale).T
    if theta0 is not None:  # original units -> normalised chart
        theta0 = theta0.at[LOG_SIZE].add(-jnp.log(scale)).at[TRANSLATION].set((theta0[TRANSLATION] - centre) / scale)
        if opts.deform:
            theta0 = theta0.at[BEND.start].multiply(scale)
    # A problem with no valid point (a batch's empty slot) is solved on a stand-in, the unit sphere, so
    # that its fit and the adjoint's linear solve stay finite: lineax refuses NaN input, and one empty
    # problem failed the gradient of the whole batch. `fit` flags it (too few points) as before.
    valid = mask  # the distances below: none for a stand-in
    if stand_in:
        empty = ~jnp.any(mask)
        pn = jnp.where(empty, _unit_sphere(points.shape[0], dtype), pn)
        mask = mask | empty
    adjoint = optx.ImplicitAdjoint(lx.AutoLinearSolver(well_posed=False))  # SVD: a sphere's pose is not unique
    theta, (cost, conv, weight) = adjoint.apply(_solve, _stationarity, (pn, mask, theta0, opts), frozenset())
    if opts.deform:  # deformations only where they pay for themselves: nested models
        plain = dataclasses.replace(opts, deform=False)
        th0 = None if theta0 is None else theta0[: plain.num_params]
        theta_u, aux_u = adjoint.apply(_solve, _stationarity, (pn, mask, th0, plain), frozenset())
        # the deformed model also starts from the undeformed optimum (zero deformation), so that its
        # gain over it measures what the 4 parameters add, not a better local minimum; and from that
        # optimum bent along its centre line and tapered along its width, each axis in turn
        # (`initial.bend_starts`, `initial.taper_starts`; the first bend bracketed, `BEND_BRACKET`). A
        # second round starts likewise from the best deformed fit of the first: the bend and taper read
        # in its frame are nearer the part's.
        flat = jnp.concatenate([theta_u, jnp.zeros(NUM_DEFORM, dtype)])
        choose = lambda flag, a, b: jax.tree.map(lambda u, v: jnp.where(flag, u, v), a, b)

        def deformed_round(carry, _):
            best, ok, base = carry
            undeformed = unpack(base[: plain.num_params], False)
            bent, tapered = (
                jax.vmap(lambda *s: pack(*s, deform=True))(*make(undeformed, pn, mask))
                for make in (bend_starts, taper_starts)
            )
            bracket = [bent[:1].at[:, BEND.start].multiply(f) for f in BEND_BRACKET]
            starts = jax.lax.stop_gradient(jnp.concatenate([base[None], bent, tapered, *bracket]))
            nested = adjoint.apply(_solve, _stationarity, (pn, mask, starts, opts), frozenset())
            # the cheaper of the two deformed fits, of those off their bounds (`_off_bounds`)
            better = _off_bounds(nested[0]) & (~ok | (nested[1][0] < best[1][0]))
            best = choose(better, nested, best)
            return (best, ok | better, best[0]), None

        carry = ((theta, (cost, conv, weight)), _off_bounds(theta), flat)
        ((theta, (cost, conv, weight)), ok, _), _ = jax.lax.scan(deformed_round, carry, None, DEFORMED_ROUNDS)
        keep = _deformation_pays(cost, aux_u[0], n) & ok  # the chosen one is off its bounds
        theta, (cost, conv, weight) = choose(keep, (theta, (cost, conv, weight)), (flat, aux_u))
    theta = theta.at[LOG_SIZE].add(jnp.log(scale)).at[TRANSLATION].set(theta[TRANSLATION] * scale + centre)
    if opts.deform:
        theta = theta.at[BEND.start].divide(scale)
    cost = cost * scale ** (3 if opts.residual == "size_weighted" else 2)  # f ~ sqrt(a1 a2 a3); d ~ length
    sq = to_superquadric(theta, opts.deform)
    dist = jnp.where(valid, distance(sq, points), 0.0)
    return theta, cost, conv, dist, weight


def _unit_sphere(n: int, dtype):
    """(3, n) points spread over the unit sphere (a Fibonacci lattice): a well-posed stand-in problem."""
    i = jnp.arange(n, dtype=dtype) + 0.5
    z = 1.0 - 2.0 * i / n
    r = jnp.sqrt(jnp.maximum(1.0 - z * z, 0.0))
    phi = i * jnp.pi * (3.0 - jnp.sqrt(jnp.asarray(5.0, dtype)))
    return jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi), z])


def map_problems(points, mask, theta0, opts, stand_in: bool = False):
    """`fit_one` over the leading axis: one vmap on accelerators; on CPU a loop over small chunks
    (`padding.fit_chunk`).

    A chunk's points and every intermediate of its LM steps then stay in cache, which on CPU is worth
    more than the width of one huge vmap.
    """
    K, N = points.shape[:2]
    if jax.default_backend() != "cpu":
        one = lambda p, m, t: fit_one(p, m, t, opts, stand_in)
        return jax.vmap(one, in_axes=(0, 0, None if theta0 is None else 0))(points, mask, theta0)
    multistart = theta0 is None and opts.multistart  # its candidates run side by side on the screened points
    screen = opts.screening(warm=theta0 is not None)  # the deformed rounds run on every point, as a warm start
    screened = N if screen is None else min(N, screen)
    chunk = fit_chunk(K, N, opts.num_candidates if multistart else 1, screened)
    return jax.lax.map(lambda a: fit_one(a[0], a[1], a[2], opts, stand_in), (points, mask, theta0), batch_size=chunk)


def padded_problems(points, mask, theta0, opts):
    """points (K, N, 3), mask (K, N), theta0 (K, P) or None -> theta, cost, converged, distance.

    `theta` is the global chart [log a, e, rotation vector, t, (Kx, Ky, k, alpha)]."""
    return map_problems(points, mask, theta0, opts)[:4]


fit_padded = persistent_kernel(kernel_jit(padded_problems, filter=True))
"""The batch kernel of segmentation's refits: one compiled call per (K, N, dtype, options), its lowered
form kept on disk with the compilation cache (`cache.persistent_kernel`)."""


def fit_problems(points, mask, init, opts):
    """Everything `fit` needs from the device in one traced function: (sq fields, cost, conv, dist, weight, init_ok)."""
    theta0, init_ok = (
        (None, jnp.ones(points.shape[:1], bool)) if init is None else from_fields(init, opts.epsilon_range, opts.deform)
    )
    theta, cost, conv, dist, weight = map_problems(points, mask, theta0, opts, stand_in=True)
    sq = to_superquadric(theta, opts.deform)
    return (sq.size, sq.epsilon, sq.rotation, sq.translation, sq.taper, sq.bend), cost, conv, dist, weight, init_ok


fit_kernel = persistent_kernel(kernel_jit(fit_problems, filter=True, fast_compile=False))
"""The kernel `fit` calls: one compile per (padded K, padded N, dtype, options, init or not), with XLA's
default emitters (`cache.kernel_jit`: run on whole batches, its throughput matters more than its compile)."""


def _split_over_devices(problems, fast_compile: bool = True):
    """`problems(points, mask, start, opts)` jitted with the problems split over every local CPU device
    (`parallel.shard`; the start, when given, split with them); `fast_compile` as `cache.kernel_jit`.
    Kept on disk as the other kernels are (`cache.persistent_kernel`), named after `problems`."""

    def run(points, mask, start, opts):
        body = lambda p, m, s: problems(p, m, s, opts)
        return shard(body, (True, True, start is not None))(points, mask, start)

    name = f"{problems.__module__}.{problems.__qualname__}.split"
    return persistent_kernel(kernel_jit(run, filter=True, fast_compile=fast_compile), name=name)


fit_sharded = _split_over_devices(fit_problems, fast_compile=False)
"""`fit_kernel` with the problems split over the CPU devices."""
fit_padded_sharded = _split_over_devices(padded_problems)
"""`fit_padded` with the problems split over the CPU devices."""
