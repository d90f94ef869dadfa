"""Recover-and-select: direct part-level segmentation with superquadrics (Leonardis, Jaklič, Solina).

`segment` interleaves model recovery (`seeds`, `growth`: every hypothesis grows and is refitted, all
in one batch per step) with model selection (`selection`: maximise m^T Q m) until no selected model
grows; then rejoins parts split by occlusion and seeds again where the data is left unexplained
(`postprocess`), and returns the selected models with their regions and a label image (`labelling`).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from .chart import NUM_PARAMS, to_world
from .domain import (
    Domain,
    bulk,
    cloud_domain,
    cloud_noise,
    depth_noise_exponent,
    estimate_noise,
    free_components,
    image_domain,
    knn,
)
from .growth import grow
from .hypotheses import Models
from .labelling import Part, label_cloud, label_full, label_image, parts
from .options import SegmentOptions
from .postprocess import MergeMemory, merge, part_volumes, prune_redundant
from .rangeimage import RangeImage
from .seeds import cloud_seeds, image_seeds, seed, surface_seeds
from .selection import SelectionWeights, build_q, select
from .timing import Clock
from .visibility import free_space_violations
from .workspace import Noise, Workspace

WORKING_PIXELS = 160 * 120
"""Range images are segmented at about this many pixels (`ExtraOptions.subsample`)."""
WORKING_VALID = 13_100
"""A range image is segmented at a finer step than its frame's (`working_step`) while its working image
keeps at most this many valid pixels: about the most that the 59 mOSD frames hold at 160 x 120 (10,035
to 13,104), on which the time per scene was measured (benchmarks/segment.py, median about 2 s)."""
WORKING_POINTS = 4 * WORKING_PIXELS
"""Point clouds are segmented on about this many of their points (`ExtraOptions.subsample`).

