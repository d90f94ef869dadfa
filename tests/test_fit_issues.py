"""Regression tests of issues 14 and 15 for `fit`: outliers, compiles per N, far from the origin,
NaN under tracing, quality flags, garbage input.

The problems are small (N <= 256) and share a few option sets so that the file compiles few kernels.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sqjax import Superquadric, lm, solver
from sqjax.evaluate import volume_iou_batch
from sqjax.fitting import FitOptions, fit
from sqjax.status import Status

from helpers import params, quick_jit, random_problem, random_rotation, volume_iou

FAST = dict(max_steps=8, multistart=False)  # one start: small kernels for the tests of plumbing


def with_outliers(pts, frac, seed=0):
    """Replace a fraction of each problem's points by uniform points in its bounding box."""
    rng = np.random.default_rng(seed)
    out, idx_all = pts.copy(), []
    for k in range(len(pts)):
        lo, hi = pts[k].min(0), pts[k].max(0)
        idx = rng.choice(pts.shape[1], int(round(frac * pts.shape[1])), replace=False)
        out[k, idx] = lo + (hi - lo) * rng.random((len(idx), 3))
        idx_all.append(idx)
    return out, idx_all


@pytest.fixture(scope="module")
def outlier_batch():
    rng = np.random.default_rng(14)
    problems = [random_problem(rng, n=200) for _ in range(16)]
    truth = [p[0] for p in problems]
    clean = np.stack([p[1] for p in problems])
    dirty, idx = with_outliers(clean, 0.10, seed=3)
    return truth, clean, dirty, idx, fit(dirty, robust=True), fit(dirty), fit(clean, robust=True)


def test_robust_fit_survives_ten_percent_outliers(outlier_batch):
    """https://github.com/sqjax/sqjax/issues/14: 10 % uniform outliers broke ~40 % of the fits."""
    truth, _, _, _, robust, plain, _ = outlier_batch
    iou_r = np.array([volume_iou(truth[k], params(robust.superquadric, k)) for k in range(len(truth))])
    iou_p = np.array([volume_iou(truth[k], params(plain.superquadric, k)) for k in range(len(truth))])
    # measured on these 16 problems: robust median 0.77 (2 below 0.5); plain least squares far lower.
    # Not yet the target (<= 5 % gross failures at 10 %): see the report of the change.
    assert np.median(iou_r) > np.median(iou_p) + 0.05, (iou_r, iou_p)
    assert np.median(iou_r) > 0.7 and np.sum(iou_r < 0.5) <= 3, iou_r


def test_weights_mark_the_outliers(outlier_batch):
    truth, clean, dirty, idx, robust, _, _ = outlier_batch
    w = np.asarray(robust.weight)
    assert w.shape == dirty.shape[:2] and np.all((w >= 0) & (w <= 1))
    good = [k for k in range(len(truth)) if volume_iou(truth[k], params(robust.superquadric, k)) > 0.8]
    out_w = np.concatenate([w[k, idx[k]] for k in good])
    in_mask = np.ones(w.shape, bool)
    for k in range(len(truth)):
        in_mask[k, idx[k]] = False
    in_w = np.concatenate([w[k][in_mask[k]] for k in good])
    # an outlier drawn in the box may land on the surface: most, not all, get a small weight
    assert np.median(out_w) < 0.05 and np.mean(out_w < 0.5) > 0.7, out_w
    assert np.median(in_w) > 0.8 and np.mean(in_w > 0.5) > 0.9


def test_non_robust_weights_are_the_mask(outlier_batch):
    plain = outlier_batch[5]
    assert np.all(np.asarray(plain.weight) == 1.0)


def _count_compiles(fn):
    from jax._src import dispatch, monitoring

    events = []

    def listener(name, secs, **kw):
        if name == dispatch.BACKEND_COMPILE_EVENT:
            events.append(secs)

    monitoring.register_event_duration_secs_listener(listener)
    try:
        fn()
    finally:
        monitoring.unregister_event_duration_listener(listener)
    return len(events)


