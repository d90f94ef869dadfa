"""Seeds (the paper's section 3, step 1): windows of the range image (or neighbourhoods of a cloud)
whose fitted model is consistent with the noise start the hypotheses.

A window holding a depth discontinuity is split into quadrants, down to the smallest window that can
hold a seed (`seed_windows`, `SeedOptions.subdivide`): seeds at several scales. Where even the smallest
window does not fit, seeds grow along the surface (`surface_seeds`, `SeedOptions.surface`). Each seed is fitted from
several one-view starts at once (`fit_best`), and kept when its fit explains its window (`seed`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .domain import Domain, knn, pixel_map
from .hypotheses import Models, pairs, split_by_model
from .initial import one_view_starts
from .workspace import Workspace


def seed_windows(idmap, broken, window: int, stride: int, min_seed: int, subdivide: bool) -> tuple[list, list, int]:
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


def image_seeds(dom: Domain, window: int, stride: int, min_seed: int, subdivide: bool) -> tuple[list, int]:
    """The seed windows of a range image's domain (`seed_windows` over its pixel grid, quadrants after
    the whole windows) and the number of pixels of the smallest."""
    whole, quadrants, smallest = seed_windows(
        pixel_map(dom.index, dom.shape), dom.broken, window, stride, min_seed, subdivide
    )
    return whole + quadrants, smallest * smallest


def surface_seeds(neighbours: np.ndarray, covered: np.ndarray, size: int) -> list:
    """Seeds where no seed window fits: balls of `size` points grown along the adjacency
    (`neighbours` (P, k), -1 = none or cut) from the points no window covers (`covered` (P,) bool),
    each started at the first such point no earlier ball took. A ball follows the surface, never a
    depth discontinuity: a leg two pixels wide, or a face between the depth edges of clutter, gets
    seeds that a square window cannot give. Balls that reach fewer than `size` points are dropped."""
    taken = covered.copy()
    out = []
    for c in np.flatnonzero(~covered):
        if taken[c]:
            continue
        ball, seen, frontier = [c], {int(c)}, [int(c)]
        while frontier and len(ball) < size:
            nxt = [q for p in frontier for q in neighbours[p].tolist() if q >= 0 and q not in seen and not seen.add(q)]
            ball += nxt
            frontier = nxt
        if len(ball) >= size:
            ids = np.sort(np.array(ball[:size]))
            taken[ids] = True
            out.append(ids)
        else:
            taken[c] = True
    return out


def cloud_seeds(dom: Domain, window: int, min_seed: int) -> list:
    """Seeds of a cloud: farthest-point samples, each with its `window` nearest points (those of at
    least `min_seed` points)."""
    P = dom.points
    n_seeds = max(1, min(256, P.shape[0] // max(window, 1)))
    centres = [0]
    dmin = np.linalg.norm(P - P[0], axis=1)
    for _ in range(n_seeds - 1):
        centres.append(int(np.argmax(dmin)))
        dmin = np.minimum(dmin, np.linalg.norm(P - P[centres[-1]], axis=1))
    seeds = [ids[ids >= 0] for ids in knn(P, window, P[centres])]
    return [ids for ids in seeds if ids.size >= min_seed]


def fit_best(ws: Workspace, regions: list, multistart: bool = False):
    """Fit every region (sorted index arrays) from each start of `initial.one_view_starts` (and the fitter's
    multistart if asked); keep, per region, the start whose fit explains most of the region's points
    within tau (eq. 10). Returns theta (K, 11), the distances of each region's points (list of K
    arrays) and the score (K,), -inf where no fit succeeded."""
    best = None
    model, point = pairs(regions)
    sizes = np.array([r.size for r in regions])
    starts = list(one_view_starts(ws.host_points, regions, ws.camera)) + ([None] if multistart else [])
    for th0 in starts:
        theta = ws.fit(regions, th0)
        ok = np.isfinite(theta).all(1)
        theta = np.where(ok[:, None], theta, 0.0)  # pyright: ignore[reportIndexIssue]  (ok: an array, not np.bool)
        d, _, _ = ws.distances(theta, model, point)
        explained = np.bincount(model, d < ws.tau, len(regions)) / sizes
        rms = np.sqrt(np.bincount(model, np.minimum(d, 1e3).astype(np.float64) ** 2, len(regions)) / sizes)
        score = np.where(ok, explained - 1e-3 * rms / ws.tau, -np.inf)
        d = split_by_model(d, model, len(regions))
        if best is None:
            best = [theta, d, score]
        else:
            for i in np.flatnonzero(score > best[2]):
                best[0][i], best[1][i], best[2][i] = theta[i], d[i], score[i]
    return tuple(best)  # pyright: ignore[reportArgumentType]  (there is always a start)


def seed(ws: Workspace, seeds: list | None = None) -> tuple[Models, Workspace]:
    """Fit the seed windows (all of the domain's, or `seeds`) and keep those consistent with the noise:
    at least `seed_inlier_fraction` of the window within tau of its fit (the paper's statistical test).

    The first call (all seeds) may raise the noise to the typical seed-fit residual
    (`SensorOptions.adaptive_noise`; in units of the local noise where it grows with depth); it returns
    the workspace in that noise."""
    opts = ws.opts
    first = seeds is None
    seeds = [np.sort(ids) for ids in (ws.dom.seeds if first else seeds)]
    if not seeds:
        return Models.empty(ws.P), ws
    theta, d, score = fit_best(ws, seeds)
    sensor = opts.sensor
    if first and sensor.adaptive_noise and sensor.noise is None and sensor.threshold is None:
        # Real surfaces are not exact superquadrics: take the noise as at least the typical residual
        # of the seed fits (robust: median over seeds of the median absolute distance / 0.6745).
        fitted = np.flatnonzero(np.isfinite(score))
        sigma = np.array([np.median(d[i]) / 0.6745 for i in fitted])
        if fitted.size:
            level = max(ws.noise.sigma, float(np.median(sigma)))
            ws = ws.with_noise(dataclasses.replace(ws.noise, sigma=level, tau=sensor.threshold_factor * level))
            model, point = pairs(seeds)
            d = split_by_model(ws.distances(theta, model, point, within=ws.tau)[0], model, len(seeds))
    regions = np.zeros((len(seeds), ws.P), bool)
    keep = np.isfinite(score)
    dist = []
    for i, ids in enumerate(seeds):
        inl = d[i] < ws.tau
        keep[i] &= inl.mean() >= opts.seeds.seed_inlier_fraction  # statistically consistent with the noise
        regions[i, ids[inl]] = True
        dist.append(d[i][inl])
    models = Models(theta, regions, dist)
    models.take(keep)
    return models, ws
