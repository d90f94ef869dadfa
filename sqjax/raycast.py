"""Ray casting: labelled range images of superquadrics and meshes (host side, numpy + trimesh).

`render` casts one ray per pixel into the union of the parts and keeps the nearest hit: depth (z of the
hit, NaN where nothing is hit) and a label image (0 background, i + 1 for part i). Superquadric hits are
moved from the triangle mesh onto the exact surface F = 1 (eq. 5, in float64 numpy through the same
core as the kernels) by bisection along the ray, so every valid pixel back-projects onto its part.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .cache import kernel_jit
from .mesh import to_trimesh
from .padding import bucket
from .rangeimage import OrthographicCamera, PinholeCamera, RangeImage
from .superquadric import Superquadric, log_inside_outside, to_model_frame


def _intersector(mesh):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError:  # no embreex: the pure numpy caster (slower, same answers)
        from trimesh.ray.ray_triangle import RayMeshIntersector
    return RayMeshIntersector(mesh)


@kernel_jit
def _log_F_deformed(sq: Superquadric, pts):
    return log_inside_outside(to_model_frame(sq, pts.astype(sq.size.dtype)), jnp.log(sq.size), sq.epsilon)


def world_log_f(size, epsilon, rotation, centre, pts: np.ndarray) -> np.ndarray:
    """log F (eq. 5) of world points (n, 3) for an undeformed model, float64 numpy."""
    return log_inside_outside((pts - centre) @ rotation, np.log(size), np.asarray(epsilon), xp=np)


def _log_F(sq: Superquadric, pts: np.ndarray) -> np.ndarray:
    """log F of world points (n, 3) -> (n,), float64 numpy for undeformed models, sqjax's kernel otherwise."""
    if np.any(np.asarray(sq.taper) != 0) or np.any(np.asarray(sq.bend)[..., 0] != 0):
        n = len(pts)
        pad = np.zeros((bucket(n, 256) - n, 3))  # few buckets: few compilations
        return np.asarray(_log_F_deformed(sq, np.concatenate([pts, pad + np.asarray(sq.translation)])), float)[:n]
    return world_log_f(*(np.asarray(v, float) for v in (sq.size, sq.epsilon, sq.rotation, sq.translation)), pts=pts)


def _refine(sq: Superquadric, o: np.ndarray, d: np.ndarray, t0: np.ndarray, iters: int = 48) -> np.ndarray:
    """Move mesh hits t0 along rays o + t d onto the surface F = 1 (bisection); unbracketed hits are kept."""
    g = lambda t: _log_F(sq, o + t[:, None] * d)
    step = 1e-3 * float(np.min(np.asarray(sq.size)))
    inside = g(t0) <= 0  # a convex model's mesh is inscribed: its hits lie just inside the solid
    lo, hi = np.where(inside, t0 - step, t0), np.where(inside, t0, t0 + step)
    ok = np.zeros(len(t0), bool)
    for k in range(12):  # widen the bracket until log F changes sign across it
        ok = (g(lo) > 0) & (g(hi) <= 0)
        if ok.all():
            break
        grow = step * 2.0 ** (k + 1)
        lo, hi = np.where(ok | ~inside, lo, t0 - grow), np.where(ok | inside, hi, t0 + grow)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        out = g(mid) > 0
        lo, hi = np.where(out, mid, lo), np.where(out, hi, mid)
    return np.where(ok, 0.5 * (lo + hi), t0)


def _rays(camera, shape):
    """Per-pixel rays o + t d (n, 3) with o_z = 0 and d_z = 1, so that t is the depth (z) of a point."""
    h, w = shape
    if isinstance(camera, PinholeCamera):
        d = camera.rays(shape).reshape(-1, 3)
        return np.zeros_like(d), d
    o = camera.back_project(np.zeros(shape)).reshape(-1, 3)
    d = np.zeros((h * w, 3))
    d[:, 2] = 1.0
    return o, d


def meshes_of(parts, resolution: int):
    """The parts as triangle meshes (superquadrics meshed at `resolution`, meshes as they are)."""
    return [p if not isinstance(p, Superquadric) else to_trimesh(p, resolution) for p in parts]