def test_one_compile_per_bucket_over_twenty_sizes():
    """https://github.com/sqjax/sqjax/issues/14: one call per problem with a new N compiled ~six small
    host-side ops each time. Now every N of one bucket reuses one compiled kernel and nothing else compiles."""
    rng = np.random.default_rng(1)
    _, pts = random_problem(rng, n=64)
    opts = FitOptions(max_steps=3, multistart=False, robust=True)  # a compile-cache key of its own
    fit(pts[:33], options=opts)  # warm: the (1, 128) kernel
    fit(pts[:33], options=opts, init=Superquadric.create([1.0, 1.0, 1.0]))  # and the warm-start one
    sizes = range(40, 60)

    def loop():
        for n in sizes:
            r = fit(pts[:n], options=opts)
            jax.block_until_ready(r)
            assert r.distance.shape == (n,) and r.weight.shape == (n,)
        for n in (41, 57):
            jax.block_until_ready(fit(pts[:n], options=opts, init=Superquadric.create([1.0, 1.0, 1.0])))

    assert _count_compiles(loop) == 0


def test_far_from_origin_float64():
    """https://github.com/sqjax/sqjax/issues/15: float64 points were cast to float32 before centring,
    so fit(pts + 5e6) was 25 % off. Now centred in float64 on the host first."""
    rng = np.random.default_rng(4)
    _, pts = random_problem(rng, n=120)
    with jax.enable_x64(True):
        ref = fit(pts, dtype=jnp.float64, **FAST)
        far = fit(pts + 1e7, dtype=jnp.float64, **FAST)
        assert np.allclose(np.asarray(far.superquadric.size), np.asarray(ref.superquadric.size), atol=1e-3)
        assert np.allclose(
            np.asarray(far.superquadric.translation) - 1e7, np.asarray(ref.superquadric.translation), atol=1e-3
        )
    # float32 output, float64 input far away: the shape is as good as at the origin
    far32, ref32 = fit(pts + 1e7, **FAST), fit(pts, **FAST)
    assert np.allclose(np.asarray(far32.superquadric.size), np.asarray(ref32.superquadric.size), rtol=1e-3)
    # float32 input far away: centred (in float32) before anything else; the shape survives
    p32 = (pts + 1e4).astype(np.float32)
    r = fit(p32, **FAST)
    assert (
        volume_iou(
            params(ref32.superquadric),
            (
                params(r.superquadric)[0],
                params(r.superquadric)[1],
                params(r.superquadric)[2],
                params(r.superquadric)[3] - 1e4,
            ),
        )
        > 0.9
    )


def test_nan_row_under_grad_and_jit():
    """https://github.com/sqjax/sqjax/issues/15: one NaN row under jax.grad gave a lineax traceback,
    under jax.jit NaN parameters. Now rows are masked by jnp.where before any arithmetic."""
    rng = np.random.default_rng(5)
    _, pts = random_problem(rng, n=100)
    bad = pts.copy()
    bad[7] = np.nan
    ref = fit(pts[np.arange(100) != 7], **FAST)

    def loss(p):
        return jnp.sum(fit(p, **FAST).superquadric.size)

    jitted = quick_jit(lambda p: fit(p, **FAST))(jnp.asarray(bad, jnp.float32))
    assert np.all(np.isfinite(np.asarray(jitted.superquadric.size)))
    assert np.allclose(np.asarray(jitted.superquadric.size), np.asarray(ref.superquadric.size), rtol=2e-2)
    assert int(jitted.num_points) == 99 and float(jitted.weight[7]) == 0.0
    g = quick_jit(jax.grad(loss))(jnp.asarray(bad, jnp.float32))
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g)[7] == 0.0)


def test_too_few_points_under_tracing_is_flagged():
    """Under jit the minimum-points check cannot raise: the status says so and converged is False."""
    rng = np.random.default_rng(6)
    _, pts = random_problem(rng, n=40)
    mask = np.arange(40) < 5
    r = quick_jit(lambda p, m: fit(p, m, **FAST))(jnp.asarray(pts, jnp.float32), jnp.asarray(mask))
    assert int(r.status) & Status.TOO_FEW_POINTS and not bool(r.converged)
    assert np.all(np.isfinite(np.asarray(r.superquadric.size)))
    with pytest.raises(ValueError, match="too few"):
        fit(pts, mask, **FAST)


def test_garbage_is_flagged_not_converged():
    """https://github.com/sqjax/sqjax/issues/15: converged=True on garbage."""
    same = np.ones((100, 3))
    r = fit(same, **FAST)
    assert int(r.status) & Status.DEGENERATE and not bool(r.converged)
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(r.superquadric))
    line = np.linspace(0, 1, 100)[:, None] * np.array([1.0, 2.0, 3.0])
    assert int(fit(line, **FAST).status) & Status.DEGENERATE


