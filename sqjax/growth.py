"""Growth (the paper's section 3, step 2): every active hypothesis grows by one step, all refitted in
one batch.

A step enlarges each model (a1..a3 times `enlarge`), takes the points image-adjacent to its region
(`rings` rings) that lie inside the enlarged model and near its surface (eq. 10 within
`admit_factor` tau: loose, or within tau: strict), refits on the grown region from the current
parameters, and keeps the step while the region grows and the fit stays acceptable (`keep_fraction` of
the grown region within tau). A failed step is tried in the other admission from the same state; when
both failed there, the model stops in its last good state (`_failed`).
"""

from __future__ import annotations

import numpy as np

from .hypotheses import Models, mask_pairs, split_by_model
from .workspace import Workspace


def grow(ws: Workspace, models: Models):
    """One growth step for every active model: enlarge, admit adjacent points near the model, refit.

    Distances are computed only where they are needed: on the candidate ring around each region
    (admission) and on the grown region after the refit (what stays)."""
    opts = ws.opts.growth
    act = np.flatnonzero(models.active)
    if act.size == 0:
        return
    R = models.regions[act]
    cand = ws.dom.dilate(R, opts.rings) & ~R  # pyright: ignore[reportArgumentType]  (segment() sets rings)
    k, p = mask_pairs(cand)
    admit = np.where(models.loose[act], opts.admit_factor, 1.0)[k] * ws.tau  # (E,) each pair's admission distance
    d, inside, _ = ws.distances(models.theta[act], k, p, within=admit)
    ok = inside & (d < admit)
    before = R.sum(1)
    grown = R.copy()
    grown[k[ok], p[ok]] = True
    has_new = np.bincount(k[ok], minlength=act.size) > 0
    _failed(models, act[~has_new], before[~has_new], admitted=False)
    sel = np.flatnonzero(has_new)
    if sel.size == 0:
        return
    grown = grown[sel]
    k, p = mask_pairs(grown)
    new_theta = ws.fit(split_by_model(p, k, sel.size), models.theta[act[sel]])  # each region's points
    d, _, _ = ws.distances(np.nan_to_num(new_theta), k, p, within=ws.tau)
    inl = d < ws.tau
    kept = np.bincount(k[inl], minlength=sel.size)
    size = np.bincount(k, minlength=sel.size)
    dist = split_by_model(d[inl], k[inl], sel.size)
    grown[:] = False
    grown[k[inl], p[inl]] = True  # now the new regions: the grown points within tau
    m = act[sel]
    good = np.isfinite(new_theta).all(1) & (kept >= opts.keep_fraction * size) & (kept > before[sel])
    _failed(models, m[~good], before[sel][~good])
    models.theta[m[good]], models.regions[m[good]] = new_theta[good], grown[good]
    for j in np.flatnonzero(good):
        models.dist[m[j]] = dist[j]


def _failed(models: Models, m: np.ndarray, size: np.ndarray, admitted: bool = True):
    """Models `m` (regions of `size` points) whose step failed: it broke the fit, did not grow or
    (`admitted` False) admitted nothing. The model takes its next step in the other admission (loose:
    candidates within admit_factor tau, strict: within tau), unless that one failed in this same state
    too, or a loose step admitted nothing (a strict one would not either); then it stops in its last
    good state. A model keeps the admission of its last good step: after a loose step fails, strict
    steps follow until they stop (a loose step after each strict one failed again in most cases, half
    the steps of the last growing models on mOSD), then one loose step tries again."""
    loose = models.loose[m]
    stop = (models.failed_at[m] == size) | (loose & (not admitted))
    models.failed_at[m] = size
    models.loose[m] = ~loose
    models.active[m[stop]] = False