def cast(meshes, camera, shape):
    """Nearest hits: (depth (H, W) float64 NaN where none, labels (H, W) int32, ray origins, directions)."""
    import trimesh

    verts = [np.asarray(m.vertices, float) for m in meshes]
    offsets = np.cumsum([0] + [len(v) for v in verts])[:-1]
    faces = np.concatenate([np.asarray(m.faces) + off for m, off in zip(meshes, offsets)])
    owner = np.repeat(np.arange(len(meshes), dtype=np.int32), [len(m.faces) for m in meshes])
    scene = trimesh.Trimesh(np.concatenate(verts), faces, process=False)
    if not isinstance(camera, (PinholeCamera, OrthographicCamera)):
        raise TypeError(f"render: unsupported camera {type(camera).__name__}")
    o, d = _rays(camera, shape)
    start = o.copy()
    if isinstance(camera, OrthographicCamera):  # parallel rays start in front of every part
        start[:, 2] = float(scene.bounds[0, 2]) - 0.1 * float(np.ptp(scene.bounds[:, 2])) - 1e-3
    tri = _intersector(scene).intersects_first(start, d)
    depth = np.full(len(o), np.nan)
    hit = tri >= 0
    v0, n = scene.triangles[tri[hit], 0], scene.face_normals[tri[hit]]
    depth[hit] = np.einsum("ij,ij->i", n, v0 - o[hit]) / np.einsum("ij,ij->i", n, d[hit])  # plane-line, d_z = 1
    labels = np.zeros(len(o), np.int32)
    labels[hit] = owner[tri[hit]] + 1
    return depth, labels, o, d


def render_meshes(parts, meshes, camera, shape, *, noise, dropout, seed, refine=True) -> RangeImage:
    """`render` with the parts already meshed (`meshes_of`)."""
    shape = tuple(int(s) for s in shape)
    depth, labels, o, d = cast(meshes, camera, shape)
    if refine:
        for i, p in enumerate(parts):
            sel = np.nonzero(labels == i + 1)[0]
            if isinstance(p, Superquadric) and len(sel):
                depth[sel] = _refine(p, o[sel], d[sel], depth[sel])
    depth, labels = depth.reshape(shape), labels.reshape(shape)
    rng = np.random.default_rng(seed)
    if noise > 0:
        depth = depth + noise * rng.standard_normal(shape)
    if dropout > 0:
        idx = np.flatnonzero(labels)
        drop = rng.choice(idx, int(round(dropout * len(idx))), replace=False)
        depth.flat[drop], labels.flat[drop] = np.nan, 0
    return RangeImage(depth.astype(np.float32), camera, labels)


def render(
    parts,
    camera,
    shape,
    *,
    noise: float = 0.0,
    dropout: float = 0.0,
    seed: int = 0,
    resolution: int = 64,
    refine: bool = True,
) -> RangeImage:
    """Ray-cast a range image of `parts` (list of `Superquadric` and/or `trimesh.Trimesh`, camera frame).

    **Arguments:**
    - `camera`: `PinholeCamera` (rays from the origin through the pixel centres) or `OrthographicCamera`
      (rays along +z from in front of all parts). `shape`: (H, W).
    - `noise`: std of Gaussian noise added to the depth (depth units); `dropout`: fraction of the valid
      pixels made missing (depth NaN, label 0); both drawn from `numpy.random.default_rng(seed)`.
    - `resolution`: mesh resolution of the superquadrics; `refine`: move their hits onto F = 1 exactly.

    **Returns:** `RangeImage` with depth = z of the nearest hit (NaN where none) and labels (H, W) int32:
    0 background, i + 1 where part i is the nearest surface.
    """
    parts = list(parts)
    if not parts:
        raise ValueError("render: no parts to render")
    if not 0.0 <= dropout <= 1.0 or noise < 0:
        raise ValueError(f"render: need noise >= 0 and dropout in [0, 1], got {noise}, {dropout}")
    return render_meshes(
        parts, meshes_of(parts, resolution), camera, shape, noise=noise, dropout=dropout, seed=seed, refine=refine
    )
