"""Labelled synthetic scenes with their true superquadrics, rendered by `raycast.render` (host side).

`paper_scene` rebuilds the three scenes of the paper's figures; `random_scene` draws seeded scenes of
separate, touching, intersecting or occluding parts; `multipart_scene` draws multi-part objects (tables,
chairs, mugs, lamps, L-shapes, dumbbells, arms) with one label per part, seen from random views;
`mesh_scene` renders a mesh file whose connected components are its parts from a chosen view.
"""

from __future__ import annotations

import numpy as np

from .mesh import sample_surface, surface_grid
from .rangeimage import PinholeCamera
from .raycast import cast, meshes_of, render, render_meshes, world_log_f
from .superquadric import Superquadric

PAPER_SCENES = ("sphere_cylinder", "two_cylinders", "occluded_block")
ARRANGEMENTS = ("separate", "touching", "intersecting", "occluding", "mixed")


def default_camera(shape=(120, 160)) -> PinholeCamera:
    """The pinhole camera of the synthetic scenes: fx = fy = image width (about 53 deg across), centred."""
    h, w = shape
    return PinholeCamera(float(w), float(w), (w - 1) / 2.0, (h - 1) / 2.0)


# ----------------------------------------------------------------------------------------------------
# ray casting


# ----------------------------------------------------------------------------------------------------
# the paper's scenes


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# world (table) frame: x, y on the table, z up  ->  camera frame (x right, y down, z forward), seen
# from 35 deg azimuth and 30 deg elevation so that boxes show three faces.
_TABLE_TO_CAMERA = _rx(np.radians(30)) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) @ _rz(np.radians(35))


def _table_part(
    size,
    epsilon,
    centre,
    rotation=np.eye(3),  # noqa: B008  (only read, never written)
    *,
    look_at=(0.0, 0.0, 0.7),
    distance=5.0,
):
    t = _TABLE_TO_CAMERA @ (np.asarray(centre, float) - look_at) + (0.0, 0.0, distance)
    return Superquadric.create(size, epsilon, rotation=_TABLE_TO_CAMERA @ rotation, translation=t)


def _paper_parts(name: str) -> list[Superquadric]:
    if name == "sphere_cylinder":  # Figure 1: a sphere and a cylinder standing apart
        return [
            _table_part((0.6, 0.6, 0.6), (1.0, 1.0), (-0.95, 0.0, 0.6)),
            _table_part((0.45, 0.45, 0.8), (0.1, 1.0), (0.95, 0.2, 0.8)),
        ]
    if name == "two_cylinders":  # Figure 2: two intersecting cylinders, a cross
        return [
            _table_part((0.4, 0.4, 1.1), (0.1, 1.0), (0.0, 0.0, 1.1)),
            _table_part((0.3, 0.3, 1.25), (0.1, 1.0), (0.0, 0.0, 1.3), _ry(np.pi / 2)),
        ]
    if name == "occluded_block":  # Figure 3: a block split in two by a nearer cylinder, and a sphere
        block_c = np.array([-0.2, 0.7, 0.4])
        cam = -_TABLE_TO_CAMERA.T @ (_TABLE_TO_CAMERA @ -np.array([0.0, 0.0, 0.7]) + (0.0, 0.0, 5.0))
        towards = (cam - block_c)[:2] / np.linalg.norm((cam - block_c)[:2])
        cyl_xy = block_c[:2] + 1.1 * towards  # on the line of sight to the block's centre
        return [
            _table_part((1.05, 0.45, 0.4), (0.1, 0.1), block_c),
            _table_part((0.22, 0.22, 1.0), (0.1, 1.0), (*cyl_xy, 1.0)),
            _table_part((0.45, 0.45, 0.45), (1.0, 1.0), (1.45, 0.3, 0.45)),
        ]
    raise ValueError(f"paper_scene: unknown scene {name!r}, expected one of {PAPER_SCENES}")


def paper_scene(name: str, *, shape=(120, 160), noise: float = 0.0, seed: int = 0):
    """One of the paper's scenes (`PAPER_SCENES`): (range image with labels, ground-truth superquadrics).

    `sphere_cylinder` (Fig. 1), `two_cylinders` (Fig. 2, a cross) and `occluded_block` (Fig. 3: a box seen
    as two pieces behind a vertical cylinder, and a sphere). Parts stand on a table about 5 units in front
    of `default_camera(shape)`, seen obliquely; label i + 1 is part i.
    """
    parts = _paper_parts(name)
    return render(parts, default_camera(shape), shape, noise=noise, seed=seed), parts


