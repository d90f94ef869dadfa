"""Synthetic range scenes: ray-cast geometry, noise and dropout, the paper's scenes, random scenes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from sqjax.mesh import sample_surface
from sqjax.rangeimage import OrthographicCamera, PinholeCamera
from sqjax.raycast import render
from sqjax.scenes import (
    ARRANGEMENTS,
    OBJECTS,
    PAPER_SCENES,
    default_camera,
    mesh_scene,
    multipart_scene,
    paper_scene,
    random_scene,
)
from sqjax.superquadric import Superquadric, contains, inside_outside

SHAPE = (60, 80)


def _components(mask) -> int:
    """Number of 4-connected components of a boolean image (a small flood fill)."""
    mask, seen, count = np.asarray(mask, bool), np.zeros(np.shape(mask), bool), 0
    for start in zip(*np.nonzero(mask)):
        if seen[start]:
            continue
        count, stack = count + 1, [start]
        seen[start] = True
        while stack:
            r, c = stack.pop()
            for rr, cc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
                if 0 <= rr < mask.shape[0] and 0 <= cc < mask.shape[1] and mask[rr, cc] and not seen[rr, cc]:
                    seen[rr, cc] = True
                    stack.append((rr, cc))
    return count


_inside_outside, _contains = jax.jit(inside_outside), jax.jit(contains)


def _padded(sq, points, n=4096):
    """Points padded to a fixed count with the model centre (one compilation for every call)."""
    out = np.broadcast_to(np.asarray(sq.translation, np.float32), (n, 3)).copy()
    out[: len(points)] = points
    return jnp.asarray(out)


def _any_inside(sq, points) -> bool:
    return bool(np.asarray(_contains(sq, _padded(sq, points)))[: len(points)].any())


def _assert_on_surfaces(image, parts, tol=1e-3):
    assert np.array_equal(image.valid, image.labels > 0)
    points = image.points
    for i, sq in enumerate(parts):
        sel = image.labels == i + 1
        assert sel.sum() > 20, f"part {i} barely visible"
        F = np.asarray(_inside_outside(sq, _padded(sq, points[sel])))[: sel.sum()]
        assert np.abs(F - 1.0).max() < tol, f"part {i}: max |F - 1| = {np.abs(F - 1).max()}"


def _two_parts():
    box = Superquadric.create((0.5, 0.35, 0.3), (0.1, 0.1), euler=(0.4, 0.9, 0.3), translation=(-0.5, 0.1, 5.0))
    blob = Superquadric.create((0.4, 0.3, 0.5), (0.6, 1.0), euler=(1.0, 0.5, -0.2), translation=(0.6, -0.1, 5.5))
    return [box, blob]


def test_render_pinhole_points_on_surface():
    parts = _two_parts()
    image = render(parts, default_camera(SHAPE), SHAPE)
    assert image.depth.shape == SHAPE and image.labels.dtype == np.int32
    _assert_on_surfaces(image, parts)


def test_render_orthographic_points_on_surface():
    parts = _two_parts()
    camera = OrthographicCamera(0.04, SHAPE[1] / 2, SHAPE[0] / 2)
    image = render(parts, camera, SHAPE)
    _assert_on_surfaces(image, parts)


def test_render_depth_is_z_and_nearest_part_wins():
    """A mesh box seen head-on: depth is the z of its front face (not the ray length); it hides a part behind."""
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.apply_translation((0.0, 0.0, 4.5))
    behind = Superquadric.create((1.5, 1.5, 0.2), (1.0, 1.0), translation=(0.0, 0.0, 6.0))
    camera = PinholeCamera(80.0, 80.0, 39.5, 29.5)
    image = render([behind, box], camera, SHAPE)
    front = image.labels == 2
    assert front.sum() > 100
    np.testing.assert_allclose(image.depth[front], 4.0, atol=1e-5)
    u, v = camera.project(np.array([[0.5, 0.5, 4.0], [-0.5, -0.5, 4.0]]))[0].T
    assert front[int(np.ceil(v[1])) : int(v[0]), int(np.ceil(u[1])) : int(u[0])].all()
    assert (image.labels == 1).sum() > 100


def test_noise_std_and_dropout_fraction():
    parts = [Superquadric.create((1.2, 0.9, 0.5), (0.5, 0.5), translation=(0.0, 0.0, 5.0))]
    camera = default_camera(SHAPE)
    clean = render(parts, camera, SHAPE)
    noisy = render(parts, camera, SHAPE, noise=0.01, seed=3)
    assert np.array_equal(clean.valid, noisy.valid)
    diff = (noisy.depth - clean.depth)[clean.valid]
    assert diff.size > 1000
    assert abs(diff.std() - 0.01) < 0.1 * 0.01 and abs(diff.mean()) < 0.002
    np.testing.assert_array_equal(render(parts, camera, SHAPE, noise=0.01, seed=3).depth, noisy.depth)

    dropped = render(parts, camera, SHAPE, dropout=0.25, seed=1)
    n = clean.valid.sum()
    assert dropped.valid.sum() == n - round(0.25 * n)
    assert not (dropped.valid & ~clean.valid).any()
    assert np.array_equal(dropped.valid, dropped.labels > 0)


@pytest.mark.parametrize("name", PAPER_SCENES)
def test_paper_scenes(name):
    image, parts = paper_scene(name)
    assert image.shape == (120, 160)
    assert len(parts) == {"sphere_cylinder": 2, "two_cylinders": 2, "occluded_block": 3}[name]
    counts = np.bincount(image.labels.ravel(), minlength=len(parts) + 1)
    assert len(counts) == len(parts) + 1 and counts[1:].min() >= 300, counts
    _assert_on_surfaces(image, parts)
    if name == "occluded_block":
        block = parts[0]
        assert np.asarray(block.epsilon).max() <= 0.1 + 1e-6  # a box
        assert _components(image.labels == 1) == 2
        assert all(_components(image.labels == k) == 1 for k in (2, 3))
    if name == "two_cylinders":
        a, b = parts
        assert _any_inside(a, sample_surface(b, 2000))  # they intersect


def test_paper_scene_unknown_name():
    with pytest.raises(ValueError, match="unknown scene"):
        paper_scene("teapot")


def test_random_scene_is_deterministic():
    a, pa = random_scene(7, noise=0.005)
    b, pb = random_scene(7, noise=0.005)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert len(pa) == len(pb) and 2 <= len(pa) <= 6
    for p, q in zip(pa, pb):
        np.testing.assert_array_equal(np.asarray(p.size), np.asarray(q.size))
        np.testing.assert_array_equal(np.asarray(p.translation), np.asarray(q.translation))
    c, _ = random_scene(8, noise=0.005)
    assert c.labels.max() != a.labels.max() or not np.array_equal(c.labels, a.labels)


@pytest.mark.parametrize("arrangement", ARRANGEMENTS)
def test_random_scene_every_part_visible(arrangement):
    image, parts = random_scene(1, n_parts=(3, 4), arrangement=arrangement, noise=0.0)
    assert 3 <= len(parts) <= 4
    counts = np.bincount(image.labels.ravel(), minlength=len(parts) + 1)
    assert len(counts) == len(parts) + 1 and counts[1:].min() >= 150, counts
    for sq in parts:
        e = np.asarray(sq.epsilon)
        assert ((0.1 <= e) & (e <= 1.0)).all()
    _assert_on_surfaces(image, parts)
    surf = [sample_surface(p, 2000) for p in parts]
    hits = lambda i, j: _any_inside(parts[j], surf[i]) or _any_inside(parts[i], surf[j])
    if arrangement == "separate":
        assert not any(hits(i, j) for i in range(len(parts)) for j in range(i))
    if arrangement == "intersecting":
        assert all(any(hits(i, j) for j in range(i)) for i in range(1, len(parts)))


def test_random_scene_arguments():
    image, parts = random_scene(2, n_parts=2, shape=(90, 120), noise=0.0, dropout=0.1)
    assert len(parts) == 2 and image.shape == (90, 120)
    with pytest.raises(ValueError, match="arrangement"):
        random_scene(0, arrangement="stacked")


def test_render_without_embree_matches(monkeypatch):
    """The pure numpy ray caster (used when embreex is missing) gives the same image."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    import sqjax.raycast as raycast

    parts, shape = _two_parts(), (24, 32)
    camera = default_camera(shape)
    fast = render(parts, camera, shape, resolution=24)
    monkeypatch.setattr(raycast, "_intersector", RayMeshIntersector)
    slow = render(parts, camera, shape, resolution=24)
    assert (fast.labels != slow.labels).sum() <= 2
    same = (fast.labels == slow.labels) & fast.valid
    np.testing.assert_allclose(fast.depth[same], slow.depth[same], atol=1e-5)


