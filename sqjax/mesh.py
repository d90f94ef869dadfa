"""Surfaces of superquadrics (host side): the parametric grid, closed triangle meshes (trimesh) and
points sampled uniformly by area, optionally of one view, for figures, exports and test data.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .cache import kernel_jit
from .superquadric import Superquadric, log_inside_outside, to_model_frame, to_world_frame, world_points


def _spow(c, e):
    return np.sign(c) * np.abs(c) ** e


def surface_grid(sq: Superquadric, resolution: int = 48):
    """Parametric surface points, numpy `(resolution, 2 * resolution, 3)` in world coordinates."""
    single(sq, "a mesh")
    a = np.asarray(sq.size, float)
    e1, e2 = np.asarray(sq.epsilon, float)
    eta = np.linspace(-np.pi / 2, np.pi / 2, resolution)
    om = np.linspace(-np.pi, np.pi, 2 * resolution, endpoint=False)
    eta, om = np.meshgrid(eta, om, indexing="ij")
    c = np.cos(eta)
    c[[0, -1]] = 0.0  # exact poles, so the mesh closes
    ce, se = _spow(c, e1), _spow(np.sin(eta), e1)
    x = np.stack([a[0] * ce * _spow(np.cos(om), e2), a[1] * ce * _spow(np.sin(om), e2), a[2] * se], -1)
    # in float64 numpy: meshes come in many sizes, and each would compile (and reload) a kernel
    return world_points(jax.tree.map(lambda v: np.asarray(v, float), sq), x, xp=np)


def single(sq: Superquadric, what: str) -> None:
    """Raise a ValueError naming `what` unless `sq` is one superquadric (no batch axis)."""
    batch = np.shape(sq.size)[:-1]
    if batch:
        raise ValueError(
            f"{what} is made of one superquadric, got a batch of shape {batch}: take sq[i], or "
            "sqjax.export.part_meshes(sq) for a mesh of each"
        )


LOCAL_MESH_SIZE = 1e-3
"""`to_trimesh` meshes a model whose largest extent is below this in its own units (trimesh's vertex
merge tolerance, 1e-8, is then over 1e-5 of the model)."""


def to_trimesh(sq: Superquadric, resolution: int = 48):
    """Closed triangle mesh of one superquadric (`trimesh.Trimesh`), world coordinates.

    trimesh merges vertices closer than an absolute 1e-8, which collapsed every mesh of a model in
    units of 1e-7 or less (`sqjax segment` then failed writing parts.glb): a model smaller than
    `LOCAL_MESH_SIZE` is meshed about its centre in units of its size, then placed. Larger ones are
    meshed where they are, as always (the scenes' renders and samples stay bit for bit)."""
    import trimesh

    g = surface_grid(sq, resolution)
    n_eta, n_om = g.shape[:2]
    centre = np.asarray(sq.translation, float)
    scale = float(np.max(np.abs(g - centre)))
    local = 0.0 < scale < LOCAL_MESH_SIZE
    verts = ((g - centre) / scale if local else g).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_eta - 1), np.arange(n_om), indexing="ij")
    a = i * n_om + j
    b = i * n_om + (j + 1) % n_om
    c = (i + 1) * n_om + j
    d = (i + 1) * n_om + (j + 1) % n_om
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    mesh = trimesh.Trimesh(verts, faces, process=True)  # merges the pole vertices
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    # the grid's winding is consistent by construction: outward is a sign (trimesh's fix_normals
    # needs networkx for a mesh it cannot check, e.g. a flat part's)
    with np.errstate(divide="ignore", invalid="ignore"):  # a flat part's mesh has no volume
        inward = mesh.volume < 0
    if inward:
        mesh.invert()
    if local:
        mesh.vertices = mesh.vertices * scale + centre
    return mesh


def sample_surface(sq: Superquadric, n: int, *, seed: int = 0, noise: float = 0.0, viewpoint=None):
    """`n` points (numpy `(n, 3)`) uniform by area on the surface, with Gaussian noise of std `noise`.

    Points are drawn on a fine mesh and moved along the ray from the model centre onto the exact surface
    (F = 1 up to rounding), so no chord error biases them inwards. With `viewpoint` (3,) only the side
    facing that point is sampled (one range-sensor view; self-occlusion of concave shapes is ignored).
    """
    import trimesh

    single(sq, "sample_surface")
    rng = np.random.default_rng(seed)
    mesh = to_trimesh(sq, 64)
    if viewpoint is not None:
        centres = mesh.triangles_center
        facing = np.einsum("ij,ij->i", mesh.face_normals, np.asarray(viewpoint, float) - centres) > 0
        mesh = mesh.submesh([np.nonzero(facing)[0]], append=True)
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(2**31)))  # pyright: ignore[reportAssignmentType]
    pts = np.asarray(_onto_surface(sq, jnp.asarray(pts, sq.size.dtype)), float)
    return pts + noise * rng.standard_normal((n, 3))


@kernel_jit
def _onto_surface(sq: Superquadric, points):
    """Move world points along the ray from the centre (undeformed model frame) onto the surface F = 1."""
    x = to_model_frame(sq, points)
    log_f = log_inside_outside(x, jnp.log(sq.size), sq.epsilon)
    return to_world_frame(sq, x * jnp.exp(-0.5 * log_f)[..., None])