# ----------------------------------------------------------------------------------------------------
# random scenes


def _random_rotation(rng) -> np.ndarray:
    w, x, y, z = (q := rng.standard_normal(4)) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class _Body:
    """A candidate part: parameters, surface samples about its centre (grid + uniform by area), its radius."""

    def __init__(self, rng):
        self.size = rng.uniform(0.25, 0.6, 3)
        self.epsilon = rng.uniform(0.1, 1.0, 2)
        self.rotation = _random_rotation(rng)
        sq = Superquadric.create(self.size, self.epsilon, rotation=self.rotation)
        grid = surface_grid(sq, 24).reshape(-1, 3)  # dense at edges and corners
        self.surface = np.concatenate([grid, sample_surface(sq, 1500, seed=int(rng.integers(2**31)))])
        self.radius = float(np.linalg.norm(self.surface, axis=-1).max())
        self.centre = np.zeros(3)

    def log_F(self, centre, pts):
        return world_log_f(self.size, self.epsilon, self.rotation, centre, pts)

    def at(self, c) -> Superquadric:
        return Superquadric.create(self.size, self.epsilon, rotation=self.rotation, translation=c)


def _overlap(a: _Body, ca, b: _Body, cb) -> bool:
    if np.linalg.norm(np.subtract(ca, cb)) > a.radius + b.radius:
        return False
    return bool((b.log_F(cb, a.surface + ca) <= 0).any() or (a.log_F(ca, b.surface + cb) <= 0).any())


def _contact(a: _Body, b: _Body, direction) -> float:
    """Distance s along the unit `direction` from b's centre at which a (centred there) just touches b."""
    lo, hi = 0.0, a.radius + b.radius
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _overlap(a, b.centre + mid * direction, b, b.centre) else (lo, mid)
    return hi


def _in_view(camera: PinholeCamera, shape, c, r) -> bool:
    if not 3.8 <= c[2] <= 6.8 or c[2] - r < 2.5:
        return False
    h, w = shape
    tx, ty = (min(camera.cx, w - 1 - camera.cx) - 2) / camera.fx, (min(camera.cy, h - 1 - camera.cy) - 2) / camera.fy
    return abs(c[0]) + r <= tx * (c[2] - r) and abs(c[1]) + r <= ty * (c[2] - r)


def _place(rng, body: _Body, placed: list[_Body], relation: str, camera, shape) -> bool:
    """Try to centre `body` in `relation` to a random placed part (or anywhere); True when it fits."""
    h, w = shape
    for _ in range(60):
        if not placed or relation == "separate":
            z = rng.uniform(5.5, 6.5) if relation == "occluding" else rng.uniform(4.6, 6.3)
            c = np.array(
                [rng.uniform(-1, 1) * 0.45 * z * w / camera.fx, rng.uniform(-1, 1) * 0.45 * z * h / camera.fy, z]
            )
            if any(np.linalg.norm(c - p.centre) < body.radius + p.radius + 0.05 for p in placed):
                continue
        else:
            j = placed[rng.integers(len(placed))]
            if relation == "occluding":
                view = j.centre / np.linalg.norm(j.centre)
                u = np.cross(view, rng.standard_normal(3))
                d = -view + rng.uniform(0.5, 1.0) * u / np.linalg.norm(u)
            else:
                d = rng.standard_normal(3) * (1.0, 1.0, 0.4)  # mostly side by side
            d /= np.linalg.norm(d)
            s = _contact(body, j, d)
            s *= {"touching": 1.0, "intersecting": rng.uniform(0.55, 0.8)}.get(relation, 1.0)
            s += rng.uniform(0.05, 0.3) if relation == "occluding" else 0.0
            c = j.centre + s * d
            if any(_overlap(body, c, p, p.centre) for p in placed if p is not j):
                continue
        if _in_view(camera, shape, c, body.radius):
            body.centre = c
            return True
    return False


