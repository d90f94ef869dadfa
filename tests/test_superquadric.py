"""The superquadric: eq. 5 on its surface, inside/outside, NaN-safety at the hard points, volume, meshes, distances."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sqjax import rotation as so3
from sqjax.mesh import sample_surface, to_trimesh
from sqjax.superquadric import (
    Superquadric,
    contains,
    distance,
    inside_outside,
    radial_distance,
    residual,
    signed_distance,
)

SHAPES = [  # (size, epsilon, extra keywords)
    ((1.0, 0.6, 1.4), (1.0, 1.0), {}),
    ((0.8, 1.2, 0.5), (0.1, 0.1), {}),
    ((1.5, 0.7, 0.9), (1.9, 1.9), {}),
    ((0.9, 1.1, 1.3), (0.3, 1.7), {}),
    ((1.0, 0.8, 1.5), (0.6, 0.9), {"taper": (0.4, -0.3)}),
    ((0.7, 0.9, 1.6), (0.8, 0.5), {"bend": (0.5, 0.7)}),
    ((0.7, 0.9, 1.6), (0.4, 1.2), {"taper": (-0.2, 0.3), "bend": (0.3, -1.1)}),
]
POSE = {"euler": (0.4, 1.1, -2.3), "translation": (0.5, -1.0, 2.0)}


def _sq(size, eps, extra, **kw):
    return Superquadric.create(size, eps, **{**POSE, **extra, **kw})


_jit_distance = jax.jit(distance)


@jax.jit
def _unit_normals(sq, pts):
    g = jax.vmap(jax.grad(lambda p: inside_outside(sq, p)))(pts)
    return g / jnp.linalg.norm(g, axis=-1, keepdims=True)


@jax.jit
def _scaled(sq, pts, scale):
    """Points scaled about the centre in the undeformed model frame (F -> scale^2 F) and F, f, inside there."""
    from sqjax.superquadric import to_model_frame, to_world_frame

    p = to_world_frame(sq, scale * to_model_frame(sq, pts))
    return inside_outside(sq, p), residual(sq, p), contains(sq, p)


@pytest.mark.parametrize("size, eps, extra", SHAPES)
def test_surface_samples_have_f_equal_one(size, eps, extra):
    sq = _sq(size, eps, extra)
    pts = jnp.asarray(sample_surface(sq, 2000, seed=3), jnp.float32)
    F, f, _ = _scaled(sq, pts, 1.0)
    assert np.allclose(np.asarray(F), 1.0, atol=2e-5)
    assert np.abs(np.asarray(f)).max() < 1e-4


@pytest.mark.parametrize("size, eps, extra", SHAPES)
def test_inside_outside_signs(size, eps, extra):
    sq = _sq(size, eps, extra)
    surf = jnp.asarray(sample_surface(sq, 500, seed=1), jnp.float32)
    centre = sq.translation
    for scale, inside in ((0.9, True), (1.1, False)):
        F, f, ins = _scaled(sq, surf, scale)
        assert np.allclose(np.asarray(F), scale**2, rtol=1e-4)
        assert bool(jnp.all(ins == inside))
        assert bool(jnp.all((f < 0) == inside))
    assert bool(contains(sq, centre)) and float(inside_outside(sq, centre)) < 1e-6


def _hard_points(sq):
    """Model-frame hard points -> world: centre, on each axis (0 .. 2 a), far away (|x / a| = 1e3), mixed."""
    a = np.asarray(sq.size, float)
    local = [np.zeros(3)]
    for i, s in itertools.product(range(3), (1e-30, 1e-8, 0.5, 1.0, 2.0, 1e3)):
        for sign in (1.0, -1.0):
            v = np.zeros(3)
            v[i] = sign * s * a[i]
            local.append(v)
    local += [1e3 * a * np.array(d) for d in ((1, 1, 0), (1, 0, 1), (0, 1, 1), (1, -1, 1))]
    local += [a * np.array(d) for d in ((1, 1, 0), (0.3, 1e-7, 0.0), (1e-20, 1e-20, 1e-20))]
    local = jnp.asarray(np.array(local), jnp.float32)
    return local @ sq.rotation.T + sq.translation


HARD_SHAPES = [((1.0, 0.5, 2.0), e, {}) for e in itertools.product((0.1, 1.0, 1.9), repeat=2)]
HARD_SHAPES += [((1.0, 0.5, 2.0), (0.1, 1.9), {"taper": (0.5, -0.5), "bend": (0.2, 0.3)})]


FUNCTIONS = (inside_outside, residual, distance, radial_distance)


@jax.jit
def _values_and_gradients(sq, pts):
    """Every function of this module at pts; the gradients of their (squashed) sum w.r.t. each point and
    the parameters: one reverse pass, in which a NaN or inf of any of the four would show."""

    def total(s, p):
        return sum(jnp.tanh(fn(s, p)) for fn in FUNCTIONS)

    out = {fn.__name__: fn(sq, pts) for fn in FUNCTIONS}
    out["d/dpoints"] = jax.vmap(jax.grad(total, argnums=1), in_axes=(None, 0))(sq, pts)
    g = jax.grad(lambda s: jnp.sum(total(s, pts)))(sq)
    out.update(
        {f"d/d{name}": getattr(g, name) for name in ("size", "epsilon", "rotation", "translation", "taper", "bend")}
    )
    return out


@pytest.mark.parametrize("size, eps, extra", HARD_SHAPES)
def test_no_nan_at_hard_points(size, eps, extra):
    sq = _sq(size, eps, extra)
    for name, value in _values_and_gradients(sq, _hard_points(sq)).items():
        assert bool(jnp.all(jnp.isfinite(value))), name


@pytest.mark.parametrize("eps", [(1.0, 1.0), (0.5, 0.5), (0.3, 1.0), (1.0, 0.4), (1.5, 1.5)])
def test_volume_formula_matches_mesh(eps):
    sq = Superquadric.create((1.0, 0.7, 1.3), eps, **POSE)
    mesh = to_trimesh(sq, 160)
    assert mesh.is_watertight
    assert mesh.volume == pytest.approx(float(sq.volume), rel=1e-2)
    if eps == (1.0, 1.0):
        assert float(sq.volume) == pytest.approx(4 / 3 * np.pi * 1.0 * 0.7 * 1.3, rel=1e-5)


@pytest.mark.parametrize("size, eps, extra", SHAPES)
def test_mesh_is_watertight(size, eps, extra):
    mesh = to_trimesh(_sq(size, eps, extra), 32)
    assert mesh.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0


def test_point_functions_take_rows_as_lists_and_name_bad_points():
    """`distance(sq, [[...], ...])` raised JAX's "unsupported operand type(s) for -: 'list' and
    'DynamicJaxprTracer'". Nested lists of rows are points like an array; a wrong shape, ragged rows,
    strings or a first argument that is not a Superquadric get an error that names the function."""
    sq = Superquadric.create((1.0, 0.6, 1.4), (0.5, 0.8))
    rows = [[0.2, 0.1, 0.0], [2.0, 0.0, 0.0]]
    for fn in (inside_outside, residual, distance, signed_distance, radial_distance, contains):
        np.testing.assert_array_equal(np.asarray(fn(sq, rows)), np.asarray(fn(sq, np.asarray(rows, np.float32))))
    for bad, message in (
        ([[1.0, 2.0], [3.0, 4.0]], r"distance: points must have shape \(\.\.\., 3\), got \(2, 2\)"),
        ([[1.0, 2.0, 3.0], [1.0, 2.0]], "distance: points must be an array of shape"),
        (np.array(["a", "b", "c"]), "distance: points must be real numbers"),
    ):
        with pytest.raises(ValueError, match=message):
            distance(sq, bad)
    with pytest.raises(TypeError, match="distance: the first argument must be a Superquadric"):
        distance(rows, np.zeros((2, 3)))  # pyright: ignore[reportArgumentType]
    # under jit and grad as before
    g = jax.grad(lambda p: jnp.sum(distance(sq, p)))(jnp.asarray(rows))
    assert np.all(np.isfinite(np.asarray(g)))


def test_a_missing_point_has_no_value():
    """A point with a NaN coordinate (missing data) gets NaN from F, the residual and the distance, and
    is not inside; the safe operands inside the functions gave it F = 2e-20, "inside"."""
    sq = Superquadric.create((1.0, 0.6, 1.4), (0.5, 0.8))
    pts = np.array([[np.nan, 0.0, 0.0], [0.2, 0.1, 0.0], [0.0, np.nan, np.nan], [2.0, 0.0, 0.0]], np.float32)
    for fn in (inside_outside, residual, distance):
        v = np.asarray(fn(sq, pts))
        assert np.isnan(v[[0, 2]]).all() and np.isfinite(v[[1, 3]]).all()
        assert np.allclose(v[[1, 3]], np.asarray(fn(sq, pts[[1, 3]])))
    assert np.asarray(contains(sq, pts)).tolist() == [False, True, False, False]
    # an infinite coordinate likewise: (inf - t) R made NaN, which the safe operands sent to the centre
    far = np.array([[np.inf, 0.0, 0.0], [0.2, 0.1, 0.0], [0.0, -np.inf, 1.0]], np.float32)
    for fn in (inside_outside, residual, distance, signed_distance, radial_distance):
        v = np.asarray(fn(sq, far))
        assert np.isnan(v[[0, 2]]).all() and np.isfinite(v[1]), fn.__name__
    assert np.asarray(contains(sq, far)).tolist() == [False, True, False]
    assert np.isnan(np.asarray(radial_distance(sq, pts))[[0, 2]]).all()  # read 0, "on the surface"


def test_a_size_below_the_dtype_s_normal_range_is_refused():
    """A float32 size below 1.2e-38 was accepted (> 0 in float64), then flushed to 0 on CPU: F NaN at
    the centre, `contains` False there."""
    with pytest.raises(ValueError, match=r"size must lie in .*float32"):
        Superquadric.create((1e-40, 1e-40, 1e-40))
    sq = Superquadric.create((1e-30, 1e-30, 1e-30))  # small but normal: fine
    assert bool(contains(sq, np.zeros(3, np.float32)))


@pytest.mark.parametrize("unit", [1e-9, 1e-7, 1e4])
def test_a_mesh_does_not_depend_on_the_unit(unit):
    """trimesh merges vertices within an absolute 1e-8: a model in units of 1e-7 or less collapsed to
    no faces (and `sqjax segment` failed writing parts.glb). Meshed in the model's own scale, every
    unit gives the same mesh, scaled."""
    sq = Superquadric.create((1.0, 0.6, 1.4), (0.5, 0.8), euler=(0.1, 0.2, 0.3), translation=(1.0, -2.0, 3.0))
    ref = to_trimesh(sq, 24)
    scaled = to_trimesh(jax.tree.map(lambda v: v * unit if v.shape[-1:] == (3,) and v.ndim == 1 else v, sq), 24)
    assert len(scaled.faces) == len(ref.faces) and scaled.is_watertight
    assert np.allclose(scaled.vertices / unit, ref.vertices, rtol=1e-6, atol=1e-6)


def test_a_flat_part_meshes_without_networkx():
    """A part flat to 1e-10 (what a cloud of repeated points gave) is meshed and exported: outward
    normals are a sign of the grid's volume, not trimesh's winding repair, which needs networkx (not a
    dependency) for a mesh it cannot check."""
    flat = to_trimesh(Superquadric.create((0.3, 1e-10, 1e-10)), 16)
    assert np.isfinite(flat.vertices).all()
    thin = to_trimesh(Superquadric.create((0.3, 0.2, 1e-6), (0.3, 0.3), **POSE), 16)
    assert thin.volume > 0 and thin.is_winding_consistent


@pytest.mark.parametrize(
    "size, eps", [((1.0, 0.6, 1.4), (1.0, 1.0)), ((1.0, 0.6, 1.4), (0.5, 0.8)), ((0.8, 1.0, 0.6), (1.3, 0.7))]
)
def test_eq10_distance_near_surface(size, eps):
    """Points moved by h along the surface normal: eq. 10 gives h to first order."""
    sq = Superquadric.create(size, eps, **POSE)
    surf = jnp.asarray(sample_surface(sq, 400, seed=2), jnp.float32)
    normal = _unit_normals(sq, surf)
    for h in (-0.01, 0.01):
        d = np.asarray(_jit_distance(sq, surf + h * normal))
        # eq. 10 is first order: the error is a fraction of h (curvature), never of the size
        assert np.median(np.abs(d - abs(h))) < 0.05 * abs(h)
        assert np.percentile(np.abs(d - abs(h)), 90) < 0.2 * abs(h)
    assert np.max(np.asarray(_jit_distance(sq, surf))) < 1e-5


def test_radial_distance_exact_along_rays():
    """For an ellipsoid, p = c + s R u with u on the surface has radial distance |s - 1| |u|."""
    sq = Superquadric.create((1.2, 0.5, 0.8), (1.0, 1.0), **POSE)
    rng = np.random.default_rng(0)
    d = rng.standard_normal((300, 3))
    a = np.asarray(sq.size, float)
    u = d / np.sqrt(np.sum((d / a) ** 2, -1, keepdims=True))  # on the ellipsoid in the model frame
    s = rng.uniform(0.05, 3.0, (300, 1))
    world = (s * u) @ np.asarray(sq.rotation, float).T + np.asarray(sq.translation, float)
    got = np.asarray(jax.jit(radial_distance)(sq, jnp.asarray(world, jnp.float32)))
    want = np.abs(s[:, 0] - 1.0) * np.linalg.norm(u, axis=-1)
    assert np.allclose(got, want, atol=2e-5, rtol=1e-4)


def test_volume_monte_carlo_matches_formula():
    sq = Superquadric.create((1.0, 0.7, 1.3), (0.4, 1.6), **POSE)
    rng = np.random.default_rng(1)
    local = rng.uniform(-1, 1, (200_000, 3)) * np.asarray(sq.size, float)
    world = local @ np.asarray(sq.rotation, float).T + np.asarray(sq.translation, float)
    frac = float(jnp.mean(contains(sq, jnp.asarray(world, jnp.float32))))
    box = 8 * float(np.prod(np.asarray(sq.size)))
    assert frac * box == pytest.approx(float(sq.volume), rel=1e-2)


def test_one_view_samples_face_the_viewpoint():
    sq = Superquadric.create((1.0, 0.8, 0.6), (0.5, 0.5), **POSE)
    view = np.asarray(sq.translation, float) + np.array([8.0, 2.0, 1.0])
    pts = sample_surface(sq, 1000, seed=0, viewpoint=view)
    normal = np.asarray(_unit_normals(sq, jnp.asarray(pts, jnp.float32)))
    assert np.mean(np.einsum("ij,ij->i", normal, view - pts) > 0) > 0.98
    assert np.allclose(np.asarray(inside_outside(sq, jnp.asarray(pts, jnp.float32))), 1.0, atol=2e-5)


def test_create_euler_and_rotation_agree():
    a = Superquadric.create((1, 2, 3), euler=(0.1, 0.2, 0.3))
    b = Superquadric.create((1, 2, 3), rotation=so3.from_euler(jnp.array([0.1, 0.2, 0.3])))
    assert np.allclose(np.asarray(a.rotation), np.asarray(b.rotation))
    assert np.allclose(np.asarray(a.euler), [0.1, 0.2, 0.3], atol=1e-6)
    d = a.to_dict()
    assert set(d) >= {"size", "epsilon", "rotation", "euler_zyz", "translation", "taper", "bend"}


def test_indexing_a_batch_checks_its_bounds():
    """A batch indexes like a numpy array: out of range, or a single superquadric, is an IndexError
    (JAX alone clamps: B[5] of a batch of 2 returned the last model, and sq[0] a broken one)."""
    B = Superquadric.create(np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]))
    assert np.allclose(np.asarray(B[1].size), [4, 5, 6]) and np.allclose(np.asarray(B[-2].size), [1, 2, 3])
    assert B[np.array([1, 0])].size.shape == (2, 3) and B[:1].size.shape == (1, 3)
    for bad in (2, -3, np.array([0, 2]), (0, 0)):
        with pytest.raises(IndexError):
            B[bad]
    with pytest.raises(IndexError, match="no batch axis"):
        B[0][0]
    assert jax.jit(lambda i: B[i].size)(1).shape == (3,)  # a traced index is JAX's to clamp


@pytest.mark.parametrize(
    "size, eps",
    [
        ((1.0, 0.6, 1.4), (1.0, 1.0)),
        ((0.8, 1.2, 0.5), (0.1, 0.1)),
        ((1.5, 0.7, 0.9), (1.9, 1.9)),
        ((0.9, 1.1, 1.3), (0.3, 1.7)),
    ],
)
def test_segmentation_distance_kernel_matches_eq10(size, eps):
    """The closed-form eq. 10 kernel of segmentation (model, point pairs; no autodiff) gives the
    autodiff `distance` for undeformed models, and is finite at the hard points."""
    from sqjax.workspace import _pair_distances

    sq = _sq(size, eps, {})
    theta = jnp.concatenate([jnp.log(sq.size), sq.epsilon, so3.log(sq.rotation), sq.translation])[None]
    rng = np.random.default_rng(0)
    local = rng.uniform(-2.0, 2.0, (500, 3)) * np.asarray(size)
    pts = jnp.asarray(local @ np.asarray(sq.rotation).T + np.asarray(sq.translation), jnp.float32)
    hard = _hard_points(sq)
    allp = jnp.concatenate([pts, hard])
    idx = jnp.arange(allp.shape[0], dtype=jnp.int32)
    views = allp / jnp.maximum(jnp.linalg.norm(allp, axis=1, keepdims=True), 1e-6)  # camera at the origin
    d, inside, away = _pair_distances(jnp.repeat(theta, idx.size, 0), allp, views, idx, 1.15, 0.0)
    assert bool(jnp.all(jnp.isfinite(d)))
    # away: the outward normal (autodiff gradient of F) turns from the camera, n . view > 0.2
    g = jax.vmap(jax.grad(lambda p: inside_outside(sq, p)))(pts)
    cos = np.sum(np.asarray(g) * np.asarray(views[:500]), 1) / np.linalg.norm(np.asarray(g), axis=1)
    sure = np.abs(cos - 0.2) > 1e-3
    np.testing.assert_array_equal(np.asarray(away[:500])[sure], (cos > 0.2)[sure])
    assert 0 < int(np.sum(cos > 0.2)) < 500  # both kinds among the samples
    np.testing.assert_allclose(d[:500], _jit_distance(sq, pts), rtol=2e-3, atol=1e-5)
    f_big = np.asarray(inside_outside(_sq(np.asarray(size) * 1.15, eps, {}), pts))
    clear = np.abs(f_big - 1.0) > 1e-3  # not on the enlarged surface itself
    np.testing.assert_array_equal(np.asarray(inside[:500])[clear], (f_big <= 1.0)[clear])


# ----------------------------------------------------------------------------------------------------
# issue 15: construction checks, bending consistent for small k


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(size=(1.0, 0.0, 1.0)), "size"),
        (dict(size=(1.0, -2.0, 1.0)), "size"),
        (dict(size=(1.0, np.nan, 1.0)), "size"),
        (dict(size=(1.0, 1.0, 1.0), epsilon=(0.0, 1.0)), "epsilon"),
        (dict(size=(1.0, 1.0, 1.0), epsilon=(np.nan, 1.0)), "epsilon"),
        (dict(size=(1.0, 1.0, 1.0), rotation=np.diag([1.0, 1.0, 2.0])), "rotation"),
        (dict(size=(1.0, 1.0, 1.0), rotation=np.diag([1.0, 1.0, -1.0])), "rotation"),
        (dict(size=(1.0, 1.0, 1.0), translation=(0.0, np.inf, 0.0)), "translation"),
        (dict(size=(1.0, 1.0, 1.0), taper=(1.5, 0.0)), "taper"),
        (dict(size=(1.0, 1.0, 1.0), bend=(-0.1, 0.0)), "bend"),
        (dict(size=(1.0, 1.0)), "size"),
    ],
)
def test_create_rejects_bad_values_naming_the_field(kwargs, field):
    """https://github.com/sqjax/sqjax/issues/15: create accepted size <= 0, NaN, non-orthonormal rotations."""
    size = kwargs.pop("size")
    with pytest.raises(ValueError, match=field):
        Superquadric.create(size, **kwargs)