Four working images' worth: a cloud is often a whole room. Measured on Bobkov's office rooms (parts
correct at T = 0.8 against the fine labels, 2026-12-03): every point 13/48 (room2, 123,692 points,
40 s) and 12/44 (room1, 237,907 points, 96 s); one in 2 and one in 3 (this budget) 13/48 in 29 s and
12/44 in 39 s; about 19,200 points (one image's worth) 9/48 and 8/44."""

MERGE_ROUNDS = 8
"""At most this many merge-and-select rounds per final selection (each joins pairs: 2^8 pieces)."""

__all__ = ["Part", "Segmentation", "SegmentOptions", "segment", "working_step", "workspace"]


@dataclasses.dataclass
class Segmentation:
    """What `segment` returns.

    - `parts`: the selected models (`labelling.Part`), largest first.
    - `labels`: (H, W) int32 for range images ((P,) for clouds): 0 = none, i + 1 = `parts[i]`.
    - `history`: after each selection, the list of selected `Superquadric`s (the paper's panels d–f).
    - `noise`, `threshold`: the values used; `timings`: seconds (`total`, `compile`, `run`), and counts.
    - `stats`: counts of the run; for a cloud whose noise was estimated, `noise_free` (`noise_free`).
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
            "parts": [
                {
                    **p.superquadric.to_dict(),
                    "num_points": int(p.num_points),
                    "num_explained": int(p.num_explained),
                    "error": float(p.error),
                }
                for p in self.parts
            ],
            "noise": float(self.noise),
            "threshold": float(self.threshold),
            "timings": self.timings,
            "stats": self.stats,
        }


NOISE_FREE = 1e-4
"""Estimated noise over a cloud's extent below which it counts as noise-free (`noise_free`): the shared
sensor clouds measure 1.3e-3 (laser-scanned rooms) to 3e-2, dense surface samples of CAD meshes 0 to
4e-6 (the float32 fits' own residual); sparse ones get the residual of their edges."""


def noise_free(points, noise: float) -> bool:
    """Whether finite points (n, 3) look noise-free: their estimated `noise` is below `NOISE_FREE` of their
    extent (surface samples of a mesh). Then every rounded edge a superquadric leaves can become a part,
    and the tolerance should be given (`noise=`, about 0.004 x a part's size for a sampled cube or cylinder).
    The extent is that of their `domain.bulk`: one row at 1e30 made a Kinect-noisy cloud look noise-free."""
    if not len(points):
        return False
    extent = float(np.max(np.ptp(points[bulk(points)], 0)))
    return extent > 0.0 and noise < NOISE_FREE * extent


def working_step(shape, valid: np.ndarray | None = None) -> int:
    """The subsampling step of an (H, W) image (>= 1): the step that brings the frame nearest to
    `WORKING_PIXELS`, or a smaller one while the working image's valid pixels (`valid` (H, W) bool;
    None = all) stay within `WORKING_VALID`.

    Segmentation's time grows with the valid pixels, not the frame. A step from the frame's size alone
    subsamples an object that fills an eighth of a 320 x 240 render like a full frame: multi-part objects
    at 320 x 240 (21 seeded scenes, 70 parts) were 84% correct at step 2 and 94% at step 1, rendered
    meshes likewise (benchmarks/RESULTS.md, 2026-12-06 evening). A Kinect frame of a table top (52-68%
    valid at 640 x 480) keeps step 4."""
    H, W = shape[:2]
    step = max(1, int(round(np.sqrt(H * W / WORKING_PIXELS))))
    if valid is None:
        return step
    valid = np.asarray(valid, bool)
    return next((s for s in range(1, step) if valid[::s, ::s].sum() <= WORKING_VALID), step)


def _cloud(data) -> np.ndarray:
    if isinstance(data, (str, os.PathLike)):
        raise ValueError(
            f"segment: expected a RangeImage or an (P, 3) array, got the path {str(data)!r}: read it first"
            " (sqjax.read_range_image, sqjax.read_points)"
        )
    try:
        if np.iscomplexobj(data):
            raise TypeError("complex numbers")
        pts = np.asarray(data, np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"segment: expected a RangeImage or an (P, 3) array of numbers, got a {type(data).__name__} that is"
            f" not one ({err})"
        ) from None
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"segment: expected a RangeImage or an (P, 3) array, got shape {pts.shape}")
    return pts


def _cloud_window(opts: SegmentOptions) -> int:
    """Points in a cloud's seed window."""
    return opts.seeds.window or max(opts.seeds.min_seed_points, 48)


def distinct_rows(cloud: np.ndarray) -> np.ndarray:
    """Indices of the finite rows of a cloud (n_rows, 3) that repeat no earlier row, ascending.

    A repeated point carries no more of the surface, and k nearest neighbours among copies of one
    point join nothing: a cloud of 50 points written 40 times each became 25 parts of zero size."""
    valid = np.flatnonzero(np.isfinite(cloud).all(1))
    order = valid[np.lexsort(cloud[valid].T)]  # stable: the first of equal rows leads
    rows = cloud[order]
    new = np.ones(order.size, bool)
    new[1:] = np.any(rows[1:] != rows[:-1], axis=1)
    return np.sort(order[new])


def working_subset(cloud: np.ndarray, distinct: np.ndarray, step: int | None = None) -> tuple[np.ndarray, int]:
    """The (n_rows, 3) cloud with all but one in `step` of its `distinct` rows (`distinct_rows`) made
    NaN (a fixed random choice, so that no order of the rows aliases with the step; the rows keep their
    places), the other rows NaN too, and the step. `step` None: the one that brings the distinct rows
    nearest to `WORKING_POINTS`. The cloud itself when nothing is dropped."""
    step = step or max(1, int(round(distinct.size / WORKING_POINTS)))
    if step == 1 and distinct.size == np.isfinite(cloud).all(1).sum():
        return cloud, 1
    keep = np.random.default_rng(0).permutation(distinct)[: -(-distinct.size // step)]
    work = np.full_like(cloud, np.nan)
    work[keep] = cloud[keep]
    return work, step


def _prepare(data, opts: SegmentOptions, k: int, cloud_sigma: float | None = None) -> tuple[Domain, Noise]:
    """The domain of `data` with its seed windows, and the noise (from the options or the data)."""
    sensor, seeds = opts.sensor, opts.seeds
    if isinstance(data, RangeImage):
        valid = data.valid
        if not valid.any():
            raise ValueError("segment: the range image has no valid pixel (all depths are NaN, 0 or inf)")
        if valid.sum() < seeds.min_seed_points:
            raise ValueError(
                f"segment: the range image has {int(valid.sum())} valid pixels; at least "
                f"{seeds.min_seed_points} are needed for one seed"
            )
        sigma = sensor.noise if sensor.noise is not None else estimate_noise(data)
        H, W = data.shape
        window = seeds.window or int(np.clip(round(min(H, W) / 12), 4, 32))
        window = min(window, H, W)
        stride = seeds.stride or max(window // 2, 1)
        dom = image_domain(data, sensor.jump_factor, sigma)
        windows, seed_size = image_seeds(dom, window, stride, seeds.min_seed_points, seeds.subdivide)
        dom = dataclasses.replace(dom, seeds=windows, seed_size=seed_size)
        noise = Noise(sigma, sensor.threshold if sensor.threshold is not None else sensor.threshold_factor * sigma)
        exponent = depth_noise_exponent(data) if sensor.noise_exponent is None else sensor.noise_exponent
        if exponent:
            noise = dataclasses.replace(noise, exponent=exponent, z_ref=float(np.median(np.abs(dom.points[:, 2]))))
        return dom, noise
    pts = _cloud(data)
    rows = np.flatnonzero(np.isfinite(pts).all(1))
    n_rows, pts = pts.shape[0], pts[rows]
    if pts.shape[0] < seeds.min_seed_points:
        raise ValueError(f"segment: {pts.shape[0]} valid points; at least {seeds.min_seed_points} are needed")
    nb = knn(pts, k)
    window = _cloud_window(opts)
    given = sensor.noise if sensor.noise is not None else cloud_sigma  # the options', else the full cloud's
    sigma = given if given is not None else max(cloud_noise(pts, window), 1e-12)
    dom = cloud_domain(pts, rows, n_rows, nb)
    dom = dataclasses.replace(dom, seeds=cloud_seeds(dom, window, seeds.min_seed_points), seed_size=window)
    return dom, Noise(sigma, sensor.threshold if sensor.threshold is not None else sensor.threshold_factor * sigma)


def workspace(
    data, options: SegmentOptions | None = None, *, k: int = 8, cloud_sigma: float | None = None
) -> Workspace:
    """The workspace `segment` starts from, for the (working-resolution) range image or (P, 3) cloud
    `data`: its domain with the seed windows, the noise from the options or the data (before the seeds
    adapt it), the points on the device, and the options with `rings` resolved (4 per 160 pixels of
    width and height; clouds 4). For notebooks and tests that call the kernels themselves."""
    opts = options if options is not None else SegmentOptions()
    if opts.growth.rings is None:
        size = data.shape[0] * data.shape[1] if isinstance(data, RangeImage) else WORKING_PIXELS
        opts = opts.replace(rings=max(1, round(4 * np.sqrt(size / WORKING_PIXELS))))
    dom, noise = _prepare(data, opts, k, cloud_sigma)
    return Workspace.create(dom, opts, noise)


def _select(ws: Workspace, models: Models, weights: SelectionWeights):
    """Maximise m^T Q m over the hypotheses (eqs. 1-4), errors capped at tau; the presence vector."""
    opts = ws.opts.selection
    d2 = [np.minimum(d, ws.tau) ** 2 for d in models.dist]
    Q = build_q(models.regions, d2, np.full(len(models.theta), NUM_PARAMS), weights)
    if opts.free_space > 0:
        # visibility: every point the camera saw through the model costs what an explained one earns
        Q[np.diag_indices_from(Q)] -= opts.free_space * weights.k1 * free_space_violations(ws, models.theta)
    return select(Q, opts.selector)


def segment(data, *, options: SegmentOptions | None = None, k: int = 8, progress=None, **kw) -> Segmentation:
    """Part-level segmentation of a range image (or an (P, 3) point cloud) by recover-and-select.

    **Arguments:**

    - `data`: a `RangeImage` (pixels adjacent on the image grid) or an `(P, 3)` array of points
      (adjacency = `k` nearest neighbours); NaN rows / missing pixels are ignored.
    - `options`: a `SegmentOptions`; keyword arguments (flat names: `noise=`, `window=`, ...) build one.
    - `progress`: optional callable `progress(step, n_active, n_models, *, stage, round)` called after
      each growth step (`stage="grow"`), before each round's merge and final selection ("merge") and
      before the labels ("finish"); `round` counts from 0 (the first pass; then each reseed round).

    **Returns:** a `Segmentation` (parts, label image, history, timings).
    """
    if options is not None and kw:
        raise TypeError(f"segment: pass options= or keyword options, not both (got {sorted(kw)})")
    opts = options if options is not None else SegmentOptions.create(**kw)
    clock = Clock()
    full, step, cloud_sigma = None, 1, None
    if isinstance(data, RangeImage):
        step = opts.extras.subsample or working_step(data.shape, data.valid)
        if step > 1:
            full, data = data, data.subsample(step)
    else:
        cloud = _cloud(data)
        distinct = distinct_rows(cloud)
        if distinct.size < opts.seeds.min_seed_points:  # one check for too few points and for copies
            valid, n = int(np.isfinite(cloud).all(1).sum()), distinct.size
            copies = f", but {n} distinct position{'' if n == 1 else 's'}" if n < valid else ""
            need = opts.seeds.min_seed_points
            raise ValueError(f"segment: {valid} valid points{copies}; at least {need} distinct points are needed")
        data, step = working_subset(cloud, distinct, opts.extras.subsample)
        if data is not cloud:  # every input row is labelled by the final models
            full = cloud
            if step > 1 and opts.sensor.noise is None:  # the sensor's noise, measured at its own density
                cloud_sigma = max(cloud_noise(cloud[distinct], _cloud_window(opts)), 1e-12)
    ws = workspace(data, opts, k=k, cloud_sigma=cloud_sigma)
    opts, dom = ws.opts, ws.dom
    models, ws = seed(ws)
    weights = opts.selection.weights or SelectionWeights.for_threshold(ws.tau)
    history, merged, reseeded = [], MergeMemory(), set()
    stats = {
        "seeds": len(dom.seeds),
        "seed_models": len(models.theta),
        "selections": 0,
        "greedy_worse": 0,
        "growth_steps": 0,
        "reseeded": 0,
        "noise_exponent": ws.noise.exponent,
    }

    def select_(models):
        m, st = _select(ws, models, weights)
        stats["selections"] += 1
        stats["greedy_worse"] += int(st["greedy_gap"] > 1e-9)
        models.take(m)
        history.append(models.theta.copy())
        return m

    def report(stage, round_):
        if progress is not None:
            progress(stats["growth_steps"], int(models.active.sum()), len(models.theta), stage=stage, round=round_)

    def recover_and_select(models, budget, round_):
        """Growth of the active models interleaved with selection, until all stop or `budget` steps."""
        step = 0
        while models.active.any() and step < budget:
            for _ in range(opts.selection.select_every):
                grow(ws, models)
                step += 1
                stats["growth_steps"] += 1
                if progress is not None:
                    progress(
                        stats["growth_steps"], int(models.active.sum()), len(models.theta), stage="grow", round=round_
                    )
                if not models.active.any() or step >= budget:
                    break
            select_(models)

    def final_selection(models, round_):
        """Rejoin occlusion splits, select, drop the redundant. While the selection keeps unions, they
        grow as hypotheses of their own (a union explains only its two regions; the part may go on
        past them) and merging repeats: a part found as n pieces (a sphere's caps) needs about
        log2(n) pairwise rounds."""
        selected = False
        for _ in range(MERGE_ROUNDS if opts.extras.merge else 0):
            n = len(models.theta)
            if n < 2:
                break
            models = merge(ws, models, merged)
            if len(models.theta) == n:
                break
            selected = True
            kept = np.flatnonzero(select_(models))
            if not (kept >= n).any():
                break
            models.active[:] = kept >= n
            recover_and_select(models, opts.growth.max_steps, round_)
        if len(models.theta):
            if not selected:
                select_(models)
            stats["pruned"] = stats.get("pruned", 0) + prune_redundant(
                models, opts.extras.min_exclusive, opts.seeds.min_seed_points
            )
        return models

    recover_and_select(models, opts.growth.max_steps, 0)
    report("merge", 0)
    models = final_selection(models, 0)
    windowed = np.zeros(ws.P, bool)  # the points some seed window covers
    windowed[np.concatenate(dom.seeds) if dom.seeds else []] = True
    for round_ in range(1, opts.extras.reseed + 1):
        # Another chance for what the final models leave unexplained: seeds lying there grow beside
        # the (stopped) selected models and compete with them in the selections.
        free = ~models.regions.any(0)
        fresh = [ids for ids in dom.seeds if free[ids].mean() >= opts.seeds.seed_inlier_fraction]
        # and every unexplained connected piece is a seed as a whole: the strips no seed window fits
        # in (a plate's border around the box on it, windows touching an edge); a piece that no
        # superquadric explains fails the seed test
        fresh += free_components(free, dom.neighbours, opts.seeds.min_seed_points)
        if opts.seeds.surface and dom.is_image:
            # and where no window fits (a leg two pixels wide), seeds that follow the surface
            fresh += surface_seeds(dom.neighbours, windowed | ~free, opts.seeds.min_seed_points)
        # a seed that had its chance in an earlier round and left the same data unexplained would
        # only grow again as it did: not tried twice
        fresh = [ids for ids in fresh if (key := np.sort(ids).tobytes()) not in reseeded and not reseeded.add(key)]
        new = seed(ws, fresh)[0] if fresh else None
        if new is None or not len(new.theta):
            break
        stats["reseeded"] += len(new.theta)
        models.active[:] = False
        models = models.concat(new)
        recover_and_select(models, opts.growth.max_steps, round_)
        report("merge", round_)
        models = final_selection(models, round_)
    report("finish", opts.extras.reseed)
    labels = label_image(ws, models)
    theta = part_volumes(ws, models, labels) if opts.extras.part_volumes else models.theta
    if isinstance(full, RangeImage):
        labels, owns, fws = label_full(full, step, ws, models, labels)
        found = parts(fws, theta[owns], labels.ravel()[fws.dom.index])
    elif full is not None:
        labels, owns, fws = label_cloud(full, ws, models, labels)
        found = parts(fws, theta[owns], labels[fws.dom.index])
    else:
        found = parts(ws, theta, labels.ravel()[ws.dom.index])
    stats["subsample"] = step
    if not isinstance(data, RangeImage) and opts.sensor.noise is None:
        stats["noise_free"] = noise_free(ws.dom.points, ws.noise.sigma)  # the working points: valid already
    history = [to_world(h, ws.centre).unbatch() if len(h) else [] for h in history]
    return Segmentation(found, labels, history, ws.noise.sigma, ws.tau, clock.timings(), stats)