def test_every_platform_installs_a_ray_caster():
    """embreex has wheels for x86_64 only; elsewhere the numpy caster above needs rtree. Both are core
    dependencies, each where the other is not, or `sqjax demo` fails on an ARM machine."""
    import tomllib
    from pathlib import Path

    from packaging.markers import Marker
    from packaging.requirements import Requirement

    deps = [
        Requirement(d)
        for d in tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]["dependencies"]
    ]
    for machine in ("x86_64", "aarch64", "arm64"):
        env = {"platform_machine": machine}
        installed = {r.name for r in deps if r.marker is None or Marker(str(r.marker)).evaluate(env)}
        assert {"embreex", "rtree"} & installed, machine


def test_render_non_convex_part():
    """A star-like superquadric (exponents > 1): hits still lie on its surface or, unbracketed, on its mesh."""
    star = Superquadric.create((0.8, 0.8, 0.8), (1.8, 1.8), euler=(0.3, 0.4, 0.0), translation=(0.0, 0.0, 5.0))
    image = render([star], default_camera(SHAPE), SHAPE)
    assert image.valid.sum() > 100 and np.isfinite(image.depth[image.valid]).all()
    F = np.asarray(_inside_outside(star, _padded(star, image.points[image.valid])))[: image.valid.sum()]
    assert np.median(np.abs(F - 1)) < 1e-3 and np.abs(F - 1).max() < 0.2