def test_create_does_not_check_traced_values():
    out = jax.jit(lambda s: Superquadric.create(s).size)(jnp.array([1.0, 0.0, 1.0]))
    assert out.shape == (3,)


@pytest.mark.parametrize("k", [0.0, 1e-9, 1e-6, 1e-5, 9e-5, 1e-4, 1.1e-4, 1e-3, 0.05])
def test_bending_round_trip_and_formula_for_small_k(k):
    """https://github.com/sqjax/sqjax/issues/15: bend_points dropped k < 1e-4 but unbend did not.

    Forward bending against the textbook formula (float64), and unbend(bend(x)) == x, in mm-sized
    coordinates (|x| up to 100) where k = 1e-4 moves points by ~0.5."""
    from sqjax.deformation import bend_points, unbend

    rng = np.random.default_rng(0)
    x = rng.uniform(-100, 100, (500, 3))
    alpha = 0.7
    with jax.enable_x64(True):
        b = jnp.array([k, alpha])
        xb = np.asarray(bend_points(jnp.asarray(x), b))
        ca, sa = np.cos(alpha), np.sin(alpha)
        r, g = x[:, 0] * ca + x[:, 1] * sa, k * x[:, 2]
        # (1/k - r)(1 - cos g) and (1/k - r) sin g, the first written without cancellation
        dR = (1 - k * r) * 2 * np.sin(g / 2) ** 2 / k if k > 0 else 0 * r
        Z = (1 - k * r) * np.sin(g) / k if k > 0 else x[:, 2]
        assert np.allclose(xb[:, 2], Z, atol=1e-9) and np.allclose(xb[:, 0], x[:, 0] + ca * dR, atol=1e-9)
        front = (1 - k * r > 0) & (np.abs(g) < np.pi)  # the bending's domain: before its centre, angle < pi
        back = np.asarray(unbend(jnp.asarray(xb), b))
        assert np.allclose(back[front], x[front], atol=1e-9)
    back32 = np.asarray(
        unbend(
            bend_points(jnp.asarray(x, jnp.float32), jnp.array([k, alpha], jnp.float32)),
            jnp.array([k, alpha], jnp.float32),
        )
    )
    tame = front & (np.abs(g) < 1.0)  # float32: atan2 near the angle pi is ill-conditioned
    assert np.allclose(back32[tame], x[tame], atol=1e-4)


