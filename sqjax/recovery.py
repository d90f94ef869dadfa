"""Model recovery (the paper's section 2.1 and 3.2): seeds, and the growth of every hypothesis.

Host orchestration in numpy around jit-compiled batch kernels: the refits of all active hypotheses at
a growth step (`fitting.fit_padded`, warm-started) and the eq. 10 distances (`_pair_distances`). The
refit of all active hypotheses at a growth step goes in calls of a few fixed numbers of problems
(`fitting.call_size`) and point counts (128 or max_points), so a growth step recompiles only when it
first meets a new size. Distances are computed only for the (model, point) pairs that are read (a
region and the ring of candidates around it), in fixed chunks of `_PAIRS`.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from . import rotation as so3
from .fitting import FitOptions, bucket, call_size, fit_padded
from .rangeimage import OrthographicCamera, PinholeCamera, RangeImage
from .superquadric import log_inside_outside_and_gradient

if TYPE_CHECKING:
    from .segment import SegmentOptions

NUM_PARAMS = 11
_PAIRS = 1 << 15  # (model, point) pairs per call of the distance kernel
_QUEUE = 3  # distance chunks in flight while one is read back


def _pair_chunk(E: int) -> int:
    """Pairs per call of a pair kernel for E pairs: 1024 times a power of 4, at most `_PAIRS` (four
    compiled sizes; a padded call's pairs are cheap next to a compile, about 1 s each on CPU)."""
    n = 1024
    while n < min(E, _PAIRS):
        n *= 4
    return min(n, _PAIRS)


_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))  # 8-neighbours (row, col)


@dataclasses.dataclass
class _Domain:
    points: np.ndarray  # (P, 3) valid points
    neighbours: np.ndarray  # (P, k) indices into points, -1 for none
    seeds: list  # index arrays, one per seed window
    index: np.ndarray  # (P,) flat pixel index (images) or point index (clouds)
    shape: tuple  # label output shape
    edges: np.ndarray | None = None  # images: (8, H, W) bool, pixel joined to its `_OFFSETS[k]` neighbour
    views: np.ndarray | None = None  # (P, 3) unit viewing rays (images), None = unknown (clouds)
    seed_size: int = 0  # points in the smallest seed window (the smallest part seeded)
    noise_model: tuple | None = None  # (k, z_ref): local noise / reference noise = (z / z_ref)^k
    void_rays: np.ndarray | None = None  # (Q, 3) unit viewing rays of the pixels with no return (pinhole images)

    def dilate(self, regions, rings: int):
        """Regions (M, P) bool grown by `rings` steps along the adjacency.

        Images: shifted slices of the (M, H, W) pixel grid, masked by the edges (a memory copy per
        direction, not a gather). Clouds: a gather per neighbour column. (M, P) temporaries only."""
        if self.edges is None:
            return _dilate(regions, self.neighbours, rings)
        H, W = self.shape
        M = regions.shape[0]
        g = np.zeros((M, H * W), bool)
        g[:, self.index] = regions
        g = g.reshape(M, H, W)
        for _ in range(rings):
            step = g.copy()
            for (dr, dc), edge in zip(_OFFSETS, self.edges):
                dst = (slice(max(-dr, 0), H - max(dr, 0)), slice(max(-dc, 0), W - max(dc, 0)))
                src = (slice(max(dr, 0), H + min(dr, 0)), slice(max(dc, 0), W + min(dc, 0)))
                step[(slice(None),) + dst] |= g[(slice(None),) + src] & edge[dst]
            g = step
        return g.reshape(M, H * W)[:, self.index]


def estimate_noise(image: RangeImage) -> float:
    """Robust depth-noise std from second differences of the depth along rows and columns.

    For a smooth surface z(u-1) - 2 z(u) + z(u+1) has std sqrt(6) sigma; the median absolute value
    (/0.6745) ignores edges. Floored at 1e-4 of the median depth.
    """
    z = image.depth.astype(np.float64)
    d = np.concatenate([(z[:, :-2] - 2 * z[:, 1:-1] + z[:, 2:]).ravel(), (z[:-2] - 2 * z[1:-1] + z[2:]).ravel()])
    d = d[np.isfinite(d)]
    if d.size == 0:
        return float(1e-3 * np.nanmedian(np.abs(z))) if np.isfinite(z).any() else 1.0
    sigma = np.median(np.abs(d)) / 0.6745 / np.sqrt(6.0)
    return float(max(sigma, 1e-4 * np.nanmedian(np.abs(z))))


def noise_exponent(depth: np.ndarray, sigma: np.ndarray, bins: int = 5) -> float:
    """The exponent k of a depth-noise model sigma(z) = sigma_ref (z / z_ref)^k, from local residuals.

    `depth` (S,) and `sigma` (S,): the depth of each seed window and the robust std of its fit's
    residuals. Structured-light and stereo depth noise grows about as z^2 (Khoshelham & Elberink
    2012); one noise at every depth gives 0. A seed's residual is the noise plus its model's error
    (an edge, a curved patch), so the noise at a depth is the floor of the residuals there: the
    seeds are put in `bins` depth quantiles, the lower quartile of sigma taken in each, and k is the
    least-squares slope of its log against log depth, clipped to [0, 2]. Fewer than 8 seeds per bin
    or a depth range under 20% give 0."""
    ok = np.isfinite(depth) & np.isfinite(sigma) & (depth > 0) & (sigma > 0)
    lz, ls = np.log(depth[ok]), np.log(sigma[ok])
    bins = min(bins, lz.size // 8)
    if bins < 3 or lz.max() - lz.min() < np.log(1.2):
        return 0.0
    order = np.argsort(lz)
    groups = np.array_split(order, bins)
    x = np.array([np.median(lz[g]) for g in groups])
    y = np.array([np.quantile(ls[g], 0.25) for g in groups])
    return float(np.clip(np.polyfit(x, y, 1)[0], 0.0, 2.0))


def _plane_residual(q: np.ndarray) -> float:
    """Std of points q (n, 3) about their least-squares plane (unbiased for the 3 fitted dof)."""
    n = q.shape[0]
    return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(q.T))[0], 0.0) * (n - 1) / max(n - 3, 1)))


