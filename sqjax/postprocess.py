"""What sqjax adds after the paper's final selection: parts split by occlusion rejoined (`merge`),
redundant models dropped (`prune_redundant`), and each part given its own volume (`part_volumes`).

Host orchestration in numpy around the workspace's kernels; each step is a switch of `ExtraOptions`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .chart import volumes
from .hypotheses import Models, pairs, split_by_model
from .initial import one_view_starts
from .seeds import fit_best
from .visibility import free_space_violations, seen_through, void_violations
from .workspace import Workspace


@dataclasses.dataclass
class MergeMemory:
    """What `merge`'s rounds keep for the next round of one segmentation. Stopped models keep their
    parameters and regions exactly, so:

    - `unions`: the outcome of every pair tried (keyed by both models' parameters and regions): a
      pair's union fit and tests depend on nothing else, so a later round fits only the pairs it has
      not seen;
    - `gaps`: the point gaps `merge_candidates` measured (keyed by both regions)."""

    unions: dict = dataclasses.field(default_factory=dict)
    gaps: dict = dataclasses.field(default_factory=dict)


def merge(ws: Workspace, models: Models, memory: MergeMemory | None = None) -> Models:
    """Hypotheses for pairs of selected models that one superquadric may explain (occlusion splits).
    `memory` carries what earlier rounds measured (`MergeMemory`)."""
    memory = MergeMemory() if memory is None else memory
    tried = memory.unions
    keep_fraction = ws.opts.growth.keep_fraction
    key = [models.theta[i].tobytes() + np.packbits(models.regions[i]).tobytes() for i in range(len(models.theta))]
    one_view = ws.dom.is_image
    neighbours = None if one_view else ws.dom.neighbours
    candidates = merge_candidates(ws.host_points, models.regions, one_view, memory.gaps, neighbours)
    pairs = [p for p in candidates if (key[p[0]], key[p[1]]) not in tried]
    new = _union_hypotheses(ws, models, pairs, keep_fraction) if pairs else {}
    for p in pairs:
        tried[key[p[0]], key[p[1]]] = new.get(p)
    found = [tried[key[i], key[j]] for i, j in candidates]
    found = [f for f in found if f is not None]
    if not found:
        return models
    theta, regions, dist = zip(*found)
    out = models.concat(Models(np.stack(theta), np.stack(regions), list(dist)))
    out.active[:] = False
    return out


def _union_hypotheses(ws: Workspace, models: Models, candidates: list, keep_fraction: float) -> dict:
    """{pair: (theta, region, distances)} of the unions of the `candidates` pairs that pass the merge's tests.

    A union is judged at the volume that agrees best with what the camera saw, as a part is
    (`part_volumes`): the unbounded fit's extent behind the surface is free (a table's model may hang
    half a metre below it and pass through the rays of pixels with no return), so a union that fails
    the visibility test is refitted with the fitter's size bound, from its fit and from the moment
    ellipsoid (`initial.one_view_starts`; on every third mOSD scene its refit made 21 unions pass,
    the union fit's own 1, the thick box of the other starts 1), and is judged by the candidate that
    explains both regions and contradicts the fewest observations."""
    unions = [np.flatnonzero(models.regions[i] | models.regions[j]) for i, j in candidates]
    theta, d, score = fit_best(_without_visibility(ws), unions, multistart=True)
    d, inside = _hollow(ws, theta, unions, d)
    both = [
        k
        for k in range(len(candidates))
        if np.isfinite(score[k]) and _explains_both(models, candidates[k], unions[k], d[k] < ws.tau, keep_fraction)
    ]
    if not both:
        return {}
    # Visibility: the union's model must not fill space the camera saw through (points behind it,
    # or no return at all) much more than its two parts do; a box under a table, whose side face
    # holds the legs, explains both pieces but fills the free space between the legs.
    parts = np.unique(np.array([candidates[k] for k in both]))
    counts = _violations(ws, np.concatenate([theta[both], models.theta[parts]]))  # one batch of ray tests
    seen, own = dict(zip(both, counts[: len(both)] - inside[both])), dict(zip(parts.tolist(), counts[len(both) :]))

    def visible(k):  # at most 1 - keep_fraction of the union's explained points more than the parts
        i, j = candidates[k]
        return seen[k] <= own[i] + own[j] + (1.0 - keep_fraction) * np.sum(d[k] < ws.tau)

    failed = [k for k in both if not visible(k)]
    if failed:
        # both starts of every failed union in one call of each kernel: the fit, the distances, the rays
        regions = [unions[k] for k in failed] * 2
        starts = np.concatenate([theta[failed], one_view_starts(ws.host_points, regions[: len(failed)], ws.camera)[0]])
        th = ws.fit(regions, starts, size_bound=True)
        ok = np.flatnonzero(np.isfinite(th).all(1))
        model, point = pairs([regions[i] for i in ok])
        dist = split_by_model(_without_visibility(ws).distances(th[ok], model, point)[0], model, len(ok))
        dist, seen_inside = _hollow(ws, th[ok], [regions[i] for i in ok], dist)
        for i, dk, v in zip(ok, dist, _violations(ws, th[ok]) - seen_inside):
            k = failed[i % len(failed)]
            if v < seen[k] and _explains_both(models, candidates[k], unions[k], dk < ws.tau, keep_fraction):
                theta[k], d[k], seen[k] = th[i], dk, v
    out = {}
    for k in filter(visible, both):
        inl = d[k] < ws.tau
        region = np.zeros(ws.P, bool)
        region[unions[k][inl]] = True
        out[candidates[k]] = (theta[k], region, d[k][inl])
    return out


def _without_visibility(ws: Workspace) -> Workspace:
    """`ws` whose distances do not test visibility (`_hollow` does, for the unions)."""
    extras = dataclasses.replace(ws.opts.extras, visibility=False)
    return dataclasses.replace(ws, opts=dataclasses.replace(ws.opts, extras=extras))


def _hollow(ws: Workspace, theta, regions: list, d: list) -> tuple[list, np.ndarray]:
    """A union's distances d (one array per region, without the visibility test) judged as a hollow
    part: (distances, (K,) the explained points the camera saw through the model).

    A bowl or a cup seen from above shows its inside through its opening: the camera sees through the
    union's model (a solid cylinder) to reach the inner wall, which lies on the model's far surface,
    and visibility splits the object into its outside, its inside and its rim. A union that the camera
    sees mostly from outside (at most half of the points it explains seen through it) is taken as hollow:
    the points on its surface seen through an opening are explained, and they are not counted against
    its visibility (the caller subtracts them). One seen mostly through (a box whose bottom face would
    explain the table around an object: 95% of what it explains seen through, test0) is a solid
    explaining a surface with its back: those points get distance inf, as `Workspace.distances` gives
    them. A bowl seen from straight above, mostly inside, stays split. Measured over every suite
    (benchmarks/RESULTS.md, 2026-12-05): mOSD 87.4% -> 89.8% (cylindric 81.0% -> 88.9%), meshes
    62.3% -> 66.2%, multi-part 97.1% -> 96.3% (a chair's leg joined to the one behind it), the rest
    unchanged; also taking as hollow a union whose inside lies within the image outline of its
    outside, whatever its share, gave mOSD 89.5%."""
    explained = [r[dk < ws.tau] for r, dk in zip(regions, d)]
    model, point = pairs(explained)
    through = split_by_model(seen_through(ws, theta, model, point), model, len(regions))
    out, inside = [], np.zeros(len(regions), np.int64)
    for k, (dk, t) in enumerate(zip(d, through)):
        if t.sum() > 0.5 * t.size:
            dk = dk.copy()
            dk[np.flatnonzero(dk < ws.tau)[t]] = np.inf
        else:
            inside[k] = t.sum()
        out.append(dk)
    return out, inside


def _explains_both(models: Models, pair, union: np.ndarray, inl: np.ndarray, keep_fraction: float) -> bool:
    """Whether one model for the union (inl: which points of `union` it explains) explains each of the
    two regions (keep_fraction of its points), not only the union: over a block standing on a cylinder
    it explains 90% of both together, at the cost of the smaller one."""
    return min(inl[models.regions[m][union]].mean() for m in pair) >= keep_fraction


def _violations(ws: Workspace, theta: np.ndarray, box: bool = False) -> np.ndarray:
    """(M,) observations the models theta (M, 11) contradict: points behind them and pixels with no
    return whose rays pass through them (`box`: sampled on the bounding box's chord, see
    `visibility.free_space_violations`)."""
    return free_space_violations(ws, theta, box=box) + void_violations(ws, theta, box=box)


MERGE_NEIGHBOURS = 4
"""The nearest models each model is paired with, in each of `merge_candidates`' lists. The point-gap
list measured with 2, 4 and 6 (benchmarks/RESULTS.md, 2026-12-06 late evening): mOSD 261, 262, 261."""


def merge_candidates(
    points: np.ndarray,
    regions: np.ndarray,
    one_view: bool = True,
    known: dict | None = None,
    neighbours: np.ndarray | None = None,
) -> list:
    """Pairs (i, j), i < j, of models worth a union fit: every pair when there are few models, else each
    model with its `MERGE_NEIGHBOURS` nearest by the gaps below, so that the union fits grow linearly
    with the number of models, not quadratically (a scene of hundreds of selected pieces must not cost
    tens of thousands of fits). Points (P, 3), regions (M, P) bool.

    - The gap between the regions' bounding spheres: a large model's sphere holds the pieces near it
      (the table's pieces, and every object on it).
    - With `one_view` (a range image), also the gap between the regions' points (the distance of their
      closest pair): seen from one viewpoint, an occluder splits an object into pieces that do not
      touch, and the spheres of large models crowded them out of the first list (mOSD's complex
      scenes). The sphere gap is a lower bound of the point gap, so the point gaps are computed in
      order of sphere gap until it exceeds the `MERGE_NEIGHBOURS`-th found. A cloud (no viewpoint)
      keeps the first list: there the nearest pieces by their points are the touching parts of one
      object (a chair's seat and back), and their unions cost Bobkov's rooms 27 -> 23 parts.
    - A cloud with its adjacency `neighbours` (P, k): of that list only the pairs whose regions touch
      (`touching`). Without a camera nothing tells a gap an occluder made from empty space, and a
      part is one connected surface: one slab explained the backs of two chairs 17 cm apart in
      Bobkov's room2 (their union kept, one region). Measured (benchmarks/RESULTS.md, 2026-12-07
      morning): clouds 123 / 134 -> 131 / 140 of 161 parts (unperturbed / `--perturb 1e-5`),
      room2 12 -> 13 of 48 and thinned to 1/2 and 1/4 7 -> 15 and 3 -> 6, room1 15 of 44 either
      way; mOSD views as clouds leave more objects in their occluded pieces (over-segmented 6 -> 12)
      but find 74 of 93 against 72.

    `known` (filled in) holds the point gaps measured so far, keyed by both regions: a merge round
    measures only the pairs with a region the previous rounds did not have.

    Over the whole benchmark (benchmarks/RESULTS.md, 2026-12-06 late evening), against the sphere
    gap alone: mOSD 260 -> 262 of 285 objects, every other image suite the same; the point gap
    alone, mOSD 259 (a complex scene's table left in pieces)."""
    M = len(regions)
    touch = touching(regions, neighbours) if neighbours is not None and not one_view else None
    if M <= 2 * MERGE_NEIGHBOURS + 1:
        return [(i, j) for i in range(M) for j in range(i + 1, M) if touch is None or (i, j) in touch]
    members = [points[r] for r in regions]
    centre = np.stack([q.mean(0) for q in members])
    radius = np.array([np.linalg.norm(q - c, axis=1).max() for q, c in zip(members, centre)])
    sphere = np.linalg.norm(centre[:, None] - centre[None], axis=-1) - radius[:, None] - radius[None]
    np.fill_diagonal(sphere, np.inf)
    order = np.argsort(sphere, 1, kind="stable")[:, : M - 1]
    out = {(min(i, int(j)), max(i, int(j))) for i in range(M) for j in order[i, :MERGE_NEIGHBOURS]}
    if not one_view:
        return sorted(out if touch is None else out & touch)

    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stub)

    trees: dict = {}
    known = {} if known is None else known
    key = [np.packbits(r).tobytes() for r in regions]

    def gap(i, j):
        pair = (key[i], key[j]) if key[i] <= key[j] else (key[j], key[i])
        if pair not in known:
            a, b = (i, j) if len(members[i]) >= len(members[j]) else (j, i)  # the smaller set queries
            if a not in trees:
                trees[a] = cKDTree(members[a])
            known[pair] = float(trees[a].query(members[b], 1)[0].min())
        return known[pair]

    for i in range(M):
        near: list = []  # (point gap, j): the MERGE_NEIGHBOURS nearest so far
        for j in order[i]:
            if len(near) == MERGE_NEIGHBOURS and sphere[i, j] > near[-1][0]:
                break
            near = sorted(near + [(gap(i, int(j)), int(j))])[:MERGE_NEIGHBOURS]
        out |= {(min(i, j), max(i, j)) for _, j in near}
    return sorted(out)


def touching(regions: np.ndarray, neighbours: np.ndarray) -> set:
    """Pairs (i, j), i < j, of regions (M, P) bool that share a point or are joined by an edge of the
    adjacency `neighbours` (P, k) (-1: none)."""
    from scipy import sparse

    M, P = regions.shape
    rows, cols = np.nonzero(neighbours >= 0)
    A = sparse.csr_matrix((np.ones(rows.size), (rows, neighbours[rows, cols])), shape=(P, P))
    A = A + A.T + sparse.identity(P, format="csr")
    m, p = np.nonzero(regions)
    R = sparse.csr_matrix((np.ones(m.size), (m, p)), shape=(M, P))
    T = (R @ A @ R.T).toarray() > 0
    i, j = np.nonzero(np.triu(T, 1))
    return set(zip(i.tolist(), j.tolist()))


def prune_redundant(models: Models, min_exclusive: float, min_points: int = 0) -> int:
    """Drop, one at a time, the selected model that explains the smallest share of points no other
    selected model explains, while that share is below `min_exclusive` or that number of points is
    below `min_points`. Returns how many went.

    Eq. 2 prices a model at K3 N_i points, so a model that duplicates another except for a few dozen
    points can still be selected; such a model is not a part of its own. Nor is one whose own points
    are too few to determine its parameters (`min_points`: the seeds' `min_seed_points`, 2 per
    parameter).
    """
    dropped = 0
    while len(models.theta) > 1:
        B = models.regions
        cover = B.sum(0)
        own = (B & (cover == 1)[None]).sum(1)
        excl = own / np.maximum(B.sum(1), 1)
        i = int(np.argmin(np.where(own < min_points, -1.0, excl)))
        if excl[i] >= min_exclusive and own[i] >= min_points:
            break
        models.take(np.arange(len(models.theta)) != i)
        dropped += 1
    return dropped


def part_volumes(ws: Workspace, models: Models, labels: np.ndarray) -> np.ndarray:
    """The final models' volumes made the parts': theta (M, 11), one row per model (label i + 1).

    A growth fit's unseen extent is free (it extrapolates to admit points), so a final model may be a
    sheet metres wide explaining one face, or a leg 40 m long whose far end lies outside the view.
    Each model is refitted to its part's points (labelled with it and explained by it) with the fitter's
    size bound (`FitOptions.size_bound`), from the growth model, from each of `initial.one_view_starts` and from the
    fitter's multistart. A candidate's agreement with what the camera saw is the number of the part's
    points it explains (within tau) less the observations it contradicts (points behind it and pixels
    with no return whose viewing rays pass through it: `visibility.free_space_violations`, `visibility.void_violations`,
    sampled on the model's bounding-box chord so that a swollen growth model is seen; none for
    clouds). The part takes the bounded candidate that agrees best (among equals the smallest
    volume, the solid that claims least of the space nobody saw) unless the growth model agrees better
    by more than 1 - keep_fraction of the part's points. The label image is not changed.
    """
    theta = models.theta.copy()
    own = labels.ravel()[ws.dom.index]
    regions = [np.flatnonzero(models.regions[i] & (own == i + 1)) for i in range(len(theta))]
    use = [i for i, r in enumerate(regions) if r.size >= ws.opts.seeds.min_seed_points]
    if not use:
        return theta
    regions = [regions[i] for i in use]
    growth = theta[use]
    starts = [growth, *one_view_starts(ws.host_points, regions, ws.camera), None]
    cands = [growth] + [ws.fit(regions, th0, size_bound=True) for th0 in starts]
    model, point = pairs(regions)
    score = []
    for i, th in enumerate(cands):  # one candidate at a time: each call's pairs fill its chunks
        ok = np.isfinite(th).all(1, keepdims=True)
        cands[i] = th = np.where(ok, th, growth)
        d, _, _ = ws.distances(th, model, point)
        agree = np.bincount(model, d < ws.tau, len(use)) - _violations(ws, th, box=True)
        score.append(np.where(ok.ravel(), agree, -np.inf))
    score, stack = np.array(score), np.concatenate(cands)
    C, K = score.shape
    volume = volumes(stack).reshape(C, K)
    # a bounded candidate whenever one agrees within 1 - keep_fraction of the part's points (the
    # tolerance by which growth accepts a step) as well as the growth model: its extent is the data's
    bounded, bvol = score[1:], volume[1:]
    best = 1 + np.argmin(np.where(bounded == bounded.max(0), bvol, np.inf), 0)
    sizes = np.array([r.size for r in regions])
    pick = np.where(bounded.max(0) >= score[0] - (1.0 - ws.opts.growth.keep_fraction) * sizes, best, 0)
    theta[use] = stack.reshape(C, K, -1)[pick, np.arange(K)]
    return theta
