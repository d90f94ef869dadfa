"""Visibility: a model that fills space the camera saw through is contradicted by the data.

A range image's pixel says that its viewing ray is empty up to the observed point (and, with no return,
empty as far as the sensor reaches). `seen_through` tells, pair by pair, whether a point's ray passes
through a model's solid deeper than the noise: such a point cannot lie on the surface the camera saw of
that model, so the model does not explain it (`Workspace.distances`, `ExtraOptions.visibility`).
`free_space_violations` counts the observed points whose viewing ray passes through a model in front of
them, `void_violations` the pixels with no return whose ray passes through it; merges
(`postprocess.merge`), the parts' volumes (`postprocess.part_volumes`) and, as an option, selection
(`SelectionOptions.free_space`) use them. Clouds have no viewpoint: never seen through, zeros.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from . import parallel
from . import rotation as so3
from .cache import kernel_jit, persistent_kernel
from .chart import EPSILON, LOG_SIZE, ROTATION, TRANSLATION
from .hypotheses import mask_pairs
from .padding import calls, pair_split
from .superquadric import distance_from_log, log_inside_outside_and_gradient

if TYPE_CHECKING:
    from .workspace import Workspace


def free_space_violations(ws: Workspace, theta, *, box: bool = False) -> np.ndarray:
    """(M,) for models theta (M, 11): the valid points whose viewing ray passes through the model
    in front of them (by more than tau, in units of the local noise; `_free_space`). Candidates
    are the points whose ray passes within the model's bounding sphere, in front of the point.
    Images only (clouds have no viewpoint): zeros otherwise. `box`: sampled with `_free_space_box`."""
    M = len(theta)
    out = np.zeros(M, np.int64)
    if ws.dom.views is None or M == 0:
        return out
    P, v = ws.host_points, ws.dom.views
    c = theta[:, TRANSLATION]
    radius = np.sqrt(np.sum(np.exp(2.0 * theta[:, LOG_SIZE]), -1))
    pairs_m, pairs_p = [], []
    for rows in _model_blocks(M, len(P)):
        w = P - c[rows, None]  # (m, P, 3)
        t = np.einsum("mpj,pj->mp", w, v)  # > 0: the model's centre is in front of p
        perp2 = np.einsum("mpj,mpj->mp", w, w) - t * t
        r = radius[rows, None]
        m, p = mask_pairs((perp2 < r * r) & (t + r > ws.tau))
        pairs_m.append(m + rows.start)
        pairs_p.append(p)
    model, point = np.concatenate(pairs_m), np.concatenate(pairs_p)
    if model.size == 0:
        return out
    margin = ws.tau * (np.ones(point.size) if ws.scale is None else ws.scale[point])
    return _ray_hits(ws, theta, model, P[point], v[point], margin, box)


def _ray_hits(ws: Workspace, theta, model, ends, rays, margin, box: bool = False) -> np.ndarray:
    """(M,) counts of the pairs e whose ray, back from `ends[e]` along `-rays[e]` (from `margin[e]`
    on), passes through the model `theta[model[e]]` (`_free_space`), in fixed-size chunks."""
    return np.bincount(model[ray_blocked(ws, theta, model, ends, rays, margin, box)], minlength=len(theta))


def seen_through(ws: Workspace, theta, model, point) -> np.ndarray:
    """(E,) whether the camera saw through the model theta[model[e]] (K, 11) on its way to the point
    point[e]: its viewing ray passes through the model's solid deeper than tau (in units of the local
    noise) before the point (`_seen_through`). Such a point is not on the surface the camera saw of
    that model, however near a back face it lies. Clouds have no rays: never."""
    if ws.dom.views is None or model.size == 0:
        return np.zeros(model.size, bool)
    depth = ws.tau * (np.ones(point.size) if ws.scale is None else ws.scale[point])
    return _ray_kernel(ws, _seen_through, theta, model, ws.host_points[point], ws.dom.views[point], depth)


def ray_blocked(ws: Workspace, theta, model, ends, rays, margin, box: bool = False) -> np.ndarray:
    """(E,) whether the ray of pair e, back from `ends[e]` (workspace frame) along `-rays[e]` (from
    `margin[e]` on), passes through the model `theta[model[e]]` (`_free_space`, or `_free_space_box`
    with `box`)."""
    return _ray_kernel(ws, _free_space_box if box else _free_space, theta, model, ends, rays, margin)


def _ray_kernel(ws: Workspace, kernel, theta, model, ends, rays, per_pair) -> np.ndarray:
    """`kernel(theta rows, ends, rays, index, per_pair[, limit])` over the pairs in calls of a few fixed
    sizes (`padding.calls`); the box-chord kernels also get `limit`, the distance back to the camera."""
    theta_d = np.asarray(theta, np.dtype(ws.dtype))
    hit = np.zeros(model.size, bool)
    for s, n in calls(model.size):
        m = min(n, model.size - s)
        mi, pts, ray, val = np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)
        mi[:m], pts[:m], ray[:m], val[:m] = model[s : s + m], ends[s : s + m], rays[s : s + m], per_pair[s : s + m]
        host = theta_d.dtype  # numpy inputs: the kernel call transfers them (no eager device ops)
        split = pair_split(n)  # every argument is per pair: split, with each block's indices its own
        index = np.arange(n, dtype=np.int32) % (n // parallel.cpu_devices() if split else n)
        args = [theta_d[mi], pts.astype(host), ray.astype(host), index, val.astype(host)]
        if kernel is not _free_space:  # back to the camera at most (its plane, orthographic)
            args.append(np.einsum("ej,ej->e", pts + ws.centre, ray).astype(host))
        run = parallel.sharded_kernel(kernel, (True,) * len(args)) if split else kernel
        hit[s : s + m] = np.asarray(run(*args))[:m]
    return hit


def void_violations(ws: Workspace, theta, *, box: bool = False) -> np.ndarray:
    """(M,) for models theta (M, 11): the pixels with no return (`_Domain.void_rays`) whose viewing
    ray passes through the model (`_free_space` along the ray's chord of the bounding sphere). The
    camera saw no surface there, so a model there is contradicted. Pinhole images only: zeros
    otherwise. `box`: sampled with `_free_space_box`."""
    M = len(theta)
    out = np.zeros(M, np.int64)
    v = ws.dom.void_rays
    if v is None or M == 0 or len(v) == 0:
        return out
    o = -ws.centre  # the camera, in the runner's frame
    c = theta[:, TRANSLATION]
    radius = np.sqrt(np.sum(np.exp(2.0 * theta[:, LOG_SIZE]), -1))
    pairs_m, ends, dirs = [], [], []
    for rows in _model_blocks(M, len(v)):
        d = c[rows] - o  # (m, 3)
        t = np.einsum("mj,qj->mq", d, v)  # along each ray to the model's centre
        perp2 = np.einsum("mj,mj->m", d, d)[:, None] - t * t
        r = radius[rows, None]
        m, q = mask_pairs((perp2 < r * r) & (t + r > 0))
        pairs_m.append(m + rows.start)
        ends.append(o + (t[m, q] + r[m, 0])[:, None] * v[q])  # behind the sphere, on the ray
        dirs.append(v[q])
    model, end, ray = np.concatenate(pairs_m), np.concatenate(ends), np.concatenate(dirs)
    if model.size == 0:
        return out
    return _ray_hits(ws, theta, model, end, ray, np.zeros(model.size), box)


_BLOCK = 1 << 21
"""(model, point) entries per block of the bounding-sphere test (a few tens of MB of float64)."""


def _model_blocks(M: int, per_model: int):
    """Slices of the M models, each block of them tested against all `per_model` rays at once."""
    n = max(1, _BLOCK // max(per_model, 1))
    return (slice(s, min(s + n, M)) for s in range(0, M, n))


_RAY_SAMPLES = 16


@persistent_kernel
@kernel_jit
def _free_space(theta, points, views, point, margin):
    """Whether the model `theta[e]` occupies the free space in front of the point `points[point[e]]`:
    any of `_RAY_SAMPLES` samples on its viewing ray, from `margin[e]` in front of the point back to the
    near side of the model's bounding sphere, lies inside the model (log F < 0, eq. 5). The camera saw
    through there, so a model that fills it is contradicted by the data. theta (E, 11), points (P, 3),
    views (P, 3) unit rays, point (E,) int32, margin (E,) -> (E,) bool.

    The samples span the sphere's chord: a swollen model (a bar 40 m long and 5 cm thick across the
    ray) is sampled every few metres and seldom seen; `_free_space_box` samples the box's chord."""
    rot = jax.vmap(so3.exp)(theta[:, ROTATION])
    p, v, c = points[point], views[point], theta[:, TRANSLATION]
    radius = jnp.sqrt(jnp.sum(jnp.exp(2.0 * theta[:, LOG_SIZE]), -1))
    reach = jnp.sum((p - c) * v, -1) + radius  # how far back towards the camera to look
    frac = (jnp.arange(_RAY_SAMPLES) + 0.5) / _RAY_SAMPLES
    back = margin[:, None] + jnp.maximum(reach - margin, 0.0)[:, None] * frac  # (E, S)
    q = p[:, None] - back[..., None] * v[:, None]
    x = jnp.einsum("esi,eij->esj", q - c[:, None], rot)
    log_f, _, _ = log_inside_outside_and_gradient(x, theta[:, None, LOG_SIZE], theta[:, None, EPSILON])
    return jnp.any(log_f < 0.0, -1) & (reach > margin)