@pytest.mark.parametrize("value", [1e15, 1e20, 1e30])
def test_one_far_row_is_dropped_and_flagged(value):
    """One depth pixel at 1e30 ruined a fit (centring on the mean): median centre, the row dropped."""
    rng = np.random.default_rng(8)
    truth, pts = random_problem(rng, n=100)
    ref = fit(np.delete(pts, 3, 0), **FAST)  # the same fit without that row
    bad = pts.copy()
    bad[3] = value
    r = fit(bad, **FAST)
    assert int(r.status) & Status.FAR_POINTS and float(r.weight[3]) == 0.0 and int(r.num_points) == 99
    assert volume_iou(params(ref.superquadric), params(r.superquadric)) > 0.95
    assert all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(r))


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("size", [np.nan, 1.0, 1.0], "init.size must be finite"),
        ("size", [0.0, 1.0, 1.0], "init.size must be > 0"),
        ("translation", [np.nan, 0.0, 0.0], "init.translation must be finite"),
    ],
)
def test_bad_warm_start_raises_naming_the_field(field, value, message):
    pts = np.random.default_rng(0).normal(size=(50, 3))
    good = Superquadric.create([1.0, 1.0, 1.0])
    init = Superquadric(
        **{
            **{k: getattr(good, k) for k in ("size", "epsilon", "rotation", "translation", "taper", "bend")},
            field: jnp.asarray(value),
        }
    )
    with pytest.raises(ValueError, match=message):
        fit(pts, init=init, **FAST)


def test_bad_warm_start_under_tracing_is_flagged():
    pts = np.random.default_rng(0).normal(size=(50, 3)) * np.array([1.0, 0.6, 0.3])

    def run(size):
        init = Superquadric.create([1.0, 1.0, 1.0])
        init = Superquadric(size, init.epsilon, init.rotation, init.translation, init.taper, init.bend)
        return fit(pts, init=init, **FAST)

    r = jax.jit(run)(jnp.asarray([0.0, 1.0, 1.0]))
    assert int(r.status) & Status.DEGENERATE and not bool(r.converged)
    assert np.all(np.isfinite(np.asarray(r.superquadric.size)))


def test_status_describe():
    assert Status.describe(0) == "OK"
    assert Status.describe(Status.MAX_STEPS | Status.FAR_POINTS) == "MAX_STEPS|FAR_POINTS"


def test_clean_fits_are_ok_and_converged(outlier_batch):
    """The robust fit of clean data (the same 16 problems without outliers; the same compiled kernel)."""
    r = outlier_batch[6]
    for k in range(len(r.cost)):
        assert Status.describe(r.status[k]) in ("OK", "BOUND_ACTIVE"), (k, Status.describe(r.status[k]))
    assert np.all(np.asarray(r.converged))
    assert np.all(np.mean(np.asarray(r.weight) > 0.5, 1) > 0.95)


def test_segmentation_kernel_unchanged_by_default_options():
    """`fit_padded` with the segmentation's options keeps its old behaviour: robust is off there."""
    assert FitOptions().robust is False
    assert FitOptions(max_steps=4, multistart=False).robust is False
    rng = np.random.default_rng(10)
    _, pts = random_problem(rng, n=64)
    opts = FitOptions(max_steps=4, multistart=False)
    theta, cost, conv, dist = solver.fit_padded(
        jnp.asarray(pts[None], jnp.float32), jnp.ones((1, 64), bool), None, opts
    )
    assert theta.shape == (1, 11) and cost.shape == (1,) and dist.shape == (1, 64)


# the five thin boxy slabs of issue 14, seen face-on: (sizes, (e1, e2)), the smallest size along z
SLABS = [
    ((2.0, 1.5, 0.30), (0.5, 0.33)),
    ((2.4, 1.8, 0.35), (0.4, 0.40)),
    ((1.5, 1.5, 0.41), (0.3, 0.49)),
    ((2.2, 1.6, 0.38), (0.6, 0.45)),
    ((1.8, 1.7, 0.33), (0.35, 0.36)),
]


@pytest.fixture(scope="module")
def slabs():
    from sqjax.mesh import sample_surface

    truth = [Superquadric.create(size, eps) for size, eps in SLABS]
    pts = np.stack(
        [
            sample_surface(sq, 300, seed=k, noise=0.01 * float(np.mean(SLABS[k][0])), viewpoint=(0.3, -0.2, 10.0))
            for k, sq in enumerate(truth)
        ]
    )
    return truth, pts