def test_bending_gradient_finite_at_zero_curvature():
    from sqjax.deformation import bend_points, unbend

    x = jnp.asarray(np.random.default_rng(1).uniform(-2, 2, (50, 3)), jnp.float32)
    for f in (bend_points, unbend):
        g = jax.grad(lambda b, f=f: jnp.sum(f(x, b) ** 2))(jnp.array([0.0, 0.3]))
        assert bool(jnp.all(jnp.isfinite(g)))


@pytest.mark.parametrize("size, eps, extra", SHAPES)
def test_host_world_points_match_the_kernel(size, eps, extra):
    """The host transform of meshes (`world_points` with numpy, float64, any size) is `to_world_frame`."""
    from sqjax.superquadric import to_world_frame, world_points

    sq = _sq(size, eps, extra)
    x = np.random.default_rng(1).uniform(-1, 1, (4, 7, 3)) * np.asarray(size)
    want = np.asarray(to_world_frame(sq, jnp.asarray(x, jnp.float32)), float)
    host = jax.tree.map(lambda v: np.asarray(v, float), sq)
    np.testing.assert_allclose(world_points(host, x, xp=np), want, atol=1e-5)


def test_host_data_reaches_the_device_without_a_compiled_conversion():
    """`numerics.to_device` (and so `Superquadric.create` on host values) converts on the host: a process
    meeting many shapes compiles (and reloads from the cache) no small conversion kernel per shape."""
    from sqjax.numerics import to_device

    compiled = []

    def listen(event: str, duration_secs: float, **kwargs: str | int) -> None:
        if "compile" in event:
            compiled.append(event)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        for n in (3, 5, 7, 11):
            v = to_device(np.arange(n, dtype=np.float64), jnp.float32)
            assert v.dtype == jnp.float32 and isinstance(v, jax.Array)
            Superquadric.create(np.full(3, 0.1 * n), (0.5, 1.0), euler=np.zeros(3), translation=np.ones(3))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiled == [], compiled
    traced = jax.jit(lambda s: to_device(s, jnp.float32) * 2)(jnp.arange(3.0))
    np.testing.assert_array_equal(traced, [0.0, 2.0, 4.0])