def _box_chord(theta, points, views, point, margin, limit):
    """Samples (E, S, 3) in the model frame on the viewing ray of each pair, over its chord of the model's
    bounding box between `margin[e]` and `limit[e]` back from the point, and whether the chord is
    not empty (E,)."""
    rot = jax.vmap(so3.exp)(theta[:, ROTATION])
    p, v, c = points[point], views[point], theta[:, TRANSLATION]
    x0 = jnp.einsum("ei,eij->ej", p - c, rot)  # the point, in the model frame
    dx = -jnp.einsum("ei,eij->ej", v, rot)  # back towards the camera, unit
    a = jnp.exp(theta[:, LOG_SIZE])
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
    return x0[:, None] + back[..., None] * dx[:, None], hi > lo


@persistent_kernel
@kernel_jit
def _free_space_box(theta, points, views, point, margin, limit):
    """`_free_space` with the samples on the ray's chord of the model's bounding box, between
    `margin[e]` and `limit[e]` (the camera) back from the point: a bar 40 m long and 5 cm thick across
    the ray is sampled across its 5 cm. limit (E,); the rest as `_free_space`."""
    x, chord = _box_chord(theta, points, views, point, margin, limit)
    log_f, _, _ = log_inside_outside_and_gradient(x, theta[:, None, LOG_SIZE], theta[:, None, EPSILON])
    return jnp.any(log_f < 0.0, -1) & chord


@persistent_kernel
@kernel_jit
def _seen_through(theta, points, views, point, depth, limit):
    """Whether the viewing ray of `points[point[e]]`, between the point and `limit[e]` (the camera),
    passes through the model `theta[e]` deeper than `depth[e]` (eq. 10 distance of a sample inside the
    model from its surface): the camera saw through solid that noise cannot explain. A ray that only
    grazes the model (its rim, within the noise) is not seen through. Shapes as `_free_space_box`."""
    x, chord = _box_chord(theta, points, views, point, jnp.zeros_like(depth), limit)
    log_f, log_gn, _ = log_inside_outside_and_gradient(x, theta[:, None, LOG_SIZE], theta[:, None, EPSILON])
    deep = (log_f < 0.0) & (distance_from_log(log_f, log_gn) > depth[:, None])
    return jnp.any(deep, -1) & chord