def _thickness(sq):
    """Half-size along world z of each model of a batched fit (K,)."""
    size, R = np.asarray(sq.size), np.asarray(sq.rotation)
    return np.array([size[k][np.argmax(np.abs(R[k][2]))] for k in range(len(size))])


def test_thin_slabs_seen_face_on_keep_their_thickness(slabs):
    """The distance residual recovers each slab's thickness within 25% (median within 10%); the paper's
    size-weighted residual makes them 1.5-2.6x too thick, and it is its cost, not the optimiser, that
    prefers the thick answer: the thick fit costs less than the truth under eq. 7."""
    truth, pts = slabs
    true_t = np.array([s[0][2] for s in SLABS])
    ratio = _thickness(fit(pts).superquadric) / true_t
    assert np.all(np.abs(ratio - 1.0) < 0.25) and abs(np.median(ratio) - 1.0) < 0.1, ratio

    sw = fit(pts, residual="size_weighted")
    assert np.median(_thickness(sw.superquadric) / true_t) > 1.4
    from sqjax import residual

    for k, sq in enumerate(truth):
        cost_truth = float(np.sum(np.asarray(residual(sq, jnp.asarray(pts[k], jnp.float32))) ** 2))
        assert float(sw.cost[k]) < cost_truth


@pytest.mark.parametrize("kind", ["box", "sphere"])
def test_distance_residual_is_exact_on_box_faces_and_spheres(kind):
    """The residual is the signed distance to the surface, inside and outside, where the root form of F
    is linear along the normal: the face of a box (away from its edges) and a sphere."""
    eps = (0.1, 0.1) if kind == "box" else (1.0, 1.0)
    la = jnp.log(jnp.array([2.0, 1.5, 1.0]) if kind == "box" else jnp.full(3, 1.3))
    e = jnp.array(eps)
    d = jnp.linspace(-0.3, 0.3, 13)
    if kind == "box":  # along the normal of the z face, near its middle
        pts = jnp.stack([jnp.full_like(d, 0.2), jnp.full_like(d, -0.1), 1.0 + d])
    else:  # along a ray through the centre
        u = jnp.array([1.0, 2.0, -2.0]) / 3.0
        pts = (1.3 + d)[None, :] * u[:, None]
    r = jax.vmap(lm.residual_point, in_axes=(0, 0, 0, None, None, None, None))(
        pts[0], pts[1], pts[2], la, e, jnp.zeros(4), False
    )
    np.testing.assert_allclose(np.asarray(r), np.asarray(d), atol=2e-3 if kind == "box" else 1e-5)


def test_residual_option_is_validated():
    with pytest.raises(ValueError, match="residual"):
        FitOptions(residual="eq7")


@pytest.mark.slow
def test_deformations_kept_only_when_they_shorten_the_description():
    """https://github.com/sqjax/sqjax/issues/14: `deform=True` fits the undeformed model too and keeps
    the 4 deformation parameters only when n log(cost_plain / cost_deformed) > 4 log n (BIC). Every
    fit either carries no deformation at all and equals the plain fit, or beats the plain fit's cost by
    that margin; a clearly tapered truth (the last problem) keeps its tapering."""
    from sqjax.mesh import sample_surface

    rng = np.random.default_rng(21)
    n = 200
    tapered = Superquadric.create((0.8, 0.8, 2.0), (0.5, 0.5), taper=(0.6, 0.6))
    pts = np.stack(
        [random_problem(rng, n=n)[1] for _ in range(7)]
        + [sample_surface(tapered, n, seed=3, noise=0.005, viewpoint=np.array([10.0, 2.0, 1.0]))]
    )
    opts = dict(multistart=False, max_steps=12)  # one start: a small kernel to compile
    plain, deformed = fit(pts, **opts), fit(pts, deform=True, **opts)  # one batch: one compile each
    for k in range(len(pts)):
        d = np.concatenate([np.asarray(deformed.superquadric.taper[k]), np.asarray(deformed.superquadric.bend[k])])
        if np.all(d == 0.0):
            np.testing.assert_allclose(
                np.asarray(deformed.superquadric.size[k]), np.asarray(plain.superquadric.size[k]), rtol=1e-4
            )
        else:
            assert n * np.log(float(plain.cost[k]) / float(deformed.cost[k])) > 4 * np.log(n)
    assert np.any(np.asarray(deformed.superquadric.taper[-1]) != 0.0)