def random_scene(
    seed: int,
    *,
    n_parts=(2, 6),
    shape=(120, 160),
    noise: float = 0.005,
    dropout: float = 0.0,
    arrangement: str = "mixed",
    min_pixels: int | None = None,
    max_tries: int = 200,
):
    """A seeded random scene: (range image with labels, ground-truth superquadrics, label i + 1 = part i).

    **Arguments:**
    - `n_parts`: an int or an inclusive range (lo, hi) the count is drawn from.
    - `arrangement`: how each new part sits against a random earlier one: "separate" (apart),
      "touching", "intersecting", "occluding" (in front of it, partly covering it), or "mixed" (each
      relation drawn at random).
    - `min_pixels`: every part must be the nearest surface in at least this many pixels (before
      dropout; default 150 at 160 x 120, scaled with the image area); scenes are redrawn until they
      are (deterministically, from the same generator).

    Sizes are drawn in [0.25, 0.6], exponents in [0.1, 1.0], rotations uniformly; parts lie 3.8 to 6.8
    units in front of `default_camera(shape)` and inside its view.
    """
    if arrangement not in ARRANGEMENTS:
        raise ValueError(f"random_scene: arrangement must be one of {ARRANGEMENTS}, got {arrangement!r}")
    lo, hi = (n_parts, n_parts) if np.isscalar(n_parts) else n_parts
    if not 1 <= lo <= hi:  # pyright: ignore[reportOperatorIssue]  (np.isscalar's TypeGuard loses the int)
        raise ValueError(f"random_scene: n_parts must be >= 1 (or a range lo <= hi), got {n_parts}")
    shape = tuple(int(s) for s in shape)
    camera, rng = default_camera(shape), np.random.default_rng([seed, ARRANGEMENTS.index(arrangement)])
    relations = ARRANGEMENTS[:4]
    if min_pixels is None:
        min_pixels = max(20, round(150 * shape[0] * shape[1] / (120 * 160)))
    n = int(rng.integers(lo, hi + 1))  # pyright: ignore[reportCallIssue, reportArgumentType, reportOperatorIssue]
    for _ in range(max_tries):
        placed: list[_Body] = []
        for _k in range(n):
            rel = relations[rng.integers(4)] if arrangement == "mixed" else arrangement
            body = _Body(rng)
            if not _place(rng, body, placed, rel, camera, shape):
                break
            placed.append(body)
        if len(placed) < n:
            continue
        parts = [b.at(b.centre) for b in placed]
        meshes = meshes_of(parts, 64)
        _, labels, _, _ = cast(meshes, camera, shape)
        if np.bincount(labels, minlength=n + 1)[1:].min() >= min_pixels:
            image = render_meshes(
                parts, meshes, camera, shape, noise=noise, dropout=dropout, seed=int(rng.integers(2**31))
            )
            return image, parts
    raise RuntimeError(f"random_scene: no scene with every part visible in {max_tries} tries (seed {seed})")


# ----------------------------------------------------------------------------------------------------
# multi-part objects

OBJECTS = ("table", "chair", "mug", "lamp", "l_shape", "dumbbell", "arm")


