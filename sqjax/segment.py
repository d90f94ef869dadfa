"""Recover-and-select: direct part-level segmentation with superquadrics (Leonardis, Jaklič, Solina).

`segment` interleaves model recovery (`recovery`: seeds, growth, batched refits) with model selection
(`selection`: maximise m^T Q m) until no selected model grows, then rejoins parts split by
occlusion and returns the selected models with their regions and a label image.
"""

from __future__ import annotations

import dataclasses
import time
from typing import NoReturn

import jax
import jax.numpy as jnp
import numpy as np

from .fitting import bucket, to_superquadric
from .rangeimage import RangeImage
from .recovery import (
    NUM_PARAMS,
    _Domain,
    _domain,
    _fit_best,
    _grow,
    _Models,
    _pad_rows,
    _pairs,
    _Runner,
    _seed,
    _split,
    _starts,
    free_components,
    viewing_rays,
)
from .selection import SELECTORS, SelectionWeights, build_q, select
from .superquadric import Superquadric


@dataclasses.dataclass(frozen=True)
class SegmentOptions:
    """Settings of `segment` (units are those of the data).

    - `noise`: sensor noise std; None = estimated from the data (`recovery.estimate_noise`).
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
    - `reseed`: rounds of a second chance after the final selection: seed again where no selected model
      explains the data, grow those seeds and select among old and new (parts whose hypotheses lost
      early to a neighbour's). 0 = the paper's single pass.
    - `merge`: try joining selected models whose union one superquadric explains (occlusion splits):
      `keep_fraction` of each of the two regions within tau, and (range images) the union's model
      fills no more space the camera saw through (points behind it, pixels with no return) than the
      two parts do, beyond 1 - `keep_fraction` of its points.
    - `min_exclusive`: after the final selection, a model explaining less than this share of its
      region alone (the rest is also explained by others) is dropped as redundant.
    - `subsample`: range images are segmented at every `subsample`-th row and column, then every pixel
      of the input is labelled by the final models (the paper subsampled its dense images). None =
      the step that brings the image nearest to `WORKING_PIXELS` (160 x 120, the resolution every
      default here was measured at: 640 x 480 -> 4); 1 = the slow exact path at full resolution.
    - `noise_exponent`: range images: the depth noise is sigma(z) = noise (z / z_median)^k and every
      distance is compared in units of the local sigma (2 for structured light, Khoshelham & Elberink
      2012); None = k estimated with the noise, from how the seed windows' plane residuals grow with
      their depth (`recovery.noise_exponent`); 0 (default) = one noise for the whole image. Measured
      over the benchmark (benchmarks/RESULTS.md): the estimate is confounded by surface curvature
      (0.6-1.0 on mOSD, up to 1.7 on constant-noise synthetic scenes), and k = 2 did not raise the
      mOSD score, so the default stays one noise per image.
    - `free_space`: visibility in selection (range images): a model that fills space in front of an
      observed point (the camera saw through it) pays `free_space` * K1 per such point (1 = as much as
      an explained point earns); 0 (default) = the paper's selection. Measured over the benchmark
      (benchmarks/RESULTS.md) with the distance fit, 1 lost mOSD objects (74.4% -> 61.4% correct,
      noise regions 20.4% -> 28.9%; complex 50.0% -> 37.5%) for a gain on multi-part objects
      (85.3% -> 91.2%), and took 55% longer. Visibility decides merges instead (`merge`).
    - `rings`: None = 4 per 160 pixels of working-image width and height (sqrt of the area ratio), so
      that growth per step scales with the image.
    - `subdivide`: seeds at several scales (range images): a seed window that fails (a depth
      discontinuity inside) is split into its four quadrants, recursively, down to the smallest window
      that can hold `min_seed_points` (5 x 5 for 22), so that parts smaller than a window and the
      surfaces between the depth edges of clutter get seeds. Measured over every suite
      (benchmarks/RESULTS.md, 2026-12-01): mOSD 58.6% -> 68.4% correct (objects 52.7% -> 63.3%,
      table 81% -> 88%), multi-part objects 83.8% -> 92.6%, meshes 24.7% -> 20.8% at T = 0.8 but
      32.5% -> 44.2% at T = 0.5, synthetic 100% both; noise regions rise (mOSD 22.7% -> 33.2%).
      Quadrants only in the reseed rounds (where the first pass left data unexplained) gained less and
      added as much noise. False = one window size, as in the paper.
    - `propagate`: the label image also covers the valid pixels that no final model explains within
      tau but that the surface joins to labelled ones (adjacency cut at depth discontinuities): ring
      by ring from the labelled pixels, each takes the neighbouring label whose model is nearest. The
      models describe a part's volume; the label image partitions the surface, including what a
      superquadric does not follow (the rounded rim of a box, the curved side of a bowl, mixed pixels
      at edges). Measured over every suite (benchmarks/RESULTS.md, 2026-12-02): mOSD 76.5% -> 82.1%
      correct (objects 70.4% -> 77.4%, noise regions 21.5% -> 15.3%, table 100% both), meshes 40.3%
      -> 42.9%, multi-part objects (85.3%) and synthetic scenes (97.7%) unchanged. False = label only
      the pixels a model explains (the paper).
    - `part_volumes`: each final model is refitted to its part's points with the fitter's size bound,
      from several starts, and the part keeps the candidate that best agrees with the observations
      (the part's points it explains, less the observed points and empty pixels whose viewing rays
      it blocks; among equals the smallest volume), unless the growth model agrees better by more
      than 1 - keep_fraction of the part's points (`_part_volumes`). Growth extrapolates, so without
      it a part is often a sheet metres wide or a leg whose far end lies outside the view. Labels are
      unchanged. Measured over every suite (benchmarks/RESULTS.md, 2026-12-02): median volume IoU of
      matched multi-part parts 0.47 -> 0.86 (tables 0.11 -> 0.59, chairs 0.33 -> 0.62, arms
      0.40 -> 0.97); Hoover scores of every suite unchanged. False = the growth models.
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
    rings: int | None = None
    keep_fraction: float = 0.9
    select_every: int = 3
    max_steps: int = 60
    max_points: int = 512
    fit_steps: int = 10
    weights: SelectionWeights | None = None
    selector: str = "greedy"
    merge: bool = True
    reseed: int = 2
    min_exclusive: float = 0.2
    jump_factor: float = 4.0
    subsample: int | None = None
    noise_exponent: float | None = 0.0
    free_space: float = 0.0
    subdivide: bool = True
    propagate: bool = True
    part_volumes: bool = True

    def __post_init__(self):
        def bad(name, want) -> NoReturn:
            raise ValueError(f"SegmentOptions: {name} must be {want}, got {getattr(self, name)!r}")

        def number(name, lo=None, hi=None, *, integer=False, optional=False, lo_open=False):
            v = getattr(self, name)
            if v is None and optional:
                return
            want = ("an integer" if integer else "a finite number") + (" or None" if optional else "")
            if isinstance(v, bool) or not isinstance(v, (int, np.integer) if integer else (int, float, np.number)):
                bad(name, want)
            if not np.isfinite(v):
                bad(name, want)
            if lo is not None and (v <= lo if lo_open else v < lo):
                bad(name, f"{'>' if lo_open else '>='} {lo}")
            if hi is not None and v > hi:
                bad(name, f"<= {hi}")

        for name in ("noise", "threshold"):
            number(name, 0, optional=True, lo_open=True)
        number("threshold_factor", 0, lo_open=True)
        number("min_seed_points", NUM_PARAMS + 1, integer=True)
        number("window", 1, integer=True, optional=True)
        if self.window is not None and self.window * self.window < self.min_seed_points:
            bad(
                "window",
                f"at least {int(np.ceil(np.sqrt(self.min_seed_points)))} (a seed window of "
                f"window^2 pixels must hold min_seed_points = {self.min_seed_points})",
            )
        number("stride", 1, integer=True, optional=True)
        number("seed_inlier_fraction", 0, 1, lo_open=True)
        number("enlarge", 1)
        number("admit_factor", 1)
        number("rings", 1, integer=True, optional=True)
        number("subsample", 1, integer=True, optional=True)
        number("noise_exponent", 0, 4, optional=True)
        number("free_space", 0)
        number("keep_fraction", 0, 1, lo_open=True)
        number("select_every", 1, integer=True)
        number("max_steps", 0, integer=True)
        number("max_points", self.min_seed_points, integer=True)
        number("fit_steps", 1, integer=True)
        number("reseed", 0, integer=True)
        number("min_exclusive", 0, 1)
        number("jump_factor", 0, lo_open=True)
        if self.selector not in SELECTORS:
            bad("selector", f"one of {SELECTORS}")
        if self.weights is not None and not isinstance(self.weights, SelectionWeights):
            bad("weights", "a SelectionWeights or None")
        for name in ("adaptive_noise", "merge", "subdivide", "propagate", "part_volumes"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                bad(name, "True or False")


@dataclasses.dataclass(frozen=True)
class Part:
    """One selected model.

    - `superquadric`: the model, in the data's frame and units.
    - `region`: the points labelled with it that it explains (eq. 10 distance within tau): flat pixel
      indices (images) or row indices of the input (clouds).
    - `error`: sum of squared eq. 10 distances over the region.
    - `num_points`: pixels (points) labelled with this part, always > 0. Each explained pixel goes to
      its nearest part; with `SegmentOptions.propagate`, so do unexplained pixels that the surface
      joins to the part's labelled ones, so this can exceed `num_explained`.
    - `num_explained`: `region.size`.
    """

    superquadric: Superquadric
    region: np.ndarray
    error: float
    num_points: int
    num_explained: int


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


# ----------------------------------------------------------------------------------------------------
# the data: points, adjacency (image grid or k nearest neighbours), seeds


def _select(run: _Runner, models: _Models, tau, opts, weights):
    d2 = [np.minimum(d, tau) ** 2 for d in models.dist]
    Q = build_q(models.regions, d2, np.full(len(models.theta), NUM_PARAMS), weights)
    if opts.free_space > 0:
        # visibility: every point the camera saw through the model costs what an explained one earns
        Q[np.diag_indices_from(Q)] -= opts.free_space * weights.k1 * run.free_space_violations(models.theta)
    m, stats = select(Q, opts.selector)
    return m, stats


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
    pairs = _merge_candidates(run.host_points, models.regions)
    if not pairs:
        return models
    unions = [np.flatnonzero(models.regions[i] | models.regions[j]) for i, j in pairs]
    theta, d, score = _fit_best(run, unions, opts.fit_steps, multistart=True)
    keep, regions, dist = [], [], []
    for k, ids in enumerate(unions):
        # One model for the union must explain each of the two (keep_fraction of its points within
        # tau), not only the union: over a block standing on a cylinder it explains 90% of both
        # together, at the cost of the smaller one.
        inl = d[k] < run.tau
        i, j = pairs[k]
        each = [inl[models.regions[m][ids]].mean() for m in (i, j)]
        if np.isfinite(score[k]) and min(each) >= opts.keep_fraction:
            region = np.zeros(run.P, bool)
            region[ids[inl]] = True
            keep.append(k)
            regions.append(region)
            dist.append(d[k][inl])
    if keep:
        # Visibility: the union's model must not fill space the camera saw through (points behind it,
        # or no return at all) much more than its two parts do; a box under a table, whose side face
        # holds the legs, explains both pieces but fills the free space between the legs.
        seen = lambda th: run.free_space_violations(th) + run.void_violations(th)
        extra = seen(theta[keep]) - seen(models.theta)[np.array([pairs[k] for k in keep])].sum(1)
        ok = extra <= (1.0 - opts.keep_fraction) * np.array([r.sum() for r in regions])
        keep, regions, dist = ([x for x, good in zip(a, ok) if good] for a in (keep, regions, dist))
    if not keep:
        return models
    out = models.concat(_Models(theta[keep], np.stack(regions), dist))
    out.active[:] = False
    return out


MERGE_NEIGHBOURS = 4


def _merge_candidates(points: np.ndarray, regions: np.ndarray) -> list:
    """Pairs (i, j), i < j, of models worth a union fit: every pair when there are few models, else each
    model with its `MERGE_NEIGHBOURS` nearest (gap between the regions' bounding spheres), so that the
    union fits grow linearly with the number of models, not quadratically (a scene of hundreds of
    selected pieces must not cost tens of thousands of fits). Points (P, 3), regions (M, P) bool."""
    M = len(regions)
    if M <= 2 * MERGE_NEIGHBOURS + 1:
        return [(i, j) for i in range(M) for j in range(i + 1, M)]
    centre = np.stack([points[r].mean(0) for r in regions])
    radius = np.array([np.linalg.norm(points[r] - c, axis=1).max() for r, c in zip(regions, centre)])
    gap = np.linalg.norm(centre[:, None] - centre[None], axis=-1) - radius[:, None] - radius[None]
    np.fill_diagonal(gap, np.inf)
    near = np.argsort(gap, 1, kind="stable")[:, :MERGE_NEIGHBOURS]
    return sorted({(min(i, j), max(i, j)) for i in range(M) for j in near[i]})


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
    - `progress`: optional callable `progress(step, n_active, n_models, *, stage, round)` called after
      each growth step (`stage="grow"`), before each round's merge and final selection ("merge") and
      before the labels ("finish"); `round` counts from 0 (the first pass; then each reseed round).

    **Returns:** a `Segmentation` (parts, label image, history, timings).
    """
    if options is not None and kw:
        raise TypeError(f"segment: pass options= or keyword options, not both (got {sorted(kw)})")
    opts = options if options is not None else SegmentOptions(**kw)
    t_start = time.perf_counter()
    compile_start = _COMPILE_SECONDS[0]
    full, step = None, 1
    if isinstance(data, RangeImage):
        step = opts.subsample or working_step(data.shape)
        if step > 1:
            full, data = data, data.subsample(step)
        if opts.rings is None:
            H, W = data.shape
            opts = dataclasses.replace(opts, rings=max(1, round(4 * np.sqrt(H * W / WORKING_PIXELS))))
    elif opts.rings is None:
        opts = dataclasses.replace(opts, rings=4)
    dom, noise, tau = _domain(data, opts, k)
    run = _Runner(dom, opts, noise, tau, jnp.float32)
    models = _seed(run, opts)
    noise, tau = run.noise, run.tau
    weights = opts.weights or SelectionWeights.for_threshold(tau)
    history, stats = (
        [],
        {
            "seeds": len(dom.seeds),
            "seed_models": len(models.theta),
            "selections": 0,
            "greedy_worse": 0,
            "growth_steps": 0,
            "reseeded": 0,
            "noise_exponent": dom.noise_model[0] if dom.noise_model else 0.0,
        },
    )

    def select_(models):
        m, st = _select(run, models, tau, opts, weights)
        stats["selections"] += 1
        stats["greedy_worse"] += int(st["greedy_gap"] > 1e-9)
        models.take(m)
        history.append(models.theta.copy())

    def report(stage, round_):
        if progress is not None:
            progress(stats["growth_steps"], int(models.active.sum()), len(models.theta), stage=stage, round=round_)

    def recover_and_select(models, budget, round_):
        """Growth of the active models interleaved with selection, until all stop or `budget` steps."""
        step = 0
        while models.active.any() and step < budget:
            for _ in range(opts.select_every):
                _grow(run, models, opts)
                step += 1
                stats["growth_steps"] += 1
                if progress is not None:
                    progress(
                        stats["growth_steps"], int(models.active.sum()), len(models.theta), stage="grow", round=round_
                    )
                if not models.active.any() or step >= budget:
                    break
            select_(models)

    def final_selection(models):
        """Rejoin occlusion splits, select, drop the redundant."""
        if opts.merge and len(models.theta) > 1:
            models = _merge(run, models, opts)
        if len(models.theta):
            select_(models)
            stats["pruned"] = stats.get("pruned", 0) + _prune_redundant(models, opts.min_exclusive)
        return models

    recover_and_select(models, opts.max_steps, 0)
    report("merge", 0)
    models = final_selection(models)
    for round_ in range(1, opts.reseed + 1):
        # Another chance for what the final models leave unexplained: seeds lying there grow beside
        # the (stopped) selected models and compete with them in the selections.
        free = ~models.regions.any(0)
        fresh = [ids for ids in dom.seeds if free[ids].mean() >= opts.seed_inlier_fraction]
        # and every unexplained connected piece is a seed as a whole: the strips no seed window fits
        # in (a plate's border around the box on it, windows touching an edge); a piece that no
        # superquadric explains fails the seed test
        fresh += free_components(free, dom.neighbours, opts.min_seed_points)
        new = _seed(run, opts, fresh) if fresh else None
        if new is None or not len(new.theta):
            break
        stats["reseeded"] += len(new.theta)
        models.active[:] = False
        models = models.concat(new)
        recover_and_select(models, opts.max_steps, round_)
        report("merge", round_)
        models = final_selection(models)
    report("finish", opts.reseed)
    labels = _finish(run, models)
    theta = _part_volumes(run, models, labels) if opts.part_volumes else models.theta
    if full is not None:
        labels, owns, frun = _label_full(full, step, run, models, labels)
        parts = _parts(frun, theta[owns], labels.ravel()[frun.dom.index])
    else:
        parts = _parts(run, theta, labels.ravel()[run.dom.index])
    stats["subsample"] = step
    history = [_to_world(h, run.centre) for h in history]
    total = time.perf_counter() - t_start
    compile_s = _COMPILE_SECONDS[0] - compile_start
    timings = {"total": total, "compile": compile_s, "run": total - compile_s}
    return Segmentation(parts, labels, history, noise, tau, timings, stats)


def _finish(run: _Runner, models: _Models) -> np.ndarray:
    """The label image (run's domain shape, int32; label i + 1 = model i): each explained point goes to
    its nearest model, speckles to the next nearest, and (`propagate`) the unexplained surface joined
    to labelled points to the nearest neighbouring model. `models` is left holding, largest first, only
    the models that own labels."""
    order = np.argsort(-models.regions.sum(1), kind="stable")
    models.take(order)
    flat = np.zeros(int(np.prod(run.dom.shape)), np.int32)
    if len(models.theta):
        # Each pixel goes to its nearest model. A model explains a pixel from the camera's side, or
        # with a face turned away from the camera (the underside of a block standing on another, the
        # inside of a cup): the camera's side wins, by tau.
        k, p = np.nonzero(models.regions)
        dk, _, away = run.distances(models.theta, k, p)
        d = np.full(models.regions.shape, np.inf, np.float32)
        d[k, p] = dk + np.where(away, run.tau, 0.0)
        has = np.isfinite(d.min(0))
        # Distances are compared after a local mean along the adjacency (capped at 2 tau), over a
        # radius of a tenth of a seed window: systematic differences decide, not single pixels' noise.
        ok = run.dom.neighbours >= 0
        cols = np.where(ok, run.dom.neighbours, 0)
        near = np.minimum(d, 2 * run.tau)
        for _ in range(max(1, round(np.sqrt(run.dom.seed_size) / 10))):
            near = (near + (near[:, cols] * ok).sum(2)) / (1 + ok.sum(1))
        near[~np.isfinite(d)] = np.inf
        best = np.argmin(near, 0)
        # Two almost coincident surfaces can still leave a speckle: a piece of a label smaller than a
        # seed window goes to the next nearest model that explains it (if none does, it stays).
        for i in range(len(models.theta)):
            for piece in free_components(has & (best == i), run.dom.neighbours, 1, run.dom.seed_size - 1):
                alt = near[:, piece]
                alt[i] = np.inf
                moved = np.isfinite(alt.min(0))
                near[i, piece[moved]] = np.inf
                best[piece[moved]] = np.argmin(alt[:, moved], 0)
        if run.opts.propagate:
            best, has = _propagate(run, models.theta, best, has)
        # A model whose every pixel went to a nearer one is not a part of the label image: drop it, so
        # that parts and labels agree (label i + 1 = parts[i], and every part owns labelled pixels).
        count = np.bincount(best[has], minlength=len(models.theta))
        owns, relabel = _owners(count)
        flat[run.dom.index[has]] = relabel[best[has] + 1]
        models.take(owns)
    return flat.reshape(run.dom.shape)


def _part_volumes(run: _Runner, models: _Models, labels: np.ndarray) -> np.ndarray:
    """The final models' volumes made the parts': theta (M, 11), one row per model (label i + 1).

    A growth fit's unseen extent is free (it extrapolates to admit points), so a final model may be a
    sheet metres wide explaining one face, or a leg 40 m long whose far end lies outside the view.
    Each model is refitted to its part's points (labelled with it and explained by it) with the fitter's
    size bound (`FitOptions.size_bound`), from the growth model, from each of `_starts` and from the
    fitter's multistart. A candidate's agreement with what the camera saw is the number of the part's
    points it explains (within tau) less the observations it contradicts (points behind it and pixels
    with no return whose viewing rays pass through it: `free_space_violations`, `void_violations`,
    sampled on the model's bounding-box chord so that a swollen growth model is seen; none for
    clouds). The part takes the bounded candidate that agrees best (among equals the smallest
    volume, the solid that claims least of the space nobody saw) unless the growth model agrees better
    by more than 1 - keep_fraction of the part's points. The label image is not changed.
    """
    theta = models.theta.copy()
    own = labels.ravel()[run.dom.index]
    regions = [np.flatnonzero(models.regions[i] & (own == i + 1)) for i in range(len(theta))]
    use = [i for i, r in enumerate(regions) if r.size >= run.opts.min_seed_points]
    if not use:
        return theta
    regions = [regions[i] for i in use]
    growth = theta[use]
    origin = -run.centre if run.dom.views is not None else None  # the camera, in the runner's frame
    starts = [growth, *_starts(run.host_points, regions, origin), None]
    cands = [growth] + [run.fit(regions, th0, run.opts.fit_steps, size_bound=True) for th0 in starts]
    model, point = _pairs(regions)
    score = []
    for i, th in enumerate(cands):  # one candidate at a time: each call's pairs fill its chunks
        ok = np.isfinite(th).all(1, keepdims=True)
        cands[i] = th = np.where(ok, th, growth)
        d, _, _ = run.distances(th, model, point)
        agree = (
            np.bincount(model, d < run.tau, len(use))
            - run.free_space_violations(th, box=True)
            - run.void_violations(th, box=True)
        )
        score.append(np.where(ok.ravel(), agree, -np.inf))
    score, stack = np.array(score), np.concatenate(cands)
    C, K = score.shape
    volume = np.asarray(
        _world(jnp.asarray(_pad_rows(stack, bucket(C * K, 8), stack[0]), jnp.float32), jnp.zeros(3, jnp.float32)).volume
    )[: C * K].reshape(C, K)
    # a bounded candidate whenever one agrees within 1 - keep_fraction of the part's points (the
    # tolerance by which growth accepts a step) as well as the growth model: its extent is the data's
    bounded, bvol = score[1:], volume[1:]
    best = 1 + np.argmin(np.where(bounded == bounded.max(0), bvol, np.inf), 0)
    sizes = np.array([r.size for r in regions])
    pick = np.where(bounded.max(0) >= score[0] - (1.0 - run.opts.keep_fraction) * sizes, best, 0)
    theta[use] = stack.reshape(C, K, -1)[pick, np.arange(K)]
    return theta


def _parts(run: _Runner, theta: np.ndarray, labels: np.ndarray) -> list:
    """`Part`s of the models theta (M, 11) that own labels (flat labels over run's points, 0 = none,
    i + 1 = model i; every model owns some): each part's region is its labelled points that its model
    explains (eq. 10 distance within tau)."""
    point = np.flatnonzero(labels > 0)
    point = point[np.argsort(labels[point], kind="stable")]  # grouped by model, in point order
    model = labels[point] - 1
    d, _, _ = run.distances(theta, model, point)
    inl = d < run.tau
    M = len(theta)
    count = np.bincount(model, minlength=M)
    error = np.bincount(model[inl], d[inl].astype(np.float64) ** 2, M)
    regions = _split(run.dom.index[point[inl]], model[inl], M)
    return [
        Part(sq, regions[i], float(error[i]), int(count[i]), int(regions[i].size))
        for i, sq in enumerate(_to_world(theta, run.centre))
    ]


def _propagate(run: _Runner, theta, best, has):
    """Labels for the valid points no model explains but the surface joins to labelled ones.

    Multi-source breadth-first along the adjacency (cut at depth discontinuities): ring by ring, an
    unlabelled point next to labelled ones takes, of its neighbours' labels, the one whose model is
    nearest to it. best (P,) model per point, has (P,) bool -> the same, extended."""
    best, has = best.copy(), has.copy()
    nb = run.dom.neighbours
    ok = nb >= 0
    cols = np.where(ok, nb, 0)
    while True:
        lab = np.where(ok & has[cols], best[cols], -1)  # (P, k) neighbours' labels
        front = ~has & (lab >= 0).any(1)
        if not front.any():
            return best, has
        p, j = np.nonzero(lab[front] >= 0)
        p = np.flatnonzero(front)[p]
        m = lab[p, j]
        key = np.unique(p * len(theta) + m)
        p, m = np.divmod(key, len(theta))
        d, _, _ = run.distances(theta, m, p)
        order = np.lexsort((d, p))
        p, m = p[order], m[order]
        first = np.r_[True, p[1:] != p[:-1]]
        best[p[first]], has[p[first]] = m[first], True


def _owners(count: np.ndarray):
    """Models that own labelled pixels (count (M,) of each model's pixels): their indices, and the map
    (M + 1,) from old label (0 = none, i + 1 = model i) to new label, 1..K in the same order."""
    owns = np.flatnonzero(count > 0)
    relabel = np.zeros(count.size + 1, np.int32)
    relabel[owns + 1] = np.arange(1, owns.size + 1)
    return owns, relabel


def working_step(shape) -> int:
    """The subsampling step that brings an (H, W) image nearest to `WORKING_PIXELS` (>= 1)."""
    return max(1, int(round(np.sqrt(shape[0] * shape[1] / WORKING_PIXELS))))


def _label_full(image: RangeImage, step: int, run: _Runner, models: _Models, coarse: np.ndarray):
    """Label every pixel of the full-size `image` with the final models fitted on its `step`-subsampled
    copy (whose labels are `coarse` (h, w)).

    A full-size pixel may take the label of any coarse pixel in the 3 x 3 block around it (its own
    coarse pixel and the 8 adjacent): it goes to the one whose model is nearest (eq. 10; a face turned
    away from the camera pays tau, as in `_finish`), if that model explains it (within tau); else, with
    `propagate`, the label of its own coarse pixel if that one was labelled by `_propagate`; else 0.
    Returns the (H, W) label image (label i + 1 = model owns[i]), the models that own labels, and the
    runner of the full-size points.
    """
    H, W = image.shape
    h, w = coarse.shape
    flat = np.flatnonzero(image.valid)
    P = image.points.reshape(-1, 3)[flat]
    dom = _Domain(P, np.zeros((P.shape[0], 0), np.int64), [], flat, (H, W), views=viewing_rays(image, P))
    dom.noise_model = run.dom.noise_model  # the same noise model as the working image's
    frun = _Runner(dom, run.opts, run.noise, run.tau, run.dtype, centre=run.centre)
    r, c = np.divmod(flat, W)
    r, c = np.clip(np.rint(r / step).astype(np.int64), 0, h - 1), np.clip(np.rint(c / step).astype(np.int64), 0, w - 1)
    padded = np.pad(coarse, 1)
    cand = np.stack([padded[r + 1 + dr, c + 1 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], 1)  # (Pf, 9)
    cand = np.unique(np.arange(P.shape[0], dtype=np.int64)[:, None] * (len(models.theta) + 1) + cand)
    point, label = np.divmod(cand, len(models.theta) + 1)
    point, model = point[label > 0], label[label > 0] - 1
    d, _, away = frun.distances(models.theta, model, point)
    inl = d < run.tau
    score = np.where(inl, d + np.where(away, run.tau, 0.0), np.inf)
    best = np.full(P.shape[0], np.inf)
    np.minimum.at(best, point, score)
    win = inl & (score == best[point])
    owner = np.zeros(P.shape[0], np.int32)
    owner[point[win]] = model[win] + 1  # ties: the later model (any one of them)
    if run.opts.propagate:
        # a pixel no model explains takes its coarse pixel's label where that one was propagated
        # (`_propagate`: labelled although no model explains it)
        explained = np.zeros(h * w, bool)
        explained[run.dom.index[models.regions.any(0)]] = True
        own = coarse[r, c]
        take = (owner == 0) & (own > 0) & ~explained[r * w + c]
        owner[take] = own[take]
    count = np.bincount(owner, minlength=len(models.theta) + 1)[1:]
    owns, relabel = _owners(count)
    labels = np.zeros(H * W, np.int32)
    labels[flat] = relabel[owner]
    return labels.reshape(H, W), owns, frun


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


def _on_jax_event(event, duration_secs, **_):
    if event.startswith("/jax/core/compile/"):
        _COMPILE_SECONDS[0] += duration_secs


_COMPILE_SECONDS = [0.0]
WORKING_PIXELS = 160 * 120
jax.monitoring.register_event_duration_secs_listener(_on_jax_event)