@pytest.mark.parametrize("deformation", [dict(taper=(0.7, -0.6)), dict(bend=(0.45, 0.7))])
def test_distance_of_a_deformed_model_is_in_world_units(deformation):
    """`signed_distance` of a tapered or bent model matches the distance to a dense sample of its surface
    (median within 5%, 95% within 25%, for points 0.02-0.1 outside; first order): the undeformed
    frame's distance is divided by the stretch of the undeforming map."""
    from sqjax.mesh import sample_surface
    from sqjax.superquadric import signed_distance

    sq = Superquadric.create((0.6, 0.8, 1.5), (0.6, 0.8), **deformation)
    dense = sample_surface(sq, 60_000, seed=1)
    rng = np.random.default_rng(2)
    base = sample_surface(sq, 200, seed=3)
    grad = jax.vmap(jax.grad(lambda p: signed_distance(sq, p)))(jnp.asarray(base, jnp.float32))
    normal = np.asarray(grad) / np.linalg.norm(np.asarray(grad), axis=1, keepdims=True)
    off = rng.uniform(0.02, 0.1, (200, 1))
    q = base + off * normal
    truth = np.min(np.linalg.norm(q[:, None] - dense[None], axis=-1), axis=1)
    d = np.asarray(signed_distance(sq, jnp.asarray(q, jnp.float32)))
    err = np.abs(d / truth - 1.0)
    assert np.median(err) < 0.05 and np.quantile(err, 0.95) < 0.25, np.quantile(err, [0.5, 0.95])


@pytest.mark.parametrize("alpha", [0.0, 2.0, -1.2])
def test_bend_starts_read_the_bend_from_the_centre_line(alpha):
    """From an unbent solution in the part's frame, the first of `initial.bend_starts` has the bend of
    the points' centre line: curvature within 15% and the bending plane within 0.15 rad of the truth
    (the second-order parabola of the bend, k a3 = 0.6); the other two bend about the other axes."""
    from sqjax.initial import bend_starts
    from sqjax.mesh import sample_surface

    k = 0.6 / 1.5
    sq = Superquadric.create((0.5, 0.4, 1.5), (0.5, 0.8), bend=(k, alpha))
    pts = jnp.asarray(sample_surface(sq, 3000, seed=1).T, jnp.float32)
    state = (jnp.log(jnp.array([0.7, 0.6, 1.5])), jnp.array([0.5, 0.8]), jnp.eye(3), jnp.zeros(3), jnp.zeros(4))
    la, e, R, t, d = bend_starts(state, pts, jnp.ones(pts.shape[1], bool))
    assert la.shape == (3, 3) and R.shape == (3, 3, 3) and np.all(np.asarray(d[:, :2]) == 0.0)
    assert abs(float(d[0, 2]) / k - 1.0) < 0.15
    assert abs(float(jnp.angle(jnp.exp(1j * (d[0, 3] - alpha))))) < 0.15
    np.testing.assert_allclose(np.asarray(R[0]), np.eye(3))


def _deformed_views(kind: str, count: int, seed: int):
    """`count` one-view problems (200 points, 1% noise, random pose and viewpoint) of tapered (|Kx|, |Ky|
    in 0.3-0.7, either sign) or bent (k a3 in 0.3-0.8) truths elongated along z, drawn as `benchmarks/fit.py
    --suites deform` draws them: the batched truths and the points (count, 200, 3)."""
    from sqjax.mesh import sample_surface

    rng = np.random.default_rng(seed)
    truths, pts = [], []
    for i in range(count):
        size = np.concatenate([rng.uniform(0.5, 1.0, 2), rng.uniform(1.5, 2.0, 1)])
        eps, R = rng.uniform(0.3, 1.2, 2), random_rotation(rng)
        taper = rng.uniform(0.3, 0.7, 2) * rng.choice([-1, 1], 2) if kind == "tapered" else np.zeros(2)
        bend = (rng.uniform(0.3, 0.8) / size[2], rng.uniform(-np.pi, np.pi)) if kind == "bent" else (0.0, 0.0)
        sq = Superquadric.create(size, eps, rotation=R, taper=taper, bend=bend)
        view = rng.normal(size=3)
        view = 10 * view / np.linalg.norm(view)
        truths.append(sq)
        pts.append(sample_surface(sq, 200, seed=i, noise=0.01 * size.mean(), viewpoint=view))
    return jax.tree.map(lambda *v: jnp.stack(v), *truths), np.stack(pts)


