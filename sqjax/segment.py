"""Recover-and-select: direct part-level segmentation with superquadrics (Leonardis, Jaklič, Solina).

Host orchestration in numpy around three jit-compiled batch kernels: the seed fits, the warm-started
refits of all active hypotheses at a growth step (`fitting.fit_padded`), and the distances of every
data point to every active model (`_distances`). Shapes are padded to power-of-two buckets so a
growth step never recompiles.
"""

from __future__ import annotations

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .fitting import FitOptions, bucket, fit_padded, to_superquadric
from .rangeimage import RangeImage
from .selection import SelectionWeights, build_q, select
from . import rotation as so3
from .superquadric import Superquadric, contains, distance

NUM_PARAMS = 11
_CHUNK = 32   # hypotheses per kernel call: fixed, so the kernels compile once


@dataclasses.dataclass(frozen=True)
class SegmentOptions:
    """Settings of `segment` (units are those of the data).

    - `noise`: sensor noise std; None = estimated from the data (`estimate_noise`).
    - `threshold`: admission distance tau (eq. 10); None = `threshold_factor * noise`.
    - `adaptive_noise`: when the noise is estimated, raise it to the typical residual of the seed fits
      (real surfaces are not exact superquadrics).
    - `window`, `stride`: seed windows in pixels (None = from the image size); clouds: `window` points.
    - `min_seed_points`: fewest valid points in a seed window (2x the 11 parameters).
    - `enlarge`: growth factor on a1..a3; `rings`: image-adjacent rings searched per growth step.
    - `admit_factor`: candidates within `admit_factor * tau` of the current model are tried; after the
      refit only points within tau stay, and the step is kept if at least `keep_fraction` of them do.
      (Lets a model turn a box edge, where the next face starts off the current surface.)
    - `select_every`: growth steps between selections; `max_steps`: cap on growth steps.
    - `max_points`: a region is subsampled to at most this many points for its refit.
    - `weights`: K1, K2, K3 (None = `SelectionWeights.for_threshold(tau)`); `selector`: "greedy" (the
      paper), "local" or "exact".
    - `merge`: try joining selected models whose union one superquadric explains (occlusion splits).
    - `min_exclusive`: after the final selection, a model explaining less than this share of its
      region alone (the rest is also explained by others) is dropped as redundant.
    """

    noise: float | None = None
    threshold: float | None = None
    threshold_factor: float = 3.0
    adaptive_noise: bool = True
    window: int | None = None
    stride: int | None = None
    min_seed_points: int = 2 * NUM_PARAMS
    seed_inlier_fraction: float = 0.9
    enlarge: float = 1.15
    admit_factor: float = 3.0
    rings: int = 2
    keep_fraction: float = 0.9
    select_every: int = 3
    max_steps: int = 60
    max_points: int = 512
    fit_steps: int = 10
    weights: SelectionWeights | None = None
    selector: str = "greedy"
    merge: bool = True
    min_exclusive: float = 0.2
    jump_factor: float = 4.0


@dataclasses.dataclass(frozen=True)
class Part:
    """One selected model: `superquadric`, its `region` (flat pixel indices, or point indices for
    clouds), `error` (sum of squared eq. 10 distances over the region), `num_points`."""

    superquadric: Superquadric
    region: np.ndarray
    error: float
    num_points: int


@dataclasses.dataclass
class Segmentation:
    """What `segment` returns.

    - `parts`: the selected models, largest first.
    - `labels`: (H, W) int32 for range images ((P,) for clouds): 0 = none, i + 1 = `parts[i]`.
    - `history`: after each selection, the list of selected `Superquadric`s (the paper's panels d–f).
    - `noise`, `threshold`: the values used; `timings`: seconds (`total`, `compile`, `run`), and counts.
    """

    parts: list
    labels: np.ndarray
    history: list
    noise: float
    threshold: float
    timings: dict
    stats: dict

    def to_dict(self) -> dict:
        return {
            "parts": [{**p.superquadric.to_dict(), "num_points": int(p.num_points), "error": float(p.error)}
                      for p in self.parts],
            "noise": float(self.noise), "threshold": float(self.threshold),
            "timings": self.timings, "stats": self.stats,
        }


# ----------------------------------------------------------------------------------------------------
# the data: points, adjacency (image grid or k nearest neighbours), seeds