def robust_centre(points: np.ndarray, far: float = 100.0) -> np.ndarray:
    """The frame of the models: the mean of the points (P, 3) within `far` median radii of their median,
    so that one far outlier (a depth pixel at 1e30) does not move it; the plain mean otherwise."""
    med = np.median(points, 0)
    r = np.linalg.norm(points - med, axis=1)
    near = r <= far * max(float(np.median(r)), 1e-30)
    return points[near].mean(0)


def noise_scale(points: np.ndarray, k: float, z_ref: float) -> np.ndarray:
    """(z / z_ref)^k of camera-frame points (P, 3): their noise in units of the noise at depth z_ref."""
    return (np.abs(points[:, 2]) / z_ref) ** k


def _image_domain(image: RangeImage, window, stride, jump_factor, noise, min_seed, subdivide=True) -> _Domain:
    H, W = image.shape
    valid = image.valid
    pts = image.points
    flat = np.flatnonzero(valid)
    idmap = -np.ones(H * W, np.int64)
    idmap[flat] = np.arange(flat.size)
    idmap = idmap.reshape(H, W)
    P = pts.reshape(-1, 3)[flat]
    # adjacency: 8-neighbours, cut where the 3-D step is a depth discontinuity
    offs = _OFFSETS
    rr, cc = np.divmod(flat, W)
    nb = -np.ones((flat.size, 8), np.int64)
    steps = np.full((flat.size, 8), np.inf)
    for k, (dr, dc) in enumerate(offs):
        r2, c2 = rr + dr, cc + dc
        ok = (r2 >= 0) & (r2 < H) & (c2 >= 0) & (c2 < W)
        j = np.where(ok, idmap[np.clip(r2, 0, H - 1), np.clip(c2, 0, W - 1)], -1)
        nb[:, k] = j
        good = j >= 0
        steps[good, k] = np.linalg.norm(P[good] - P[j[good]], axis=1) / np.hypot(dr, dc)
    typical = np.median(steps[np.isfinite(steps)]) if np.isfinite(steps).any() else 1.0
    jump = steps > jump_factor * typical + 6.0 * noise
    cut = (nb >= 0) & jump
    nb[cut] = -1
    broken = cut.any(1)
    whole, quadrants, smallest = _seed_windows(idmap, broken, window, stride, min_seed, subdivide)
    edges = np.zeros((len(offs), H * W), bool)
    edges[:, flat] = (nb >= 0).T
    void = None
    if isinstance(image.camera, PinholeCamera):  # the camera saw no surface along these rays
        rays = image.camera.rays((H, W))[~valid]
        void = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    return _Domain(
        P,
        nb,
        whole + quadrants,
        flat,
        (H, W),
        edges.reshape(len(offs), H, W),
        viewing_rays(image, P),
        smallest * smallest,
        void_rays=void,
    )


def _seed_windows(idmap, broken, window: int, stride: int, min_seed: int, subdivide: bool) -> tuple[list, list, int]:
    """Seed windows of the (H, W) pixel grid `idmap` (point index, -1 = invalid) as index arrays.

    A `window` x `window` window every `stride` pixels is a seed when it holds `min_seed` valid pixels
    and none of them touches a depth discontinuity (`broken` (P,) bool). With `subdivide`, a window
    that fails is split into its four quadrants, each tried the same way (a quadtree), down to the
    smallest window that can hold `min_seed` pixels: parts smaller than a window, and the
    surfaces between the depth edges of a cluttered scene, still get seeds where whole windows do not
    fit, while surfaces that whole windows cover get no extra hypotheses.

    Returns the whole windows (row-major), the quadrants, and the side of the smallest window among
    them (`window` if none)."""
    H, W = idmap.shape
    smallest = int(np.ceil(np.sqrt(min_seed)))
    whole, quadrants, tried, sides = [], [], set(), [window]

    def visit(r0, c0, w):
        if (r0, c0, w) in tried:
            return
        tried.add((r0, c0, w))
        ids = idmap[r0 : r0 + w, c0 : c0 + w].ravel()
        ids = ids[ids >= 0]
        if ids.size < min_seed:
            return
        if not broken[ids].any():
            (whole if w == window else quadrants).append(ids)
            sides.append(w)
        elif subdivide and w // 2 >= smallest:
            h = w // 2
            for dr in (0, w - h):
                for dc in (0, w - h):
                    visit(r0 + dr, c0 + dc, h)

    for r0 in range(0, max(H - window, 0) + 1, stride):
        for c0 in range(0, max(W - window, 0) + 1, stride):
            visit(r0, c0, window)
    return whole, quadrants, min(sides)