@pytest.mark.parametrize("kind", OBJECTS)
def test_multipart_objects_show_their_parts(kind):
    """Every multi-part object renders deterministically with one label per part, and at least two
    of its parts visible (>= 30 pixels) in the first view."""
    image, parts = multipart_scene(0, kind)
    again, _ = multipart_scene(0, kind)
    np.testing.assert_array_equal(image.labels, again.labels)
    counts = np.bincount(image.labels.ravel(), minlength=len(parts) + 1)
    assert len(counts) == len(parts) + 1 and np.sum(counts[1:] >= 30) >= 2
    # every labelled pixel lies on its part's surface (before noise): F ~ 1 there
    clean, _ = multipart_scene(0, kind, noise=0.0)
    pts = clean.points[clean.labels > 0]
    lab = clean.labels[clean.labels > 0]
    for i, sq in enumerate(parts):
        f = np.asarray(inside_outside(sq, pts[lab == i + 1]))
        assert f.size == 0 or np.median(np.abs(f - 1)) < 1e-2


def _two_boxes():
    """A mesh of two disjoint boxes (two connected components), in millimetres."""
    a = trimesh.creation.box((40.0, 30.0, 20.0))
    b = trimesh.creation.box((20.0, 20.0, 50.0))
    b.apply_translation((60.0, 0.0, 15.0))
    return trimesh.util.concatenate([a, b])


def test_mesh_scene_labels_each_connected_component():
    """A mesh's connected components are its parts: each is seen with its own label, the returned parts
    are the components moved by the returned similarity, and the depths are the parts' surfaces."""
    mesh = _two_boxes()
    image, parts, T = mesh_scene(mesh, azimuth=30, elevation=30, shape=SHAPE, noise=0.0)
    assert image.shape == SHAPE and len(parts) == 2
    assert all(np.sum(image.labels == i) >= 100 for i in (1, 2))
    assert set(np.unique(image.labels)) == {0, 1, 2}
    moved = mesh.copy()
    moved.apply_transform(T)
    assert np.allclose(np.sort(moved.vertices, 0), np.sort(np.concatenate([p.vertices for p in parts]), 0))
    scale = np.cbrt(np.linalg.det(T[:3, :3]))  # a similarity: a rotation times one scale
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, scale**2 * np.eye(3))
    assert np.isclose(np.linalg.norm(T[:3, :3] @ mesh.bounding_sphere.primitive.center + T[:3, 3] - (0, 0, 5)), 0)
    for i, part in enumerate(parts):  # each labelled pixel's point lies on its part's surface
        pts = image.points[image.labels == i + 1]
        _, dist, _ = trimesh.proximity.closest_point(part, pts)
        assert np.max(dist) < 1e-3 * 5.0