@dataclasses.dataclass
class _Domain:
    points: np.ndarray            # (P, 3) valid points
    neighbours: np.ndarray        # (P, k) indices into points, -1 for none
    seeds: list                   # index arrays, one per seed window
    index: np.ndarray             # (P,) flat pixel index (images) or point index (clouds)
    shape: tuple                  # label output shape


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


def _image_domain(image: RangeImage, window, stride, jump_factor, noise, min_seed) -> _Domain:
    H, W = image.shape
    valid = image.valid
    pts = image.points
    flat = np.flatnonzero(valid)
    idmap = -np.ones(H * W, np.int64)
    idmap[flat] = np.arange(flat.size)
    idmap = idmap.reshape(H, W)
    P = pts.reshape(-1, 3)[flat]
    # adjacency: 8-neighbours, cut where the 3-D step is a depth discontinuity
    offs = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
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
    seeds = []
    for r0 in range(0, max(H - window, 0) + 1, stride):
        for c0 in range(0, max(W - window, 0) + 1, stride):
            ids = idmap[r0 : r0 + window, c0 : c0 + window].ravel()
            ids = ids[ids >= 0]
            if ids.size >= min_seed and not broken[ids].any():
                seeds.append(ids)
    return _Domain(P, nb, seeds, flat, (H, W))