def viewing_rays(image: RangeImage, P: np.ndarray) -> np.ndarray:
    """Unit viewing rays (P, 3) of camera-frame points P (P, 3) of `image`."""
    if isinstance(image.camera, OrthographicCamera):
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), P.shape)
    return P / np.linalg.norm(P, axis=1, keepdims=True)


def _cloud_domain(
    points: np.ndarray, rows: np.ndarray, n_rows: int, nb: np.ndarray, window: int, min_seed: int
) -> _Domain:
    """Points (P, 3) that are rows `rows` of an (n_rows, 3) input; nb (P, k) their nearest neighbours."""
    P = np.asarray(points, np.float64)
    d = np.linalg.norm(P[np.maximum(nb, 0)] - P[:, None], axis=-1)
    nb = np.where((nb < 0) | (d > 4.0 * np.median(d[nb >= 0])), -1, nb)
    # seeds: farthest-point samples, each with its `window` nearest points
    n_seeds = max(1, min(256, P.shape[0] // max(window, 1)))
    centres = [0]
    dmin = np.linalg.norm(P - P[0], axis=1)
    for _ in range(n_seeds - 1):
        centres.append(int(np.argmax(dmin)))
        dmin = np.minimum(dmin, np.linalg.norm(P - P[centres[-1]], axis=1))
    seeds = [ids[ids >= 0] for ids in _knn(P, window, P[centres])]
    seeds = [ids for ids in seeds if ids.size >= min_seed]
    return _Domain(P, nb, seeds, rows, (n_rows,), seed_size=window)


def _knn(P, k, queries=None):
    """Indices (Q, k) of the k nearest points of P (P, 3) to each query (Q, 3), nearest first, by a
    k-d tree (O(P log P)). queries=None: the neighbours of every point of P, itself excluded (also when
    duplicates tie with it). Fewer than k points: the columns past P are -1."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stub)

    own = queries is None
    Q = P if own else queries
    k_eff = min(k + own, P.shape[0])
    _, idx = cKDTree(P).query(Q, k_eff)
    idx = np.asarray(idx, np.int64).reshape(Q.shape[0], k_eff)
    if own:  # drop the query itself (or, if duplicates pushed it out, the farthest)
        is_self = idx == np.arange(Q.shape[0])[:, None]
        drop = np.where(is_self.any(1), is_self.argmax(1), k_eff - 1)
        keep = np.ones_like(idx, bool)
        keep[np.arange(Q.shape[0]), drop] = False
        idx = idx[keep].reshape(Q.shape[0], k_eff - 1)
    return np.pad(idx, ((0, 0), (0, k - idx.shape[1])), constant_values=-1) if idx.shape[1] < k else idx


# ----------------------------------------------------------------------------------------------------
# jitted kernels


@jax.jit
def _pair_distances(theta, points, views, point, enlarge, margin):
    """Eq. 10 distance of `points[point[e]]` to the model `theta[e]`, whether the point
    lies inside that model enlarged (a1..a3 times `enlarge`, plus `margin`), and whether the model's
    outward normal there turns away from the camera (n . view > 0.2 for the unit viewing ray `views`
    (P, 3) of the point; zero rays = unknown, never away).

    theta (E, 11) (one row per pair: the shapes depend on E only), points (P, 3), point (E,) int32
    -> (E,) distances, (E,) bool, (E,) bool.
    Undeformed models only (segmentation fits none): |F - 1| / |grad F| = |1 - 1/F| / |grad log F|,
    which is rotation-invariant, so it is evaluated in the model frame in closed form, without autodiff.
    """
    rot = jax.vmap(so3.exp)(theta[:, 5:8])
    x = jnp.einsum("ei,eij->ej", points[point] - theta[:, 8:11], rot)
    view = jnp.einsum("ei,eij->ej", views[point], rot)
    la, e = theta[:, 0:3], theta[:, 3:5]
    log_f, log_gnorm, normal = log_inside_outside_and_gradient(x, la, e)
    lf = jnp.where(log_f == 0.0, 1e-30, log_f)  # safe operand: F = 1 gives d = 0 below
    log_num = jnp.where(
        lf < 0, -lf + jnp.log(-jnp.expm1(jnp.minimum(lf, -1e-30))), jnp.log(-jnp.expm1(-jnp.maximum(lf, 1e-30)))
    )  # log |1 - 1/F|
    d = jnp.where(log_f == 0.0, 0.0, jnp.exp(jnp.minimum(log_num - log_gnorm, 30.0)))
    big, _, _ = log_inside_outside_and_gradient(x, jnp.log(jnp.exp(la) * enlarge + margin), e)
    return d, big <= 0.0, jnp.sum(normal * view, -1) > 0.2


_RAY_SAMPLES = 16


@jax.jit
def _free_space(theta, points, views, point, margin):
    """Whether the model `theta[e]` occupies the free space in front of the point `points[point[e]]`:
    any of `_RAY_SAMPLES` samples on its viewing ray, from `margin[e]` in front of the point back to the
    near side of the model's bounding sphere, lies inside the model (log F < 0, eq. 5). The camera saw
    through there, so a model that fills it is contradicted by the data. theta (E, 11), points (P, 3),
    views (P, 3) unit rays, point (E,) int32, margin (E,) -> (E,) bool.

    The samples span the sphere's chord: a swollen model (a bar 40 m long and 5 cm thick across the
    ray) is sampled every few metres and seldom seen; `_free_space_box` samples the box's chord."""
    rot = jax.vmap(so3.exp)(theta[:, 5:8])
    p, v, c = points[point], views[point], theta[:, 8:11]
    radius = jnp.sqrt(jnp.sum(jnp.exp(2.0 * theta[:, 0:3]), -1))
    reach = jnp.sum((p - c) * v, -1) + radius  # how far back towards the camera to look
    frac = (jnp.arange(_RAY_SAMPLES) + 0.5) / _RAY_SAMPLES
    back = margin[:, None] + jnp.maximum(reach - margin, 0.0)[:, None] * frac  # (E, S)
    q = p[:, None] - back[..., None] * v[:, None]
    x = jnp.einsum("esi,eij->esj", q - c[:, None], rot)
    log_f, _, _ = log_inside_outside_and_gradient(x, theta[:, None, 0:3], theta[:, None, 3:5])
    return jnp.any(log_f < 0.0, -1) & (reach > margin)


@jax.jit
def _free_space_box(theta, points, views, point, margin, limit):
    """`_free_space` with the samples on the ray's chord of the model's bounding box, between
    `margin[e]` and `limit[e]` (the camera) back from the point: a bar 40 m long and 5 cm thick across
    the ray is sampled across its 5 cm. limit (E,); the rest as `_free_space`."""
    rot = jax.vmap(so3.exp)(theta[:, 5:8])
    p, v, c = points[point], views[point], theta[:, 8:11]
    x0 = jnp.einsum("ei,eij->ej", p - c, rot)  # the point, in the model frame
    dx = -jnp.einsum("ei,eij->ej", v, rot)  # back towards the camera, unit
    a = jnp.exp(theta[:, 0:3])
    tiny = jnp.finfo(x0.dtype).tiny
    big = jnp.finfo(x0.dtype).max
    safe = jnp.where(jnp.abs(dx) > tiny, dx, tiny)
    s1, s2 = (-a - x0) / safe, (a - x0) / safe
    parallel = jnp.abs(dx) <= tiny  # within the slab for every s, or never
    s_lo = jnp.where(parallel, jnp.where(jnp.abs(x0) <= a, -big, big), jnp.minimum(s1, s2))
    s_hi = jnp.where(parallel, jnp.where(jnp.abs(x0) <= a, big, -big), jnp.maximum(s1, s2))
    lo = jnp.maximum(jnp.max(s_lo, -1), margin)
    hi = jnp.minimum(jnp.min(s_hi, -1), limit)
    frac = (jnp.arange(_RAY_SAMPLES) + 0.5) / _RAY_SAMPLES
    back = lo[:, None] + jnp.maximum(hi - lo, 0.0)[:, None] * frac  # (E, S)
    x = x0[:, None] + back[..., None] * dx[:, None]
    log_f, _, _ = log_inside_outside_and_gradient(x, theta[:, None, 0:3], theta[:, None, 3:5])
    return jnp.any(log_f < 0.0, -1) & (hi > lo)


def _pad_rows(a, n, fill):
    return np.concatenate([a, np.repeat(fill[None], n - a.shape[0], 0)]) if n > a.shape[0] else a


def _pairs(regions: list):
    """Index arrays (one per hypothesis) -> (model, point) pairs, as `np.nonzero` of the masks gives."""
    sizes = np.array([r.size for r in regions], np.int64)
    return np.repeat(np.arange(len(regions)), sizes), np.concatenate(regions) if regions else np.zeros(0, np.int64)


def _split(values, model, k):
    """Values (E,) of pairs sorted by model -> list of k arrays, one per model."""
    return np.split(values, np.cumsum(np.bincount(model, minlength=k))[:-1])


class _Models:
    """The hypotheses on the host: parameters theta (M, 11), regions (M, P) bool, and for each model
    the eq. 10 distances of its region's points (`dist[i]` aligned with `np.flatnonzero(regions[i])`,
    float32); flags `active` (still growing) and `loose` (admission at admit_factor * tau)."""

    def __init__(self, theta, regions, dist):
        self.theta, self.regions, self.dist = theta, regions, list(dist)
        self.active = np.ones(len(theta), bool)
        self.loose = np.ones(len(theta), bool)

    def concat(self, other: _Models) -> _Models:
        """These hypotheses followed by `other`'s, flags included."""
        out = _Models(
            np.concatenate([self.theta, other.theta]),
            np.concatenate([self.regions, other.regions]),
            self.dist + other.dist,
        )
        out.active = np.concatenate([self.active, other.active])
        out.loose = np.concatenate([self.loose, other.loose])
        return out

    def take(self, keep):
        keep = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        self.dist = [self.dist[i] for i in keep]
        for name in ("theta", "regions", "active", "loose"):
            setattr(self, name, getattr(self, name)[keep])


class _Runner:
    def __init__(self, dom: _Domain, opts: SegmentOptions, noise: float, tau: float, dtype, centre=None):
        self.dom, self.opts, self.noise, self.tau, self.dtype = dom, opts, noise, tau, dtype
        # per point: the local noise over the reference noise (`noise_exponent`); distances are divided
        # by it, so that tau and the selection weights count in units of the local noise
        self.scale = None if dom.noise_model is None else noise_scale(dom.points, *dom.noise_model).astype(np.float32)
        self.centre = robust_centre(dom.points) if centre is None else np.asarray(centre, np.float64)
        self.host_points = dom.points - self.centre  # float32 keeps its precision near the data
        Pn = -(-dom.points.shape[0] // 4096) * 4096  # a few sizes share one compiled kernel
        self.points = jnp.asarray(_pad_rows(self.host_points, Pn, np.zeros(3)), dtype)
        views = np.zeros_like(self.host_points) if dom.views is None else dom.views
        self.views = jnp.asarray(_pad_rows(views, Pn, np.zeros(3)), dtype)
        self.P = dom.points.shape[0]
        self.margin = 2.0 * tau

    def set_noise_model(self, k: float, z_ref: float):
        self.dom.noise_model = (k, z_ref)
        self.scale = noise_scale(self.dom.points, k, z_ref).astype(np.float32)

    def set_noise(self, noise):
        self.noise, self.tau = noise, self.opts.threshold_factor * noise
        self.margin = 2.0 * self.tau

    def distances(self, theta, model, point):
        """Eq. 10 distances (E,) float32 of the pairs (point[e] to model theta[model[e]]), whether
        each point is inside its model enlarged (E,) bool and whether the model's surface there faces
        away from the camera (E,) bool (see `_pair_distances`). theta (K, 11); model, point (E,).

        Only the pairs asked for are computed (a region and the ring around it, not every point), in
        fixed chunks of `_PAIRS` (smaller calls padded, `_pair_chunk`), a few queued ahead of the
        one read back. Each pair gets its model's row of theta, gathered here, so the kernel compiles
        once per chunk size whatever the number of models.
        """
        E = model.size
        d, inside, away = np.empty(E, np.float32), np.empty(E, bool), np.empty(E, bool)
        if E == 0:
            return d, inside, away
        theta = np.asarray(theta, np.dtype(self.dtype))
        args = (jnp.asarray(self.opts.enlarge, self.dtype), jnp.asarray(self.margin, self.dtype))
        n = _pair_chunk(E)

        def read(s, out):
            m = min(n, E - s)
            for dst, src in zip((d, inside, away), out):
                dst[s : s + m] = np.asarray(src)[:m]

        pending = []
        for s in range(0, E, n):
            mi, pi = np.zeros(n, np.int64), np.zeros(n, np.int32)
            mi[: min(n, E - s)], pi[: min(n, E - s)] = model[s : s + n], point[s : s + n]
            th = jnp.asarray(theta[mi], self.dtype)
            pending.append((s, _pair_distances(th, self.points, self.views, jnp.asarray(pi), *args)))
            if len(pending) > _QUEUE:
                read(*pending.pop(0))
        for item in pending:
            read(*item)
        if self.scale is not None:
            d /= self.scale[point]
        return d, inside, away

    def free_space_violations(self, theta, *, box: bool = False) -> np.ndarray:
        """(M,) for models theta (M, 11): the valid points whose viewing ray passes through the model
        in front of them (by more than tau, in units of the local noise; `_free_space`). Candidates
        are the points whose ray passes within the model's bounding sphere, in front of the point.
        Images only (clouds have no viewpoint): zeros otherwise. `box`: sampled with `_free_space_box`."""
        M = len(theta)
        out = np.zeros(M, np.int64)
        if self.dom.views is None or M == 0:
            return out
        P, v = self.host_points, self.dom.views
        c = theta[:, 8:11]
        radius = np.sqrt(np.sum(np.exp(2.0 * theta[:, 0:3]), -1))
        pairs_m, pairs_p = [], []
        for i in range(M):
            w = P - c[i]
            t = np.einsum("pj,pj->p", w, v)  # > 0: the model's centre is in front of p
            perp2 = np.einsum("pj,pj->p", w, w) - t * t
            cand = np.flatnonzero((perp2 < radius[i] ** 2) & (t + radius[i] > self.tau))
            pairs_m.append(np.full(cand.size, i))
            pairs_p.append(cand)
        model, point = np.concatenate(pairs_m), np.concatenate(pairs_p)
        if model.size == 0:
            return out
        margin = self.tau * (np.ones(point.size) if self.scale is None else self.scale[point])
        return self._ray_hits(theta, model, P[point], v[point], margin, box)

    def _ray_hits(self, theta, model, ends, rays, margin, box: bool = False) -> np.ndarray:
        """(M,) counts of the pairs e whose ray, back from `ends[e]` along `-rays[e]` (from `margin[e]`
        on), passes through the model `theta[model[e]]` (`_free_space`), in fixed-size chunks."""
        theta_d = np.asarray(theta, np.dtype(self.dtype))
        n = _pair_chunk(model.size)
        hit = np.zeros(model.size, bool)
        for s in range(0, model.size, n):
            m = min(n, model.size - s)
            mi, pts, ray, mg = np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)
            mi[:m], pts[:m], ray[:m], mg[:m] = model[s : s + m], ends[s : s + m], rays[s : s + m], margin[s : s + m]
            args = (
                jnp.asarray(theta_d[mi]),
                jnp.asarray(pts, self.dtype),
                jnp.asarray(ray, self.dtype),
                jnp.arange(n, dtype=jnp.int32),
                jnp.asarray(mg, self.dtype),
            )
            if box:  # back to the camera at most (its plane, orthographic)
                limit = np.einsum("ej,ej->e", pts + self.centre, ray)
                hit[s : s + m] = np.asarray(_free_space_box(*args, jnp.asarray(limit, self.dtype)))[:m]
            else:
                hit[s : s + m] = np.asarray(_free_space(*args))[:m]
        return np.bincount(model[hit], minlength=len(theta))

    def void_violations(self, theta, *, box: bool = False) -> np.ndarray:
        """(M,) for models theta (M, 11): the pixels with no return (`_Domain.void_rays`) whose viewing
        ray passes through the model (`_free_space` along the ray's chord of the bounding sphere). The
        camera saw no surface there, so a model there is contradicted. Pinhole images only: zeros
        otherwise. `box`: sampled with `_free_space_box`."""
        M = len(theta)
        out = np.zeros(M, np.int64)
        v = self.dom.void_rays
        if v is None or M == 0 or len(v) == 0:
            return out
        o = -self.centre  # the camera, in the runner's frame
        c = theta[:, 8:11]
        radius = np.sqrt(np.sum(np.exp(2.0 * theta[:, 0:3]), -1))
        pairs_m, ends, dirs = [], [], []
        for i in range(M):
            t = (c[i] - o) @ v.T  # along each ray to the model's centre
            perp2 = np.sum((c[i] - o) ** 2) - t * t
            cand = np.flatnonzero((perp2 < radius[i] ** 2) & (t + radius[i] > 0))
            pairs_m.append(np.full(cand.size, i))
            ends.append(o + (t[cand] + radius[i])[:, None] * v[cand])  # behind the sphere, on the ray
            dirs.append(v[cand])
        model, end, ray = np.concatenate(pairs_m), np.concatenate(ends), np.concatenate(dirs)
        if model.size == 0:
            return out
        return self._ray_hits(theta, model, end, ray, np.zeros(model.size), box)

    def fit(self, regions, theta0, steps, size_bound=False):
        """Fit each region (index array, subsampled to max_points) from theta0 (K, 11), or with the
        fitter's own multistart (moment axes + EMS switches) when theta0 is None -> theta (K, 11).

        The regions go to the batch kernel in calls of one size (`fitting.call_size`: on CPU 4096 // N
        problems), each of N = 128 points when all regions fit (seed windows at 160x120 hold
        about 100), else of max_points. Kernels compiled on CPU: one per (N, start or multistart),
        5-15 s each the first time. The calls are queued before any result is read back.
        """
        K = len(regions)
        cap = bucket(self.opts.max_points, 32)
        small = max(min(r.size, self.opts.max_points) for r in regions) <= 128
        N = min(128, cap) if small else cap
        # the size bound traced, not compiled in: growth (which extrapolates) and the bounded part refits
        # share one kernel per shape
        opts = FitOptions(max_steps=steps, multistart=theta0 is None, size_bound=np.asarray(size_bound))
        pts = np.zeros((K, N, 3))
        msk = np.zeros((K, N), bool)
        for i, r in enumerate(regions):
            if r.size > self.opts.max_points:
                r = r[np.linspace(0, r.size - 1, self.opts.max_points).astype(np.int64)]
            pts[i, : r.size], msk[i, : r.size] = self.host_points[r], True
        size = call_size(K, N)  # one kernel per refit: a long one's last call is full too
        rows = np.arange(-(-K // size) * size)
        rows = np.where(rows < K, rows, 0).reshape(-1, size)  # padding: copies of problem 0, dropped below
        pending = [
            fit_padded(
                jnp.asarray(pts[r], self.dtype),
                jnp.asarray(msk[r]),
                None if theta0 is None else jnp.asarray(theta0[r], self.dtype),
                opts,
            )[0]
            for r in rows
        ]
        theta = np.concatenate([np.asarray(t) for t in pending])[:K].astype(np.float64)
        return np.where(np.isfinite(theta).all(1, keepdims=True), theta, np.nan)


def _dilate(regions, neighbours, rings):
    """Regions (M, P) grown by `rings` steps along the adjacency (P, k); (M, P) temporaries only."""
    cols = [(np.where(nb >= 0, nb, 0), nb >= 0) for nb in neighbours.T]
    out = regions
    for _ in range(rings):
        step = out.copy()
        for nb, ok in cols:
            step |= out[:, nb] & ok
        out = step
    return out


# ----------------------------------------------------------------------------------------------------
# the recover-and-select loop


def _starts(points: np.ndarray, regions: list, origin: np.ndarray | None = None) -> np.ndarray:
    """Starting models (C=3, K, 11) for point sets given as index arrays: the moment ellipsoid of
    Solina & Bajcsy, and a thick ellipsoid and box.

    Axes from the central second moments (z = the direction of least spread, the surface normal of a
    patch), half-sizes from the extents, the thickness floored at half the mean lateral half-size.
    The floor matters: a thin start lies on the patch's own mid-plane, and a solid is better found
    from a thick one. With the camera at `origin` (images), a thick start's centre lies behind the
    patch, so that the patch is its front face (one view sees the side towards the camera); a start
    with the points on its mid-plane is a saddle of the distances (their gradient has no component
    along the normal there), which an exactly planar patch never leaves.
    """
    K = len(regions)
    R = np.zeros((K, 3, 3))
    centre, half, thin, back = np.zeros((K, 3)), np.zeros((K, 3)), np.zeros((K, 3)), np.zeros((K, 3))
    for i, ids in enumerate(regions):
        q = points[ids]
        c = q.mean(0)
        _, V = np.linalg.eigh(np.cov((q - c).T))
        V = V[:, ::-1].copy()  # largest spread first; z = least
        V[:, 2] *= np.sign(np.linalg.det(V))
        loc = (q - c) @ V
        lo, hi = loc.min(0), loc.max(0)
        h = np.maximum((hi - lo) / 2, 1e-9)
        thin[i] = h
        h = h.copy()
        h[2] = max(h[2], 0.25 * (h[0] + h[1]))
        R[i], centre[i], half[i] = V, c + V @ ((lo + hi) / 2), h
        if origin is not None:  # away from the camera, by the added thickness
            n = V[:, 2] * (1.0 if np.dot(centre[i] - origin, V[:, 2]) >= 0 else -1.0)
            back[i] = n * (h[2] - thin[i, 2])
    w = np.asarray(_log_rotations(jnp.asarray(_pad_rows(R, bucket(K, 32), np.eye(3)))), np.float64)[:K]
    out = [np.concatenate([np.log(np.maximum(thin, 1e-3 * thin.max(1, keepdims=True))), np.ones((K, 2)), w, centre], 1)]
    for e in (1.0, 0.3):
        out.append(np.concatenate([np.log(half), np.full((K, 2), e), w, centre + back], 1))
    return np.stack(out)


_log_rotations = jax.jit(so3.log)


def _fit_best(run: _Runner, regions: list, steps: int, multistart: bool = False):
    """Fit every region (sorted index arrays) from each start of `_starts` (and the fitter's
    multistart if asked); keep, per region, the start whose fit explains most of the region's points
    within tau (eq. 10). Returns theta (K, 11), the distances of each region's points (list of K
    arrays) and the score (K,), -inf where no fit succeeded."""
    best = None
    model, point = _pairs(regions)
    sizes = np.array([r.size for r in regions])
    origin = -run.centre if run.dom.views is not None else None  # the camera, in the runner's frame
    starts = list(_starts(run.host_points, regions, origin)) + ([None] if multistart else [])
    for th0 in starts:
        theta = run.fit(regions, th0, steps)
        ok = np.isfinite(theta).all(1)
        theta = np.where(ok[:, None], theta, 0.0)  # pyright: ignore[reportIndexIssue]  (ok: an array, not np.bool)
        d, _, _ = run.distances(theta, model, point)
        explained = np.bincount(model, d < run.tau, len(regions)) / sizes
        rms = np.sqrt(np.bincount(model, np.minimum(d, 1e3).astype(np.float64) ** 2, len(regions)) / sizes)
        score = np.where(ok, explained - 1e-3 * rms / run.tau, -np.inf)
        d = _split(d, model, len(regions))
        if best is None:
            best = [theta, d, score]
        else:
            for i in np.flatnonzero(score > best[2]):
                best[0][i], best[1][i], best[2][i] = theta[i], d[i], score[i]
    return tuple(best)  # pyright: ignore[reportArgumentType]  (there is always a start)


def _seed(run: _Runner, opts: SegmentOptions, seeds: list | None = None):
    """Fit the seed windows (all of the domain's, or `seeds`) and keep those consistent with the noise.

    The first call (all seeds) may raise the noise to the typical seed-fit residual."""
    first = seeds is None
    seeds = [np.sort(ids) for ids in (run.dom.seeds if first else seeds)]
    if not seeds:
        return _Models(np.zeros((0, NUM_PARAMS)), np.zeros((0, run.P), bool), [])
    theta, d, score = _fit_best(run, seeds, opts.fit_steps)
    if first and opts.adaptive_noise and opts.noise is None and opts.threshold is None:
        # Real surfaces are not exact superquadrics: take the noise as at least the typical residual
        # of the seed fits (robust: median over seeds of the median absolute distance / 0.6745).
        fitted = np.flatnonzero(np.isfinite(score))
        sigma = np.array([np.median(d[i]) / 0.6745 for i in fitted])
        if fitted.size:
            if run.dom.edges is not None and opts.noise_exponent is None and run.scale is None:
                # images: how the seeds' residuals grow with depth gives the sensor's noise model; the
                # residual of each window's plane (the least principal axis; the model's eq. 10
                # residual has a floor of its own fitting error)
                depth = np.array([np.median(np.abs(run.dom.points[seeds[i], 2])) for i in fitted])
                k = noise_exponent(depth, np.array([_plane_residual(run.dom.points[seeds[i]]) for i in fitted]))
                if k > 0:
                    run.set_noise_model(k, float(np.median(np.abs(run.dom.points[:, 2]))))
                    sigma = sigma / (depth / run.dom.noise_model[1]) ** k  # pyright: ignore[reportOptionalSubscript]
            run.set_noise(max(run.noise, float(np.median(sigma))))
            model, point = _pairs(seeds)
            d = _split(run.distances(theta, model, point)[0], model, len(seeds))
    regions = np.zeros((len(seeds), run.P), bool)
    keep = np.isfinite(score)
    dist = []
    for i, ids in enumerate(seeds):
        inl = d[i] < run.tau
        keep[i] &= inl.mean() >= opts.seed_inlier_fraction  # statistically consistent with the noise
        regions[i, ids[inl]] = True
        dist.append(d[i][inl])
    models = _Models(theta, regions, dist)
    models.take(keep)
    return models


def free_components(free, neighbours, min_size: int, max_size: int | None = None) -> list:
    """Connected sets of `free` points (P,) bool along the adjacency (P, k), as index arrays, for the
    components with `min_size` to `max_size` (None: any) points (min-label propagation with pointer
    jumping)."""
    P = free.shape[0]
    label = np.where(free, np.arange(P), P)
    nb = np.where(neighbours >= 0, neighbours, np.arange(P)[:, None])
    ok = free[:, None] & free[nb]
    label_ext = np.append(label, P)
    while True:
        cand = np.where(ok, label_ext[nb], P).min(1)
        new = np.minimum(label, cand)
        new = np.where(free, new, P)
        new = np.where(free, np.append(new, P)[new], P)  # pointer jumping: labels are indices
        if np.array_equal(new, label):
            break
        label = new
        label_ext = np.append(label, P)
    ids = np.flatnonzero(free)
    order = np.argsort(label[ids], kind="stable")
    ids, lab = ids[order], label[ids][order]
    cuts = np.flatnonzero(np.diff(lab)) + 1
    return [c for c in np.split(ids, cuts) if min_size <= c.size <= (max_size or P)]


def _grow(run: _Runner, models: _Models, opts: SegmentOptions):
    """One growth step for every active model: enlarge, admit adjacent points near the model, refit.

    Distances are computed only where they are needed: on the candidate ring around each region
    (admission) and on the grown region after the refit (what stays)."""
    act = np.flatnonzero(models.active)
    if act.size == 0:
        return
    R = models.regions[act]
    cand = run.dom.dilate(R, opts.rings) & ~R  # pyright: ignore[reportArgumentType]  (segment() sets rings)
    k, p = np.nonzero(cand)
    d, inside, _ = run.distances(models.theta[act], k, p)
    factor = np.where(models.loose[act], opts.admit_factor, 1.0)
    ok = inside & (d < factor[k] * run.tau)
    before = R.sum(1)
    grown = R.copy()
    grown[k[ok], p[ok]] = True
    has_new = np.bincount(k[ok], minlength=act.size) > 0
    models.active[act[~has_new]] = False
    sel = np.flatnonzero(has_new)
    if sel.size == 0:
        return
    grown = grown[sel]
    new_theta = run.fit([np.flatnonzero(g) for g in grown], models.theta[act[sel]], opts.fit_steps)
    k, p = np.nonzero(grown)
    d, _, _ = run.distances(np.nan_to_num(new_theta), k, p)
    inl = d < run.tau
    kept = np.bincount(k[inl], minlength=sel.size)
    size = np.bincount(k, minlength=sel.size)
    dist = _split(d[inl], k[inl], sel.size)
    grown[:] = False
    grown[k[inl], p[inl]] = True  # now the new regions: the grown points within tau
    m = act[sel]
    good = np.isfinite(new_theta).all(1) & (kept >= opts.keep_fraction * size) & (kept > before[sel])
    retry = ~good & models.loose[m]  # retry with only the points within tau
    models.active[m[~good & ~retry]] = False  # fit broke down or no growth: keep the last good state
    models.loose[m[retry]] = False
    models.theta[m[good]], models.regions[m[good]], models.loose[m[good]] = new_theta[good], grown[good], True
    for j in np.flatnonzero(good):
        models.dist[m[j]] = dist[j]


def _domain(data, opts: SegmentOptions, k: int):
    if isinstance(data, RangeImage):
        valid = data.valid
        if not valid.any():
            raise ValueError("segment: the range image has no valid pixel (all depths are NaN, 0 or inf)")
        if valid.sum() < opts.min_seed_points:
            raise ValueError(
                f"segment: the range image has {int(valid.sum())} valid pixels; at least "
                f"{opts.min_seed_points} are needed for one seed"
            )
        noise = opts.noise if opts.noise is not None else estimate_noise(data)
        tau = opts.threshold if opts.threshold is not None else opts.threshold_factor * noise
        H, W = data.shape
        window = opts.window or int(np.clip(round(min(H, W) / 12), 4, 32))
        window = min(window, H, W)
        stride = opts.stride or max(window // 2, 1)
        dom = _image_domain(data, window, stride, opts.jump_factor, noise, opts.min_seed_points, opts.subdivide)
        if opts.noise_exponent:  # else the seeds estimate it (`_seed`), or it is 0
            dom.noise_model = (opts.noise_exponent, float(np.median(np.abs(dom.points[:, 2]))))
        return dom, noise, tau
    pts = np.asarray(data, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"segment: expected a RangeImage or an (P, 3) array, got shape {pts.shape}")
    rows = np.flatnonzero(np.isfinite(pts).all(1))
    n_rows, pts = pts.shape[0], pts[rows]
    if pts.shape[0] < opts.min_seed_points:
        raise ValueError(f"segment: {pts.shape[0]} valid points; at least {opts.min_seed_points} are needed")
    nb = _knn(pts, k)
    spacing = np.median(np.linalg.norm(pts[nb[:, 0]] - pts, axis=1))
    noise = opts.noise if opts.noise is not None else float(max(spacing / 4, 1e-12))
    tau = opts.threshold if opts.threshold is not None else opts.threshold_factor * noise
    window = opts.window or max(opts.min_seed_points, 48)
    return _cloud_domain(pts, rows, n_rows, nb, window, opts.min_seed_points), noise, tau