def test_a_found_part_maps_back_to_the_mesh_frame():
    """The README's recipe: a box 1.0 x 0.5 x 0.3 placed away from the origin, seen from a view and
    segmented; the inverse of the returned similarity takes the found part's surface back onto the box,
    in the mesh's own frame and units (its bounds within a tenth of each of the box's sizes: the far end,
    which the view does not see, comes out 0.06 long)."""
    from sqjax import segment
    from sqjax.mesh import to_trimesh

    box = trimesh.creation.box((1.0, 0.5, 0.3))
    box.apply_translation((2.0, 3.0, 4.0))
    view, _, T = mesh_scene(box, azimuth=40, elevation=25)
    seg = segment(view)
    assert len(seg.parts) == 1
    part = to_trimesh(seg.parts[0].superquadric).apply_transform(np.linalg.inv(T))
    assert np.all(np.abs(part.bounds - box.bounds) < 0.1 * np.array([1.0, 0.5, 0.3]))


def test_mesh_scene_reads_files_as_read_points_does(tmp_path):
    """A mesh file is loaded as `read_points` loads it (`formats.load_mesh`): an OBJ with a Latin-1
    comment renders its two boxes (it stopped on a missing charset_normalizer inside trimesh), and a
    file trimesh cannot parse is refused with its name."""
    text = _two_boxes().export(file_type="obj")
    (tmp_path / "boxes.obj").write_bytes(("# caf\xe9 \xb5m\n" + text).encode("latin-1"))
    image = mesh_scene(tmp_path / "boxes.obj", shape=SHAPE, noise=0.0)[0]
    assert set(np.unique(image.labels)) == {0, 1, 2}
    (tmp_path / "bad.glb").write_bytes(b"glTF not really")
    with pytest.raises(ValueError, match="bad.glb"):
        mesh_scene(tmp_path / "bad.glb", shape=SHAPE)


def test_mesh_scene_views_and_bad_meshes(tmp_path):
    """Views from other azimuths see the parts from other sides; a file of points (no faces) and a mesh
    of only tiny components are refused by name."""
    mesh = _two_boxes()
    a = mesh_scene(mesh, azimuth=0, elevation=20, shape=SHAPE, noise=0.0)[0]
    b = mesh_scene(mesh, azimuth=180, elevation=20, shape=SHAPE, noise=0.0)[0]
    ca, cb = (np.nanmean(np.argwhere(x.labels == 2)[:, 1]) for x in (a, b))
    assert ca > SHAPE[1] / 2 > cb  # the second box is right of the first from one side, left from the other
    mesh.export(tmp_path / "boxes.stl")
    assert np.array_equal(
        mesh_scene(tmp_path / "boxes.stl", shape=SHAPE, noise=0.0)[0].labels,
        mesh_scene(mesh, shape=SHAPE, noise=0.0)[0].labels,
    )
    trimesh.PointCloud(mesh.vertices).export(tmp_path / "points.ply")
    with pytest.raises(ValueError, match="no faces"):
        mesh_scene(tmp_path / "points.ply")
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]]).subdivide()
    image, parts, T = mesh_scene(flat, elevation=90, shape=SHAPE, noise=0.0)  # a flat mesh has a sphere too
    assert (
        len(parts) == 1
        and image.valid.sum() > 100
        and np.isclose(np.cbrt(np.linalg.det(T[:3, :3])), 5 * 0.4 * SHAPE[0] / SHAPE[1] / np.sqrt(0.5))
    )
    with pytest.raises(ValueError, match="4 faces"):
        mesh_scene(trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
