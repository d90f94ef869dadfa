"""Model recovery (the paper's section 2.1 and 3.2): seeds, and the growth of every hypothesis.

Host orchestration in numpy around jit-compiled batch kernels: the refits of all active hypotheses at
a growth step (`fitting.fit_padded`, warm-started) and the distances of every data point to every
active model (`_distances`). The refit is one call per growth step over all active hypotheses, their
number padded to a few fixed batch sizes (`batch_bucket`) and the point counts to fixed sizes, so a
growth step recompiles only when the hypotheses first reach a new bucket; the distances go out in
fixed chunks of `_CHUNK` hypotheses (one compiled shape).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import rotation as so3
from .fitting import FitOptions, bucket, fit_padded
from .rangeimage import RangeImage
if TYPE_CHECKING:
    from .segment import SegmentOptions

NUM_PARAMS = 11
_CHUNK = 32   # hypotheses per call of the distance kernel (one compiled shape, bounded memory)
_QUEUE = 3    # distance chunks in flight while one is read back


def batch_bucket(k: int) -> int:
    """Padded number of hypotheses for k: 32, 48, 64, 96, 128, 192, ... (at most 1/3 wasted)."""
    b = 32
    while b < k:
        b = b * 3 // 2 if b & (b - 1) == 0 else b * 4 // 3
    return b


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


def _log_f_and_grad(x, log_size, epsilon):
    """log F (eq. 5) of model-frame points x (P, 3) and log |d log F / dx| (P,), closed form.

    With A, B, C the log-powers of |x/a1|, |y/a2|, |z/a3| and the two log-sum-exps s = lse(A, B),
    t = lse(e2/e1 s, C): d log F / dx = 2 w_t w_s / x, d/dy = 2 w_t (1 - w_s) / y, d/dz = 2 (1 - w_t) / z,
    where w are the softmax weights; everything stays in logs, so it is finite at 0 and far away.
    """
    e1, e2 = epsilon[0], epsilon[1]
    tiny = jnp.finfo(x.dtype).tiny
    lx = jnp.log(jnp.maximum(jnp.abs(x), tiny))
    la = lx - log_size
    A, B, C = la[:, 0] * (2 / e2), la[:, 1] * (2 / e2), la[:, 2] * (2 / e1)
    s = jnp.logaddexp(A, B)
    u = s * (e2 / e1)
    t = jnp.logaddexp(u, C)
    log_f = e1 * t
    log_g = jnp.stack([u - t + A - s, u - t + B - s, C - t], -1) - lx + jnp.log(2.0)   # log |components|
    return log_f, 0.5 * jax.scipy.special.logsumexp(2.0 * log_g, axis=-1)


@eqx.filter_jit
def _distances(theta, points, enlarge, margin):
    """theta (K, 11), points (P, 3) -> eq. 10 distances (K, P) and inside-enlarged-model (K, P) bool.

    Undeformed models only (segmentation fits none): |F - 1| / |grad F| = |1 - 1/F| / |grad log F|,
    rotation-invariant, so it is evaluated in the model frame without autodiff.
    """
    def one(th):
        la, e, w, t = th[0:3], th[3:5], th[5:8], th[8:11]
        x = (points - t) @ so3.exp(w)
        log_f, log_gnorm = _log_f_and_grad(x, la, e)
        lf = jnp.where(log_f == 0.0, 1e-30, log_f)           # safe operand: F = 1 gives d = 0 below
        log_num = jnp.where(lf < 0, -lf + jnp.log(-jnp.expm1(jnp.minimum(lf, -1e-30))),
                            jnp.log(-jnp.expm1(-jnp.maximum(lf, 1e-30))))     # log |1 - 1/F|
        d = jnp.where(log_f == 0.0, 0.0, jnp.exp(jnp.minimum(log_num - log_gnorm, 30.0)))
        big, _ = _log_f_and_grad(x, jnp.log(jnp.exp(la) * enlarge + margin), e)
        return d, big <= 0.0
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

    def concat(self, other: _Models) -> _Models:
        """These hypotheses followed by `other`'s, flags included."""
        out = _Models(*(np.concatenate([getattr(self, n), getattr(other, n)]) for n in ("theta", "regions", "dist", "inside")))
        out.active = np.concatenate([self.active, other.active])
        out.loose = np.concatenate([self.loose, other.loose])
        return out

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
        """(K, 11) -> eq. 10 distances (K, P) float32 and inside-the-enlarged-model (K, P).

        Dispatched as fixed chunks of `_CHUNK` hypotheses, a few queued ahead of the one read back:
        on CPU ~2x faster than one call looping over the chunks inside XLA (`lax.map`), and only a
        few chunks of device memory alive at once.
        """
        K = theta.shape[0]
        d, inside = np.empty((K, self.P), np.float32), np.empty((K, self.P), bool)
        args = (self.points, jnp.asarray(self.opts.enlarge, self.dtype), jnp.asarray(self.margin, self.dtype))

        def read(s, out):
            n = min(_CHUNK, K - s)
            d[s : s + n], inside[s : s + n] = np.asarray(out[0])[:n, : self.P], np.asarray(out[1])[:n, : self.P]

        pending = []
        for s in range(0, K, _CHUNK):
            th = jnp.asarray(_pad_rows(theta[s : s + _CHUNK], _CHUNK, theta[s]), self.dtype)
            pending.append((s, _distances(th, *args)))
            if len(pending) > _QUEUE:
                read(*pending.pop(0))
        for item in pending:
            read(*item)
        return d, inside

    def fit(self, regions, theta0, steps):
        """Fit each region (index array, subsampled to max_points) from theta0 (K, 11), or with the
        fitter's own multistart (moment axes + EMS switches) when theta0 is None.

        One call of the batch kernel for all K regions, padded to (`batch_bucket(K)`, max_points).
        """
        K = len(regions)
        cap = self.opts.max_points
        N, Kb = bucket(cap, 32), batch_bucket(K)
        opts = FitOptions(max_steps=steps, multistart=theta0 is None)
        pts = np.zeros((Kb, N, 3))
        msk = np.zeros((Kb, N), bool)
        for i, r in enumerate(regions):
            if r.size > cap:
                r = r[np.linspace(0, r.size - 1, cap).astype(np.int64)]
            pts[i, : r.size], msk[i, : r.size] = self.host_points[r], True
        pts[K:], msk[K:] = pts[0], msk[0]          # padding rows: copies of the first problem
        th0 = None if theta0 is None else jnp.asarray(_pad_rows(theta0, Kb, theta0[0]), self.dtype)
        theta, _, _, _ = fit_padded(jnp.asarray(pts, self.dtype), jnp.asarray(msk), th0, opts)
        theta = np.asarray(theta)[:K].astype(np.float64)
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
            best = [theta, np.array(d), np.array(inside), score]   # own, writable copies
        else:
            better = score > best[3]
            for j, new in enumerate((theta, d, inside, score)):
                best[j][better] = new[better]        # in place: these are (K, P) arrays
    return best[0], best[1], best[2], best[3]