def _object_parts(kind: str, rng) -> list[tuple]:
    """Parts of a multi-part object in its own frame (z up, standing on z = 0, about 1 unit across):
    (half-sizes, exponents (e1, e2), centre, rotation) per part, dimensions jittered by `rng`."""
    j = lambda *v: np.asarray(v, float) * rng.uniform(0.85, 1.18, len(v))
    box, cyl, ball = (0.1, 0.1), (0.1, 1.0), (1.0, 1.0)
    eye = np.eye(3)
    if kind in ("table", "chair"):
        w, d, h = j(0.55, 0.4, 0.45) if kind == "table" else j(0.3, 0.3, 0.3)
        leg = j(0.05)[0] if kind == "table" else j(0.04)[0]
        leg_e = box if rng.random() < 0.5 else cyl
        top = j(0.05)[0]
        parts = [((w, d, top), box, (0, 0, 2 * h + top), eye)]
        parts += [
            ((leg, leg, h), leg_e, (sx * (w - 1.5 * leg), sy * (d - 1.5 * leg), h), eye)
            for sx in (-1, 1)
            for sy in (-1, 1)
        ]
        if kind == "chair":
            back = j(0.32)[0]
            parts.append(((w, top, back), box, (0, -d + top, 2 * h + 2 * top + back), eye))
        return parts
    if kind == "mug":
        r, h = j(0.3, 0.36)
        hw, hh = j(0.05, 0.2)
        return [((r, r, h), cyl, (0, 0, h), eye), ((hw, 0.6 * hw, hh), (0.3, 0.3), (r + hw, 0, h), eye)]
    if kind == "lamp":
        rb, hb, rp, hp, rs, hs = j(0.3, 0.04, 0.04, 0.5, 0.3, 0.2)
        return [
            ((rb, rb, hb), cyl, (0, 0, hb), eye),
            ((rp, rp, hp), cyl, (0, 0, 2 * hb + hp), eye),
            ((rs, rs, hs), (0.6, 1.0), (0, 0, 2 * hb + 2 * hp + 0.6 * hs), eye),
        ]
    if kind == "l_shape":
        a, b, t = j(0.5, 0.45, 0.16)
        return [((a, t, t), box, (0, 0, t), eye), ((t, t, b), box, (a - t, 0, 2 * t + b), eye)]
    if kind == "dumbbell":
        r, lb, rb = j(0.28, 0.42, 0.07)
        return [
            ((r, r, r), ball, (-lb - 0.7 * r, 0, r), eye),
            ((r, r, r), ball, (lb + 0.7 * r, 0, r), eye),
            ((rb, rb, lb + 0.3 * r), cyl, (0, 0, r), _ry(np.pi / 2)),
        ]
    if kind == "arm":  # a base and two cylindric links, bent at the joint
        bw, l1, l2, r = j(0.25, 0.34, 0.3, 0.08)
        a1, a2 = rng.uniform(0.3, 0.8), rng.uniform(-1.6, -0.8)
        u1, u2 = np.array([np.sin(a1), 0, np.cos(a1)]), np.array([np.sin(a1 + a2), 0, np.cos(a1 + a2)])
        base = np.array([0, 0, 0.16])
        joint = base + 2 * l1 * u1
        return [
            ((bw, bw, 0.08), box, (0, 0, 0.08), eye),
            ((r, r, l1), cyl, base + l1 * u1, _ry(a1)),
            ((0.8 * r, 0.8 * r, l2), cyl, joint + (l2 - r) * u2, _ry(a1 + a2)),
        ]
    raise ValueError(f"multipart_scene: unknown object {kind!r}, expected one of {OBJECTS}")


def multipart_scene(
    seed: int, kind: str | None = None, *, shape=(120, 160), noise: float = 0.005, dropout: float = 0.0
):
    """A seeded multi-part object seen from a random viewpoint: (range image with per-part labels,
    ground-truth superquadrics; label i + 1 = part i).

    `kind` is one of `OBJECTS` (None: drawn from the seed): a table with four legs, a chair (seat, back,
    legs), a mug with a handle, a lamp (base, pole, shade), an L-shape of two boxes, a dumbbell (two
    balls on a bar) or an arm (a base and two links bent at the joint). Parts touch or interpenetrate;
    dimensions are jittered by up to about 18%. The object is seen from a random azimuth and 15 to 50
    degrees above its base, at the distance where its bounding sphere spans 80% of the image height of
    `default_camera(shape)`. Some parts may be hidden in some views (count visible pixels per label).
    """
    rng = np.random.default_rng([seed, 7])
    kind = OBJECTS[int(rng.integers(len(OBJECTS)))] if kind is None else kind
    spec = _object_parts(kind, rng)
    turn = (
        _rx(np.radians(rng.uniform(15, 50)))
        @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
        @ _rz(rng.uniform(0, 2 * np.pi))
    )
    centres = np.array([c for _, _, c, _ in spec], float)
    reach = np.array([np.max(s) for s, _, _, _ in spec])
    mid = 0.5 * ((centres - reach[:, None]).min(0) + (centres + reach[:, None]).max(0))
    radius = float(np.max(np.linalg.norm(centres - mid, axis=1) + reach))
    camera = default_camera(shape)
    distance = radius * camera.fy / (0.4 * shape[0])
    parts = [
        Superquadric.create(
            np.asarray(s, float),
            e,
            rotation=turn @ R,
            translation=turn @ (np.asarray(c, float) - mid) + (0.0, 0.0, distance),
        )
        for s, e, c, R in spec
    ]
    return render(
        parts, camera, shape, noise=noise * distance / 5.0, dropout=dropout, seed=int(rng.integers(2**31))
    ), parts


