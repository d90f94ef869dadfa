"""The label image (the paper's output: pixel -> model or none) and the parts it names.

Each explained pixel goes to its nearest final model (`label_image`), and an island of a label that
another part encloses and explains goes to that part; with `ExtraOptions.propagate` the surface the
models leave unexplained is labelled too (`propagate`). An image segmented at a working resolution is
labelled at its own by the final models (`label_full`), and a cloud segmented on a working subset of
its points is labelled in full likewise (`label_cloud`). Every part owns labelled pixels: label i + 1
is `parts[i]`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .chart import to_world
from .domain import Domain, free_components, image_adjacency, viewing_rays
from .hypotheses import Models, mask_pairs, split_by_model
from .rangeimage import RangeImage
from .superquadric import Superquadric
from .workspace import Workspace


@dataclasses.dataclass(frozen=True)
class Part:
    """One selected model.

    - `superquadric`: the model, in the data's frame and units.
    - `region`: the points labelled with it that it explains (eq. 10 distance within tau): flat pixel
      indices (images) or row indices of the input (clouds).
    - `error`: sum of squared eq. 10 distances over the region.
    - `num_points`: pixels (points) labelled with this part, always > 0. Each explained pixel goes to
      its nearest part; with `ExtraOptions.propagate`, so do unexplained pixels that the surface
      joins to the part's labelled ones, so this can exceed `num_explained`.
    - `num_explained`: `region.size`.
    """

    superquadric: Superquadric
    region: np.ndarray
    error: float
    num_points: int
    num_explained: int


def label_image(ws: Workspace, models: Models) -> np.ndarray:
    """The label image (the workspace domain's shape, int32; label i + 1 = model i): each explained point goes to
    its nearest model, speckles to the next nearest, and (`ExtraOptions.propagate`) the unexplained surface joined
    to labelled points to the nearest neighbouring model. `models` is left holding, largest first, only
    the models that own labels."""
    order = np.argsort(-models.regions.sum(1), kind="stable")
    models.take(order)
    flat = np.zeros(int(np.prod(ws.dom.shape)), np.int32)
    if len(models.theta):
        # Each pixel goes to its nearest model. A model explains a pixel from the camera's side, or
        # with a face turned away from the camera (the underside of a block standing on another, the
        # inside of a cup): the camera's side wins, by tau.
        k, p = mask_pairs(models.regions)
        dk, _, away = ws.distances(models.theta, k, p)
        d = np.full(models.regions.shape, np.inf, np.float32)
        d[k, p] = dk + np.where(away, ws.tau, 0.0)
        has = np.isfinite(d.min(0))
        # Distances are compared after a local mean along the adjacency (capped at 2 tau), over a
        # radius of a tenth of a seed window: systematic differences decide, not single pixels' noise.
        ok = ws.dom.neighbours >= 0
        cols = np.where(ok, ws.dom.neighbours, 0)
        near = np.minimum(d, 2 * ws.tau)
        for _ in range(max(1, round(np.sqrt(ws.dom.seed_size) / 10))):
            near = (near + (near[:, cols] * ok).sum(2)) / (1 + ok.sum(1))
        near[~np.isfinite(d)] = np.inf
        best = np.argmin(near, 0)
        # Two almost coincident surfaces can still leave a speckle: a piece of a label smaller than a
        # seed window goes to the next nearest model that explains it (if none does, it stays).
        for i in range(len(models.theta)):
            for piece in free_components(has & (best == i), ws.dom.neighbours, 1, ws.dom.seed_size - 1):
                alt = near[:, piece]
                alt[i] = np.inf
                moved = np.isfinite(alt.min(0))
                near[i, piece[moved]] = np.inf
                best[piece[moved]] = np.argmin(alt[:, moved], 0)
        _join_islands(ws, best, has, near)
        if ws.opts.extras.propagate:
            best, has = propagate(ws, models.theta, best, has)
        # A model whose every pixel went to a nearer one is not a part of the label image: drop it, so
        # that parts and labels agree (label i + 1 = parts[i], and every part owns labelled pixels).
        count = np.bincount(best[has], minlength=len(models.theta))
        owns, relabel = owners(count)
        flat[ws.dom.index[has]] = relabel[best[has] + 1]
        models.take(owns)
    return flat.reshape(ws.dom.shape)


def _join_islands(ws: Workspace, best: np.ndarray, has: np.ndarray, near: np.ndarray) -> None:
    """Give each island of a label to the part around it, in place (best (P,) model per point, has
    (P,) bool, near (M, P) the smoothed distances, inf where a model does not explain a point).

    Growth makes every region connected, but nearest-model labels need not be: where two selected
    models nearly coincide (a lid's model continuing the body's surface) the nearer one alternates in
    blobs. A piece of model i's label other than its largest, enclosed by the label of one model j
    (every neighbour outside the piece is labelled j: no depth discontinuity, image border or
    unlabelled point on its rim) and explained by j over most of it (more than half its points within
    tau), lies on j's part: it goes to j. Where j's model departs from the part's real surface (a
    teapot's body is no superquadric) the blob is where i's model happens to be nearer, and j misses
    some of it. Measured (benchmarks/RESULTS.md, 2026-12-06 evening) against "explained by j
    everywhere": mOSD 259 -> 260 of 285, mOSD as clouds 70 -> 72 of 93, multi-part objects at 320 x
    240 66 -> 68 of 70, meshes at 320 x 240 51 -> 53 of 96, every other suite the same; with no
    explanation asked, mOSD fell to 251 (pieces of an object that the table's surface encloses)."""
    nb = ws.dom.neighbours
    lab = np.where(has, best, -1)
    for i in range(near.shape[0]):
        pieces = free_components(lab == i, nb, 1)
        if len(pieces) < 2:
            continue
        for piece in sorted(pieces, key=len)[:-1]:
            rim = nb[piece].ravel()
            around = np.unique(lab[rim[rim >= 0]])
            around = around[(around >= 0) & (around != i)]
            if around.size == 1 and np.isfinite(near[around[0], piece]).mean() > 0.5:
                best[piece] = lab[piece] = around[0]


def propagate(ws: Workspace, theta, best, has, neighbours: np.ndarray | None = None):
    """Labels for the valid points no model explains but the surface joins to labelled ones.

    Multi-source breadth-first along the adjacency (`neighbours` (P, k), -1 = none; default the
    domain's, cut at depth discontinuities): ring by ring, an unlabelled point next to labelled ones
    takes, of its neighbours' labels, the one whose model is nearest to it. best (P,) model per point,
    has (P,) bool -> the same, extended."""
    best, has = best.copy(), has.copy()
    nb = ws.dom.neighbours if neighbours is None else neighbours
    ok = nb >= 0
    cols = np.where(ok, nb, 0)
    while True:
        lab = np.where(ok & has[cols], best[cols], -1)  # (P, k) neighbours' labels
        front = ~has & (lab >= 0).any(1)
        if not front.any():
            return best, has
        p, j = mask_pairs(lab[front] >= 0)
        p = np.flatnonzero(front)[p]
        m = lab[p, j]
        key = np.unique(p * len(theta) + m)
        p, m = np.divmod(key, len(theta))
        d, _, _ = ws.distances(theta, m, p)
        order = np.lexsort((d, p))
        p, m = p[order], m[order]
        first = np.r_[True, p[1:] != p[:-1]]
        best[p[first]], has[p[first]] = m[first], True


def owners(count: np.ndarray):
    """Models that own labelled pixels (count (M,) of each model's pixels): their indices, and the map
    (M + 1,) from old label (0 = none, i + 1 = model i) to new label, 1..K in the same order."""
    owns = np.flatnonzero(count > 0)
    relabel = np.zeros(count.size + 1, np.int32)
    relabel[owns + 1] = np.arange(1, owns.size + 1)
    return owns, relabel


def label_full(image: RangeImage, step: int, ws: Workspace, models: Models, coarse: np.ndarray):
    """Label every pixel of the full-size `image` with the final models fitted on its `step`-subsampled
    copy (whose labels are `coarse` (h, w)).

    A full-size pixel may take the label of any coarse pixel in the 3 x 3 block around it (its own
    coarse pixel and the 8 adjacent): it goes to the one whose model is nearest (eq. 10; a face turned
    away from the camera pays tau, as in `label_image`), if that model explains it (within tau); else, with
    `propagate`, the label of its own coarse pixel if that one carries a label its model does not explain
    (`_carried`: `propagate`'s, or one the free-space test put out of its model's reach); else 0.
    Returns the (H, W) label image (label i + 1 = model owns[i]), the models that own labels, and the
    runner of the full-size points.
    """
    H, W = image.shape
    h, w = coarse.shape
    flat = np.flatnonzero(image.valid)
    P = image.points.reshape(-1, 3)[flat]
    dom = Domain(P, np.zeros((P.shape[0], 0), np.int64), flat, (H, W), views=viewing_rays(image, P))
    full = Workspace.create(dom, ws.opts, ws.noise, ws.dtype, centre=ws.centre)  # the working image's noise
    r, c = np.divmod(flat, W)
    r, c = np.clip(np.rint(r / step).astype(np.int64), 0, h - 1), np.clip(np.rint(c / step).astype(np.int64), 0, w - 1)
    padded = np.pad(coarse, 1)
    cand = np.stack([padded[r + 1 + dr, c + 1 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], 1)  # (Pf, 9)
    carried = np.zeros(h * w, bool)
    carried[ws.dom.index] = _carried(ws, models, coarse.ravel()[ws.dom.index])
    own = coarse[r, c]
    owner = _nearest_candidate(full, ws, models, cand, np.where(carried[r * w + c], own, 0))
    if ws.opts.extras.propagate:
        owner = _fill_footprint(full, ws, models, owner, np.asarray((cand > 0).any(1)))
    labels, owns = _relabel(full, owner, len(models.theta))
    return labels.reshape(H, W), owns, full


def _fill_footprint(full: Workspace, ws: Workspace, models: Models, owner: np.ndarray, footprint: np.ndarray):
    """`propagate` on the full-size grid: owner (P,) (0 = none, i + 1 = model i) extended to the
    unlabelled full-size pixels of `footprint` (P,) bool (a labelled working pixel in the 3 x 3 block
    around theirs) that the surface joins to labelled ones, along the full-size 8-adjacency cut at depth
    discontinuities (`image_adjacency`, the working image's noise).

    The working labels cover the surface their models leave unexplained; without this the full-size
    pixels between two working rows that no candidate model explains stay 0, and a Kinect's depth bands
    leave stripes across a table (mOSD at 640 x 480: 262 of 285 objects correct at full size instead of
    261, as on the 160 x 120 working grid; 0.2 s of a 6 s scene; benchmarks/RESULTS.md, 2026-12-07).
    Pixels outside the footprint stay as the working labels left them. Clouds labelled in full
    (`label_cloud`) are not filled: along the full cloud's nearest neighbours it cost Bobkov's room1 a
    part (15 -> 14 of 44) and room2 1.5 s, for none gained."""
    todo = footprint & (owner == 0)
    if not todo.any():
        return owner
    nb, _ = image_adjacency(full.dom.index, full.dom.points, full.dom.shape, ws.opts.sensor.jump_factor, ws.noise.sigma)
    inside = footprint[np.where(nb >= 0, nb, 0)] & (nb >= 0)
    nb = np.where(inside & footprint[:, None], nb, -1)
    best, has = propagate(full, models.theta, owner - 1, owner > 0, nb)
    return np.where(has, best + 1, 0).astype(np.int32)


def label_cloud(cloud: np.ndarray, ws: Workspace, models: Models, coarse: np.ndarray):
    """Label every valid row of the (n_rows, 3) `cloud` with the final models fitted on a subset of its
    rows (the workspace's points; their labels `coarse` (n_rows,), 0 elsewhere): as `label_full`, with
    the `_CLOUD_CANDIDATES` nearest working points in place of the 3 x 3 block of coarse pixels.
    Returns the (n_rows,) labels (label i + 1 = model owns[i]), the models that own labels, and the
    runner of the full cloud's points."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stub)

    rows = np.flatnonzero(np.isfinite(cloud).all(1))
    P = np.asarray(cloud[rows], np.float64)
    dom = Domain(P, np.zeros((P.shape[0], 0), np.int64), rows, (len(cloud),))
    full = Workspace.create(dom, ws.opts, ws.noise, ws.dtype, centre=ws.centre)
    k = min(_CLOUD_CANDIDATES, ws.P)
    _, near = cKDTree(ws.dom.points).query(P, k, workers=-1)
    near = near.reshape(P.shape[0], k)
    cand = coarse[ws.dom.index[near]]  # (Pf, k) labels of the nearest working points
    carried = _carried(ws, models, coarse[ws.dom.index])
    fallback = np.where(carried[near[:, 0]], cand[:, 0], 0)
    owner = _nearest_candidate(full, ws, models, cand, fallback)
    return (*_relabel(full, owner, len(models.theta)), full)


def _carried(ws: Workspace, models: Models, labels: np.ndarray) -> np.ndarray:
    """Which working points (P,) hold a label (labels (P,), 0 = none, i + 1 = model i) that their model does
    not explain (eq. 10 within tau): labels `propagate` carried along the surface, or given where the
    free-space test puts the point out of its model's reach. A full-size point no candidate model explains
    takes such a label (`_label_by_candidates`' fallback), as the working point it is nearest did."""
    point = np.flatnonzero(labels > 0)
    d, _, _ = ws.distances(models.theta, labels[point] - 1, point)
    out = np.zeros(labels.shape, bool)
    out[point] = ~(d < ws.tau)
    return out


_CLOUD_CANDIDATES = 8
"""Working points whose labels a full cloud's point may take (`label_cloud`): the adjacency's k."""


def _nearest_candidate(full: Workspace, ws: Workspace, models: Models, cand: np.ndarray, fallback: np.ndarray):
    """The owner (P,) of each of `full`'s points (0 = none, i + 1 = model i) from their candidate labels
    cand (P, C) (the same code): the nearest candidate model that explains the point (eq. 10 within tau;
    a face turned away from the camera pays tau, as in `label_image`), else (with `propagate`)
    `fallback` (P,), the label the working labels propagated to where no model explains."""
    # each point's distinct candidate labels, in (point, label) order: a sort within each row, not of
    # all P x C pairs (a 1.2M-point cloud's 9.6M)
    cand = np.sort(cand, axis=1)
    first = np.ones(cand.shape, bool)
    first[:, 1:] = cand[:, 1:] != cand[:, :-1]
    point, j = mask_pairs(first & (cand > 0))
    model = cand[point, j] - 1
    d, _, away = full.distances(models.theta, model, point)
    inl = d < ws.tau
    score = np.where(inl, d + np.where(away, ws.tau, 0.0), np.inf)
    best = np.full(full.P, np.inf)
    if point.size:  # the pairs are grouped by point: the least score of each group
        starts = np.flatnonzero(np.r_[True, point[1:] != point[:-1]])
        best[point[starts]] = np.minimum.reduceat(score, starts)
    win = inl & (score == best[point])
    owner = np.zeros(full.P, np.int32)
    owner[point[win]] = model[win] + 1  # ties: the later model (any one of them)
    if ws.opts.extras.propagate:
        owner = np.where(owner == 0, fallback, owner).astype(np.int32)
    return owner


def _relabel(full: Workspace, owner: np.ndarray, M: int):
    """owner (P,) over `full`'s points (0 = none, i + 1 = model i, M models) -> flat labels over the
    domain's shape (label i + 1 = model owns[i]) and owns."""
    count = np.bincount(owner, minlength=M + 1)[1:]
    owns, relabel = owners(count)
    labels = np.zeros(int(np.prod(full.dom.shape)), np.int32)
    labels[full.dom.index] = relabel[owner]
    return labels, owns


def parts(ws: Workspace, theta: np.ndarray, labels: np.ndarray) -> list:
    """`Part`s of the models theta (M, 11) that own labels (flat labels over the workspace's points, 0 = none,
    i + 1 = model i; every model owns some): each part's region is its labelled points that its model
    explains (eq. 10 distance within tau)."""
    point = np.flatnonzero(labels > 0)
    point = point[np.argsort(labels[point], kind="stable")]  # grouped by model, in point order
    model = labels[point] - 1
    d, _, _ = ws.distances(theta, model, point)
    inl = d < ws.tau
    M = len(theta)
    count = np.bincount(model, minlength=M)
    error = np.bincount(model[inl], d[inl].astype(np.float64) ** 2, M)
    regions = split_by_model(ws.dom.index[point[inl]], model[inl], M)
    return [
        Part(sq, regions[i], float(error[i]), int(count[i]), int(regions[i].size))
        for i, sq in enumerate(to_world(theta, ws.centre).unbatch() if M else [])
    ]