def _seed(run: _Runner, opts: SegmentOptions, seeds: list | None = None):
    """Fit the seed windows (all of the domain's, or `seeds`) and keep those consistent with the noise.

    The first call (all seeds) may raise the noise to the typical seed-fit residual."""
    first = seeds is None
    seeds = run.dom.seeds if first else seeds
    if not seeds:
        return _Models(np.zeros((0, NUM_PARAMS)), np.zeros((0, run.P), bool), np.zeros((0, run.P), np.float32),
                       np.zeros((0, run.P), bool))
    theta, d, inside, score = _fit_best(run, seeds, opts.fit_steps)
    if first and opts.adaptive_noise and opts.noise is None and opts.threshold is None:
        # Real surfaces are not exact superquadrics: take the noise as at least the typical residual
        # of the seed fits (robust: median over seeds of the median absolute distance / 0.6745).
        per_seed = [np.median(d[i, ids]) / 0.6745 for i, ids in enumerate(seeds) if np.isfinite(score[i])]
        if per_seed:
            run.set_noise(max(run.noise, float(np.median(per_seed))))
            d, inside = run.distances(theta)
    regions = np.zeros((len(seeds), run.P), bool)
    keep = np.isfinite(score)
    for i, ids in enumerate(seeds):
        inl = d[i, ids] < run.tau
        keep[i] &= inl.mean() >= opts.seed_inlier_fraction      # statistically consistent with the noise
        regions[i, ids[inl]] = True
    models = _Models(theta, regions, d, inside)
    models.take(keep)
    return models


def free_components(free, neighbours, min_size: int, max_size: int) -> list:
    """Connected sets of `free` points (P,) bool along the adjacency (P, k), as index arrays, for the
    components with `min_size` to `max_size` points (min-label propagation with pointer jumping)."""
    P = free.shape[0]
    label = np.where(free, np.arange(P), P)
    nb = np.where(neighbours >= 0, neighbours, np.arange(P)[:, None])
    ok = free[:, None] & free[nb]
    label_ext = np.append(label, P)
    while True:
        cand = np.where(ok, label_ext[nb], P).min(1)
        new = np.minimum(label, cand)
        new = np.where(free, new, P)
        new = np.where(free, np.append(new, P)[new], P)          # pointer jumping: labels are indices
        if np.array_equal(new, label):
            break
        label = new
        label_ext = np.append(label, P)
    ids = np.flatnonzero(free)
    order = np.argsort(label[ids], kind="stable")
    ids, lab = ids[order], label[ids][order]
    cuts = np.flatnonzero(np.diff(lab)) + 1
    return [c for c in np.split(ids, cuts) if min_size <= c.size <= max_size]


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