def _mesh(mesh):
    import trimesh

    from .formats import load_mesh

    if not isinstance(mesh, trimesh.Trimesh):
        try:
            mesh = load_mesh(mesh, force="mesh")
        except ValueError as e:
            raise ValueError(f"mesh_scene: {mesh}: {e}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("mesh_scene: the mesh has no faces (a point cloud? segment it as points)")
    return mesh


def mesh_parts(mesh) -> list:
    """The parts of a mesh (a `trimesh.Trimesh`, or a file trimesh reads: .stl, .obj, .ply, .off,
    .glb): its connected components (faces joined by shared edges) of at least 4 faces, as meshes."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    mesh = _mesh(mesh)
    adj = mesh.face_adjacency
    n = len(mesh.faces)
    _, comp = connected_components(coo_matrix((np.ones(len(adj)), (adj[:, 0], adj[:, 1])), shape=(n, n)))
    # each component's faces in index order, in one pass (not one scan of every face per component)
    by_comp = np.split(np.argsort(comp, kind="stable"), np.cumsum(np.bincount(comp))[:-1])
    groups = [g for g in by_comp if g.size >= 4]
    if not groups:
        raise ValueError("mesh_scene: the mesh has no connected component of 4 faces or more")
    parts = mesh.submesh(groups, only_watertight=False)
    return list(parts) if isinstance(parts, list) else [parts]


def _bounding_sphere(mesh) -> tuple[np.ndarray, float]:
    """(centre, radius) of trimesh's minimum bounding sphere; for a flat mesh, whose convex hull trimesh
    cannot orient without networkx, the sphere about its vertices' box centre."""
    try:
        sphere = mesh.bounding_sphere.primitive
        return np.asarray(sphere.center, float), float(sphere.radius)
    except Exception:  # trimesh raises many kinds on degenerate hulls
        v = np.asarray(mesh.vertices, float)
        centre = 0.5 * (v.min(0) + v.max(0))
        return centre, float(np.max(np.linalg.norm(v - centre, axis=1)))


def mesh_scene(
    mesh, *, azimuth: float = 30.0, elevation: float = 30.0, shape=(120, 160), noise: float = 0.005, seed: int = 0
):
    """A mesh seen from a viewpoint, one label per part: (range image with per-part labels, the parts as
    `trimesh.Trimesh` in the camera frame (label i + 1 = part i), the 4 x 4 similarity from the mesh's
    frame to the camera frame).

    `mesh`: a `trimesh.Trimesh` or a mesh file; its parts are its connected components (`mesh_parts`:
    a CAD assembly's bodies, the legs of pyvista's ant). The camera looks at the centre of the mesh's
    bounding sphere from `azimuth` degrees about its z axis and `elevation` degrees above its xy plane.
    Like every scene here the mesh is scaled to the scenes' units: the sphere's centre 5 units in front
    of `default_camera(shape)`, its radius 40% of the image height, and `noise` is the depth noise std
    in those units (the benchmark's `meshes` suite). Map a segmented part back to the mesh's frame with
    the inverse of the similarity (`np.linalg.inv(T)`; `trimesh.Trimesh.apply_transform`). To segment
    a mesh into parts, segment such views of it: read as a cloud, a CAD mesh is its vertices, which
    sample its surface unevenly."""
    mesh = _mesh(mesh)
    parts = mesh_parts(mesh)
    centre, radius = _bounding_sphere(mesh)
    camera = default_camera(shape)
    distance = 5.0
    scale = 0.4 * shape[0] * distance / camera.fy / radius
    R = _rx(np.radians(elevation)) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) @ _rz(np.radians(azimuth))
    moved = []
    for p in parts:
        q = p.copy()
        q.vertices = (np.asarray(q.vertices, float) - centre) * scale @ R.T + (0.0, 0.0, distance)
        moved.append(q)
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = (0.0, 0.0, distance) - scale * R @ centre
    return render(moved, camera, shape, noise=noise, seed=seed), moved, T