def test_a_batch_of_models_pairs_each_with_its_own_points():
    """A batch of K models (as `fit` returns for K clouds) evaluated on points (N, K, 3) gives each
    model's own values (N, K), equal to the single models'; one point per model (K, 3) gives (K,).
    A batch is iterable and has a len; a single model is neither (it iterated as empty). Shapes that do
    not pair and meshes of a batch raise errors that say what to pass."""
    rng = np.random.default_rng(0)
    sqs = [
        Superquadric.create([1.0, 2.0, 0.5], [0.5, 1.2], rotation=so3.from_euler(jnp.array(a)), translation=t)
        for a, t in (([0.3, 0.2, -0.4], [0.0, 0.0, 4.0]), ([-1.0, 0.5, 0.1], [1.0, -2.0, 6.0]))
    ]
    batch = jax.tree.map(lambda *v: jnp.stack(v), *sqs)
    pts = rng.normal(size=(5, 2, 3)) + np.array([[0.0, 0.0, 4.0], [1.0, -2.0, 6.0]])
    for fn in (inside_outside, distance):
        both = np.asarray(fn(batch, pts))
        assert both.shape == (5, 2)
        for i, sq in enumerate(sqs):
            np.testing.assert_allclose(both[:, i], np.asarray(fn(sq, pts[:, i])), rtol=1e-5)
        np.testing.assert_allclose(np.asarray(fn(batch, pts[0])), both[0], rtol=1e-5)
    assert len(batch) == 2 and [np.asarray(s.size).tolist() for s in batch] == [[1.0, 2.0, 0.5]] * 2
    with pytest.raises(TypeError, match="single Superquadric has no len"):
        list(sqs[0])
    assert bool(sqs[0])
    with pytest.raises(ValueError, match=r"inside_outside: points of shape \(2, 5, 3\) do not broadcast.*\(N, 2, 3\)"):
        inside_outside(batch, np.swapaxes(pts, 0, 1))
    with pytest.raises(ValueError, match=r"one superquadric, got a batch of shape \(2,\).*part_meshes"):
        to_trimesh(batch)
    with pytest.raises(ValueError, match=r"sample_surface is made of one superquadric"):
        sample_surface(batch, 10)