@pytest.mark.slow
def test_bent_truths_are_recovered_in_any_bending_plane():
    """https://github.com/sqjax/sqjax/issues/14: one-view points (200, 1% noise) of bent truths drawn as
    `benchmarks/fit.py --suites deform` draws them are fitted with `deform=True` to volume IoU >= 0.95
    and their curvature k a3 within 20%. Two problems of that draw (seed 1, the 4th and the 15th) whose
    fits reached only 0.48 and 0.89 from the unbent optimum and the multistart: at k = 0 the cost does
    not depend on the bending plane, and LM found no bend out of alpha = 0 (`initial.bend_starts`)."""
    truths, pts = _deformed_views("bent", 15, seed=1)
    stacked = jax.tree.map(lambda v: v[np.array([3, 14])], truths)
    out = fit(pts[[3, 14]], deform=True)
    iou = np.asarray(volume_iou_batch(stacked, out.superquadric, n=20_000))
    assert np.all(iou >= 0.95), iou
    ka = np.asarray(out.superquadric.bend[:, 0] * out.superquadric.size[:, 2])
    np.testing.assert_allclose(ka, np.asarray(stacked.bend[:, 0] * stacked.size[:, 2]), rtol=0.2)


@pytest.mark.parametrize("turn", [0.0, 0.7, -1.1])
def test_taper_starts_read_the_taper_in_a_turned_frame(turn):
    """From an untapered solution whose lateral axes are turned by `turn` about z (an untapered fit of a
    nearly round cross-section has them anywhere), the first of `initial.taper_starts` turns them back
    onto the part's (within 0.1 rad, modulo the quarter turns that swap or flip x and y) and reads the
    tapers along them within 0.1, for tapers of opposite sign (which cancel in a frame turned 45 degrees);
    its lateral sizes are those of the part's untapered cross-section within 15%."""
    from sqjax.initial import taper_starts
    from sqjax.mesh import sample_surface

    taper, size = np.array([0.5, -0.6]), np.array([0.5, 0.7, 1.5])
    sq = Superquadric.create(size, (0.5, 0.8), taper=taper)
    pts = jnp.asarray(sample_surface(sq, 3000, seed=1).T, jnp.float32)
    c, s = np.cos(turn), np.sin(turn)
    R0 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    state = (jnp.log(jnp.array([0.9, 0.9, 1.5])), jnp.array([0.5, 0.8]), jnp.asarray(R0), jnp.zeros(3), jnp.zeros(4))
    la, e, R, t, d = taper_starts(state, pts, jnp.ones(pts.shape[1], bool))
    assert la.shape == (3, 3) and R.shape == (3, 3, 3) and np.all(np.asarray(d[:, 2:]) == 0.0)
    lateral = np.asarray(R[0])[:2, :2]  # columns: the start's x and y axes in the part's frame
    along = np.argmax(np.abs(lateral), axis=0)  # the part's axis each one lies on
    assert sorted(along) == [0, 1] and np.all(np.abs(lateral).max(0) > np.cos(0.1)), lateral
    np.testing.assert_allclose(np.asarray(d[0, :2]), taper[along], atol=0.1)
    np.testing.assert_allclose(np.exp(np.asarray(la[0, :2])), size[along], rtol=0.15)


@pytest.mark.slow
@pytest.mark.parametrize("kind, problems", [("tapered", [55, 56]), ("bent", [4, 5])])
def test_deformed_truths_missed_from_the_first_starts_are_recovered(kind, problems):
    """https://github.com/sqjax/sqjax/issues/14: four one-view problems of one draw (seed 3) that
    `deform=True` fitted to volume IoU 0.66-0.91 with the bend starts of the untapered optimum alone: two
    tapered (their tapers not along that optimum's lateral axes) and two bent. With the taper starts
    (`initial.taper_starts`) and a second round of both kinds of start from the best deformed fit
    (`solver.fit_one`), each reaches IoU >= 0.95."""
    truths, pts = _deformed_views(kind, max(problems) + 1, seed=3)
    truths = jax.tree.map(lambda v: v[np.asarray(problems)], truths)
    out = fit(pts[problems], deform=True)
    iou = np.asarray(volume_iou_batch(truths, out.superquadric, n=20_000))
    assert np.all(iou >= 0.95), iou