def _cloud_domain(points: np.ndarray, k: int, window: int, min_seed: int) -> _Domain:
    P = np.asarray(points, np.float64)
    nb = _knn(P, k)
    d = np.linalg.norm(P[nb] - P[:, None], axis=-1)
    nb = np.where(d > 4.0 * np.median(d), -1, nb)
    # seeds: farthest-point samples, each with its `window` nearest points
    n_seeds = max(1, min(256, P.shape[0] // max(window, 1)))
    centres = [0]
    dmin = np.linalg.norm(P - P[0], axis=1)
    for _ in range(n_seeds - 1):
        centres.append(int(np.argmax(dmin)))
        dmin = np.minimum(dmin, np.linalg.norm(P - P[centres[-1]], axis=1))
    seeds = [ids for ids in _knn(P, window, P[centres]) if ids.size >= min_seed]
    return _Domain(P, nb, seeds, np.arange(P.shape[0]), (P.shape[0],))


def _knn(P, k, queries=None, block=2048):
    """k nearest neighbours (excluding the query itself when queries is None), brute force in blocks."""
    Q = P if queries is None else queries
    k_eff = min(k + (queries is None), P.shape[0])
    out = np.empty((Q.shape[0], k_eff), np.int64)
    sq = np.sum(P * P, 1)
    for s in range(0, Q.shape[0], block):
        q = Q[s : s + block]
        d = sq[None] - 2 * q @ P.T + np.sum(q * q, 1)[:, None]
        idx = np.argpartition(d, k_eff - 1, axis=1)[:, :k_eff]
        order = np.take_along_axis(d, idx, 1).argsort(1)
        out[s : s + block] = np.take_along_axis(idx, order, 1)
    return out[:, 1:] if queries is None else out


# ----------------------------------------------------------------------------------------------------
# jitted kernels over all data points


@eqx.filter_jit
def _distances(theta, points, enlarge, margin):
    """theta (K, 11), points (P, 3) -> eq. 10 distances (K, P) and inside-enlarged-model (K, P) bool."""
    def one(th):
        sq = to_superquadric(th)
        big = Superquadric(sq.size * enlarge + margin, sq.epsilon, sq.rotation, sq.translation, sq.taper, sq.bend)
        return distance(sq, points), contains(big, points)
    return jax.vmap(one)(theta)


def _pad_rows(a, n, fill):
    return np.concatenate([a, np.repeat(fill[None], n - a.shape[0], 0)]) if n > a.shape[0] else a


class _Models:
    """The hypotheses on the host: parameters (M, 11), regions (M, P) bool, distances (M, P) of every
    point to each model, inside-the-enlarged-model (M, P), and the active flags (M,)."""

    def __init__(self, theta, regions, dist, inside):
        self.theta, self.regions, self.dist, self.inside = theta, regions, dist, inside
        self.active = np.ones(len(theta), bool)
        self.loose = np.ones(len(theta), bool)     # admission at admit_factor * tau (else tau)

    def take(self, keep):
        for name in ("theta", "regions", "dist", "inside", "active", "loose"):
            setattr(self, name, getattr(self, name)[keep])


class _Runner:
    def __init__(self, dom: _Domain, opts: SegmentOptions, noise: float, tau: float, dtype):
        self.dom, self.opts, self.noise, self.tau, self.dtype = dom, opts, noise, tau, dtype
        Pn = -(-dom.points.shape[0] // 4096) * 4096   # a few sizes share one compiled kernel
        self.centre = dom.points.mean(0)
        self.host_points = dom.points - self.centre   # float32 keeps its precision near the data
        self.points = jnp.asarray(_pad_rows(self.host_points, Pn, np.full(3, 1e6)), dtype)
        self.P = dom.points.shape[0]
        self.margin = 2.0 * tau

    def set_noise(self, noise):
        self.noise, self.tau = noise, self.opts.threshold_factor * noise
        self.margin = 2.0 * self.tau

    def distances(self, theta):
        """(K, 11) -> eq. 10 distances (K, P) and inside-the-enlarged-model (K, P), in fixed-size chunks."""
        K = theta.shape[0]
        ds, ins = [], []
        for s in range(0, K, _CHUNK):
            th = _pad_rows(theta[s : s + _CHUNK], _CHUNK, theta[s])
            d, inside = _distances(jnp.asarray(th, self.dtype), self.points,
                                   jnp.asarray(self.opts.enlarge, self.dtype), jnp.asarray(self.margin, self.dtype))
            ds.append(np.asarray(d)[:, : self.P])
            ins.append(np.asarray(inside)[:, : self.P])
        return np.concatenate(ds)[:K].astype(np.float64), np.concatenate(ins)[:K]

    def fit(self, regions, theta0, steps):
        """Fit each region (index array, subsampled to max_points) from theta0 (K, 11), or with the
        fitter's own multistart (moment axes + EMS switches) when theta0 is None.

        Calls the kernel on fixed (chunk, max_points) shapes: one compilation serves every step.
        """
        K = len(regions)
        cap = self.opts.max_points
        N = bucket(cap, 32)
        opts = FitOptions(max_steps=steps, multistart=theta0 is None)
        out = []
        for s in range(0, K, _CHUNK):
            pts = np.zeros((_CHUNK, N, 3))
            msk = np.zeros((_CHUNK, N), bool)
            for i in range(_CHUNK):
                r = regions[min(s + i, K - 1)]
                if r.size > cap:
                    r = r[np.linspace(0, r.size - 1, cap).astype(np.int64)]
                pts[i, : r.size], msk[i, : r.size] = self.host_points[r], True
            th0 = None if theta0 is None else jnp.asarray(_pad_rows(theta0[s : s + _CHUNK], _CHUNK, theta0[s]),
                                                          self.dtype)
            theta, _, _, _ = fit_padded(jnp.asarray(pts, self.dtype), jnp.asarray(msk), th0, opts)
            out.append(np.asarray(theta))
        theta = np.concatenate(out)[:K].astype(np.float64)
        return np.where(np.isfinite(theta).all(1, keepdims=True), theta, np.nan)


def _dilate(regions, neighbours, rings):
    out = regions
    for _ in range(rings):
        nb = np.where(neighbours >= 0, neighbours, 0)
        hit = out[:, nb] & (neighbours >= 0)[None]
        out = out | hit.any(-1)
    return out


# ----------------------------------------------------------------------------------------------------
# the recover-and-select loop


def _select(models: _Models, tau, opts, weights):
    d2 = np.minimum(models.dist, tau) ** 2
    Q = build_q(models.regions, d2, np.full(len(models.theta), NUM_PARAMS), weights)
    m, stats = select(Q, opts.selector)
    return m, stats


def _starts(points: np.ndarray, regions: list) -> np.ndarray:
    """Starting models (C=3, K, 11) for point sets given as index arrays: the moment ellipsoid of
    Solina & Bajcsy, and a thick ellipsoid and box.

    Axes from the central second moments (z = the direction of least spread, the surface normal of a
    patch), half-sizes from the extents, the thickness floored at half the mean lateral half-size.
    The floor matters: on a nearly planar patch the size-weighted cost (eq. 7) is smallest for a
    slab as thin as the noise, which explains the points badly; a thick start finds the solid.
    """
    K = len(regions)
    R = np.zeros((K, 3, 3))
    centre, half, thin = np.zeros((K, 3)), np.zeros((K, 3)), np.zeros((K, 3))
    for i, ids in enumerate(regions):
        q = points[ids]
        c = q.mean(0)
        _, V = np.linalg.eigh(np.cov((q - c).T))
        V = V[:, ::-1].copy()                       # largest spread first; z = least
        V[:, 2] *= np.sign(np.linalg.det(V))
        loc = (q - c) @ V
        lo, hi = loc.min(0), loc.max(0)
        h = np.maximum((hi - lo) / 2, 1e-9)
        thin[i] = h
        h = h.copy()
        h[2] = max(h[2], 0.25 * (h[0] + h[1]))
        R[i], centre[i], half[i] = V, c + V @ ((lo + hi) / 2), h
    w = np.asarray(_log_rotations(jnp.asarray(_pad_rows(R, bucket(K, 32), np.eye(3)))), np.float64)[:K]
    out = [np.concatenate([np.log(np.maximum(thin, 1e-3 * thin.max(1, keepdims=True))), np.ones((K, 2)), w, centre], 1)]
    for e in (1.0, 0.3):
        out.append(np.concatenate([np.log(half), np.full((K, 2), e), w, centre], 1))
    return np.stack(out)


_log_rotations = jax.jit(so3.log)


def _fit_best(run: _Runner, regions: list, steps: int, multistart: bool = False):
    """Fit every region from each start of `_starts` (and the fitter's multistart if asked); keep, per region, the start whose fit explains
    most of the region's points within tau (eq. 10). Returns theta (K, 11), distances, inside flags."""
    best = None
    starts = list(_starts(run.host_points, regions)) + ([None] if multistart else [])
    for th0 in starts:
        theta = run.fit(regions, th0, steps)
        ok = np.isfinite(theta).all(1)
        theta = np.where(ok[:, None], theta, 0.0)
        d, inside = run.distances(theta)
        score = np.array([np.mean(d[i, r] < run.tau) - 1e-3 * np.sqrt(np.mean(np.minimum(d[i, r], 1e3) ** 2))
                          / run.tau if ok[i] else -np.inf for i, r in enumerate(regions)])
        if best is None:
            best = [theta, d, inside, score]
        else:
            better = score > best[3]
            for j, new in enumerate((theta, d, inside, score)):
                best[j] = np.where(better.reshape((-1,) + (1,) * (new.ndim - 1)), new, best[j])
    return best[0], best[1], best[2], best[3]


def _seed(run: _Runner, opts: SegmentOptions):
    dom = run.dom
    if not dom.seeds:
        return _Models(np.zeros((0, NUM_PARAMS)), np.zeros((0, run.P), bool), np.zeros((0, run.P)),
                       np.zeros((0, run.P), bool))
    theta, d, inside, score = _fit_best(run, dom.seeds, opts.fit_steps)
    if opts.adaptive_noise and opts.noise is None and opts.threshold is None:
        # Real surfaces are not exact superquadrics: take the noise as at least the typical residual
        # of the seed fits (robust: median over seeds of the median absolute distance / 0.6745).
        per_seed = [np.median(d[i, ids]) / 0.6745 for i, ids in enumerate(dom.seeds) if np.isfinite(score[i])]
        if per_seed:
            run.set_noise(max(run.noise, float(np.median(per_seed))))
            d, inside = run.distances(theta)
    regions = np.zeros((len(dom.seeds), run.P), bool)
    keep = np.isfinite(score)
    for i, ids in enumerate(dom.seeds):
        inl = d[i, ids] < run.tau
        keep[i] &= inl.mean() >= opts.seed_inlier_fraction      # statistically consistent with the noise
        regions[i, ids[inl]] = True
    models = _Models(theta, regions, d, inside)
    models.take(keep)
    return models


def _grow(run: _Runner, models: _Models, opts: SegmentOptions):
    """One growth step for every active model: enlarge, admit adjacent points near the model, refit."""
    act = np.flatnonzero(models.active)
    if act.size == 0:
        return
    R = models.regions[act]
    cand = _dilate(R, run.dom.neighbours, opts.rings) & ~R
    factor = np.where(models.loose[act], opts.admit_factor, 1.0)[:, None]
    admit = cand & models.inside[act] & (models.dist[act] < factor * run.tau)
    grown = R | admit
    has_new = admit.any(1)
    theta = models.theta[act].copy()
    if has_new.any():
        sel = np.flatnonzero(has_new)
        new_theta = run.fit([np.flatnonzero(grown[i]) for i in sel], theta[sel], opts.fit_steps)
        new_d, new_in = run.distances(np.nan_to_num(new_theta))
        for k, i in enumerate(sel):
            m = act[i]
            region = grown[i] & (new_d[k] < run.tau)
            ok = np.isfinite(new_theta[k]).all() and region.sum() >= opts.keep_fraction * grown[i].sum()
            if ok and region.sum() > R[i].sum():
                models.theta[m], models.regions[m], models.dist[m], models.inside[m] = (new_theta[k], region,
                                                                                       new_d[k], new_in[k])
                models.loose[m] = True
            elif models.loose[m]:
                models.loose[m] = False             # retry with only the points within tau
            else:
                models.active[m] = False            # fit broke down or no growth: keep the last good state
    models.active[act[~has_new]] = False


def _prune_redundant(models: _Models, min_exclusive: float) -> int:
    """Drop, one at a time, the selected model that explains the smallest share of points no other
    selected model explains, while that share is below `min_exclusive`. Returns how many went.

    Eq. 2 prices a model at K3 N_i points, so a model that duplicates another except for a few dozen
    points can still be selected; such a model is not a part of its own.
    """
    dropped = 0
    while len(models.theta) > 1:
        B = models.regions
        cover = B.sum(0)
        excl = (B & (cover == 1)[None]).sum(1) / np.maximum(B.sum(1), 1)
        i = int(np.argmin(excl))
        if excl[i] >= min_exclusive:
            break
        models.take(np.arange(len(models.theta)) != i)
        dropped += 1
    return dropped


def _merge(run: _Runner, models: _Models, opts):
    """Hypotheses for pairs of selected models that one superquadric may explain (occlusion splits)."""
    M = len(models.theta)
    pairs = [(i, j) for i in range(M) for j in range(i + 1, M)]
    if not pairs:
        return models
    regions = [np.flatnonzero(models.regions[i] | models.regions[j]) for i, j in pairs]
    theta, d, inside, score = _fit_best(run, regions, opts.fit_steps, multistart=True)
    ok = np.isfinite(score)
    union = np.stack([models.regions[i] | models.regions[j] for i, j in pairs])
    reg = union & (d < run.tau)
    good = ok & (reg.sum(1) >= opts.keep_fraction * union.sum(1))
    if not good.any():
        return models
    out = _Models(*(np.concatenate([a, b[good]]) for a, b in
                    ((models.theta, theta), (models.regions, reg), (models.dist, d), (models.inside, inside))))
    out.active[:] = False
    return out


@jax.jit
def _world(theta, centre) -> Superquadric:
    """(M, 11) centred parameters -> batched `Superquadric` in the data's frame."""
    sq = to_superquadric(theta)
    return Superquadric(sq.size, sq.epsilon, sq.rotation, sq.translation + centre, sq.taper, sq.bend)


def segment(data, *, options: SegmentOptions | None = None, k: int = 8, progress=None, **kw) -> Segmentation:
    """Part-level segmentation of a range image (or an (P, 3) point cloud) by recover-and-select.

    **Arguments:**

    - `data`: a `RangeImage` (pixels adjacent on the image grid) or an `(P, 3)` array of points
      (adjacency = `k` nearest neighbours); NaN rows / missing pixels are ignored.
    - `options`: a `SegmentOptions`; keyword arguments build one (`noise=`, `window=`, ...).
    - `progress`: optional callable `progress(step, n_active, n_models)` called after each growth step.

    **Returns:** a `Segmentation` (parts, label image, history, timings).
    """
    opts = options if options is not None else SegmentOptions(**kw)
    t_start = time.perf_counter()
    compile_start = _COMPILE_SECONDS[0]
    if True:
        dom, noise, tau = _domain(data, opts, k)
        dtype = jnp.float32
        run = _Runner(dom, opts, noise, tau, dtype)
        models = _seed(run, opts)
        noise, tau = run.noise, run.tau
        weights = opts.weights or SelectionWeights.for_threshold(tau)
        history, stats = [], {"seeds": len(dom.seeds), "seed_models": len(models.theta), "selections": 0,
                              "greedy_worse": 0, "growth_steps": 0}
        step = 0
        while models.active.any() and step < opts.max_steps:
            for _ in range(opts.select_every):
                _grow(run, models, opts)
                step += 1
                if progress is not None:
                    progress(step, int(models.active.sum()), len(models.theta))
                if not models.active.any() or step >= opts.max_steps:
                    break
            m, st = _select(models, tau, opts, weights)
            stats["selections"] += 1
            stats["greedy_worse"] += int(st["greedy_gap"] > 1e-9)
            models.take(m)
            history.append(models.theta.copy())
        stats["growth_steps"] = step
        if opts.merge and len(models.theta) > 1:
            models = _merge(run, models, opts)
        if len(models.theta):
            m, st = _select(models, tau, opts, weights)
            models.take(m)
            stats["selections"] += 1
            stats["greedy_worse"] += int(st["greedy_gap"] > 1e-9)
            stats["pruned"] = _prune_redundant(models, opts.min_exclusive)
            history.append(models.theta.copy())
        parts, labels = _finish(run, models)
        history = [_to_world(h, run.centre) for h in history]
    total = time.perf_counter() - t_start
    compile_s = _COMPILE_SECONDS[0] - compile_start
    timings = {"total": total, "compile": compile_s, "run": total - compile_s}
    return Segmentation(parts, labels, history, noise, tau, timings, stats)


def _domain(data, opts: SegmentOptions, k: int):
    if isinstance(data, RangeImage):
        valid = data.valid
        if not valid.any():
            raise ValueError("segment: the range image has no valid pixel (all depths are NaN, 0 or inf)")
        if valid.sum() < opts.min_seed_points:
            raise ValueError(f"segment: the range image has {int(valid.sum())} valid pixels; at least "
                             f"{opts.min_seed_points} are needed for one seed")
        noise = opts.noise if opts.noise is not None else estimate_noise(data)
        tau = opts.threshold if opts.threshold is not None else opts.threshold_factor * noise
        H, W = data.shape
        window = opts.window or int(np.clip(round(min(H, W) / 12), 4, 32))
        window = min(window, H, W)
        stride = opts.stride or max(window // 2, 1)
        return _image_domain(data, window, stride, opts.jump_factor, noise, opts.min_seed_points), noise, tau
    pts = np.asarray(data, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"segment: expected a RangeImage or an (P, 3) array, got shape {pts.shape}")
    pts = pts[np.isfinite(pts).all(1)]
    if pts.shape[0] < opts.min_seed_points:
        raise ValueError(f"segment: {pts.shape[0]} valid points; at least {opts.min_seed_points} are needed")
    nb = _knn(pts, k)
    spacing = np.median(np.linalg.norm(pts[nb[:, 0]] - pts, axis=1))
    noise = opts.noise if opts.noise is not None else float(max(spacing / 4, 1e-12))
    tau = opts.threshold if opts.threshold is not None else opts.threshold_factor * noise
    window = opts.window or max(opts.min_seed_points, 48)
    return _cloud_domain(pts, k, window, opts.min_seed_points), noise, tau


def _finish(run: _Runner, models: _Models):
    order = np.argsort(-models.regions.sum(1), kind="stable")
    models.take(order)
    flat = np.zeros(int(np.prod(run.dom.shape)), np.int32)
    if len(models.theta):
        # each pixel to its nearest model; near-ties (within the noise) go to the larger part, so two
        # almost coincident surfaces do not leave a speckle decided by noise
        d = np.where(models.regions, models.dist, np.inf)
        near = d <= d.min(0) + run.noise
        best = np.argmax(near, 0)                       # models are sorted largest first
        has = np.isfinite(d.min(0))
        flat[run.dom.index[has]] = best[has] + 1
    parts = []
    sqs = _to_world(models.theta, run.centre)
    for i, sq in enumerate(sqs):
        reg = np.flatnonzero(models.regions[i])
        parts.append(Part(sq, run.dom.index[reg], float(np.sum(models.dist[i, reg] ** 2)), int(reg.size)))
    return parts, flat.reshape(run.dom.shape)


def _to_world(theta, centre) -> list:
    """(M, 11) centred parameters -> list of M `Superquadric`s (padded so few shapes compile)."""
    M = len(theta)
    if M == 0:
        return []
    th = jnp.asarray(_pad_rows(theta, bucket(M, 8), theta[0]), jnp.float32)
    return _unbatch(_world(th, jnp.asarray(centre, jnp.float32)))[:M]


def _unbatch(sq: Superquadric) -> list:
    leaves = jax.tree.map(np.asarray, sq)
    return [jax.tree.map(lambda v, i=i: jnp.asarray(v[i]), leaves) for i in range(leaves.size.shape[0])]


def _on_jax_event(event, duration, **_):
    if event.startswith("/jax/core/compile/"):
        _COMPILE_SECONDS[0] += duration


_COMPILE_SECONDS = [0.0]
jax.monitoring.register_event_duration_secs_listener(_on_jax_event)