@pytest.mark.parametrize(
    "e2, taper, alpha",
    [(0.3, (0.0, 0.0), 0.4), (1.0, (0.5, -0.3), 2.0), (1.7, (-0.8, 0.6), -1.0), (1.0, (0.0, 0.0), 0.0)],
)
def test_max_curvature_is_where_the_bend_would_fold_the_solid(e2, taper, alpha):
    """`deformation.max_curvature` is 1 / r_max, r_max the farthest reach of the model towards the
    bending plane (while that is below pi / a3): a dense sample of an untapered surface reaches 97-100%
    of it, none beyond, so at the bound 1 - k r > 0 on the whole solid but for its extreme points. With
    tapering it bounds the reach from above (the widest extents at both ends taken together): no point
    beyond it, the sample reaching 70% of it or more."""
    from sqjax.deformation import max_curvature
    from sqjax.mesh import sample_surface

    size = np.array([0.7, 0.4, 1.0])
    sq = Superquadric.create(size, (0.6, e2), taper=taper)
    pts = sample_surface(sq, 60_000, seed=1)
    r = pts[:, 0] * np.cos(alpha) + pts[:, 1] * np.sin(alpha)
    k = float(max_curvature(jnp.log(jnp.asarray(size)), e2, jnp.asarray(taper), alpha))
    assert k < np.pi / size[2]
    assert (0.97 if taper == (0.0, 0.0) else 0.7) <= k * r.max() <= 1.0 + 1e-4, k * r.max()
    np.testing.assert_allclose(max_curvature(np.log(size), e2, np.asarray(taper), alpha, xp=np), k, rtol=1e-5)


def test_fitted_deformations_stay_off_the_ends_of_their_range():
    """https://github.com/sqjax/sqjax/issues/14: a deformation is kept only inside its valid range,
    off its bounds (|taper| < 1, bending k below `max_curvature`): on the upper half of half a torus
    (a curved tube seen from above, no superquadric shape) the fit kept a tapering of -1, a model tapered
    to a point, and on a thin leg of the pyvista ant it kept a bend of curvature 1e9 (a cross-section
    swept round an axis, no bent superquadric) with 40x less cost. Either sits on the edge of the
    family, and the undeformed fit is returned instead."""
    import trimesh

    from sqjax.deformation import max_curvature

    tube = trimesh.creation.torus(major_radius=0.5, minor_radius=0.06)
    p, _ = trimesh.sample.sample_surface(tube, 4000, seed=1)
    p = p[(np.arctan2(p[:, 1], p[:, 0]) % (2 * np.pi) <= np.pi) & (p[:, 2] > -0.01)][:600]
    p = p + np.random.default_rng(0).normal(0.0, 0.003, p.shape)
    sq = fit(p, deform=True).superquadric
    taper, bend = np.asarray(sq.taper), np.asarray(sq.bend)
    k_max = max_curvature(np.log(np.asarray(sq.size)), float(sq.epsilon[1]), taper, bend[1], xp=np)
    assert np.all(np.abs(taper) < 1.0 - solver.BOUND_TOLERANCE), taper
    assert bend[0] < (1.0 - solver.BOUND_TOLERANCE) * k_max, (bend, k_max)


def test_max_curvature_and_its_gradient_are_finite_everywhere():
    """No NaN from `max_curvature` or its gradient for any finite input: bending planes along an axis
    (a zero reach component), exponents at and beyond the fitter's range (e2 = 2 and more: a star-shaped
    cross-section), tapering at +-1, tiny and huge sizes."""
    from sqjax.deformation import max_curvature

    grad = jax.grad(lambda *a: max_curvature(*a), argnums=(0, 1, 2, 3))
    for la in (jnp.zeros(3), jnp.array([-20.0, 3.0, 0.5]), jnp.array([5.0, -5.0, 20.0])):
        for e2 in (0.1, 1.0, 1.9, 2.0, 3.0):
            for taper in ((0.0, 0.0), (1.0, -1.0)):
                for alpha in (0.0, np.pi / 2, -np.pi, 0.7):
                    args = (la, jnp.float32(e2), jnp.asarray(taper, jnp.float32), jnp.float32(alpha))
                    k = max_curvature(*args)
                    assert np.isfinite(float(k)) and float(k) > 0.0
                    assert all(np.all(np.isfinite(np.asarray(g))) for g in grad(*args)), (la, e2, taper, alpha)
