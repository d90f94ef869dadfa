"""Initial estimates of a superquadric (Solina & Bajcsy's moment start, and what batching adds).

[jax] for the fitter, on one problem's normalised points (3, N) (centroid 0, rms radius 1) with a mask
(N,): the ellipsoid of the central second moments (the paper's start), a one-view "rim" start and an
algebraic-quadric start, each in its three axis assignments, and the two EMS "switched" alternatives
of a solution. Each returns a stacked LM state (log a, e, R, t, d) of candidates.

[host] for segmentation: `one_view_starts`, numpy float64 starts of many point sets at once (the
moment ellipsoid and two thick starts that lie behind a patch seen from the camera).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import rotation as so3
from .cache import kernel_jit, persistent_kernel
from .deformation import unbend
from .numerics import to_device
from .padding import bucket, pad_rows

# ----------------------------------------------------------------------------------------------------
# [jax] the fitter's candidates


_PERMS = ((0, 1, 2), (1, 2, 0), (2, 0, 1))  # cyclic: the rotation keeps det +1


def take(x, idx, axis: int = 0):
    """x gathered at static indices along `axis` (plain slices: no index arrays, any x64 setting)."""
    return jnp.stack([jnp.take(x, i, axis) for i in idx], axis)


def moment_frame(points, mask):
    """Centroid, right-handed eigenvectors of the covariance (ascending variance), local coordinates."""
    w = mask.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    c = jnp.sum(points * w, 1) / n
    q = (points - c[:, None]) * w
    _, V = jnp.linalg.eigh(q @ q.T / n)
    V = V * jnp.where(jnp.linalg.det(V) < 0, -1.0, 1.0)
    return c, V, V.T @ (points - c[:, None])


def _extent(local, mask):
    big = jnp.finfo(local.dtype).max / 4
    lo = jnp.min(jnp.where(mask, local, big), 1)
    hi = jnp.max(jnp.where(mask, local, -big), 1)
    return lo, hi


def _three(centre, V, half, dtype):
    """The three axis assignments (which eigenvector becomes the model z axis) of one ellipsoid start."""
    half = jnp.maximum(half, 1e-3 * jnp.max(half) + jnp.finfo(dtype).eps)
    return (
        jnp.stack([jnp.log(take(half, p)) for p in _PERMS]),
        jnp.ones((3, 2), dtype),
        jnp.stack([take(V, p, 1) for p in _PERMS]),
        jnp.broadcast_to(centre, (3, 3)),
        jnp.zeros((3, 4), dtype),
    )


def moment_starts(points, mask):
    """The paper's start: the ellipsoid of the bounding box in the frame of the central second moments."""
    c, V, local = moment_frame(points, mask)
    lo, hi = _extent(local, mask)
    return _three(c + V @ ((lo + hi) / 2), V, (hi - lo) / 2, points.dtype)


def _rim_starts(points, mask):
    """One-view start: the visible surface is the front half, so the centre lies at its rim.

    Along the least-spread moment axis (the viewing direction for a half shell) the rim points lie
    behind the apex; the sign comes from the covariance of that coordinate with the squared distance
    from the axis. The centre is put at the rim end and the size along that axis is the full extent.
    """
    c, V, local = moment_frame(points, mask)
    lo, hi = _extent(local, mask)
    w = mask.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    u = local[0]
    rho2 = local[1] ** 2 + local[2] ** 2
    cov = jnp.sum(w * (u - jnp.sum(w * u) / n) * (rho2 - jnp.sum(w * rho2) / n))
    mid = ((lo + hi) / 2).at[0].set(jnp.where(cov > 0, hi[0], lo[0]))
    half = ((hi - lo) / 2).at[0].set(hi[0] - lo[0])
    return _three(c + V @ mid, V, half, points.dtype)


def _quadric_starts(points, mask):
    """Centre and axes of the algebraic least-squares quadric x^T M x + 2 g^T x = 1 when it is an ellipsoid.

    Uses the curvature of a partial view, which moments cannot; half-sizes are the extents of the points
    about that centre. Falls back to the moment start where the quadric is not a bounded ellipsoid.
    """
    dtype = points.dtype
    w = mask.astype(dtype)
    x, y, z = points
    D = jnp.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z]) * w
    A = D @ D.T
    A = A + (1e-6 * jnp.trace(A) / 9 + jnp.finfo(dtype).tiny) * jnp.eye(9, dtype=dtype)
    v = jnp.linalg.solve(A, D @ w)
    M = jnp.stack([jnp.stack([v[0], v[3], v[4]]), jnp.stack([v[3], v[1], v[5]]), jnp.stack([v[4], v[5], v[2]])])
    lam, V = jnp.linalg.eigh(M)
    V = V * jnp.where(jnp.linalg.det(V) < 0, -1.0, 1.0)
    c = -(V @ ((V.T @ v[6:9]) / jnp.where(lam > 0, lam, 1.0)))
    ok = (lam[0] > 1e-3 * lam[2]) & jnp.all(jnp.isfinite(c)) & (jnp.sum(c * c) < 9.0)
    local = jnp.abs(V.T @ (points - c[:, None]))
    half = jnp.max(jnp.where(mask, local, 0.0), 1)
    quad = _three(c, V, half, dtype)
    moment = moment_starts(points, mask)
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), quad, moment)


START_FNS = {"moments": moment_starts, "rim": _rim_starts, "quadric": _quadric_starts}


def initial_states(points, mask, starts, epsilon_starts):
    """All first-stage candidates, stacked: (C, ...) with C = 3 * len(starts) * len(epsilon_starts)."""
    families = [START_FNS[name](points, mask) for name in starts]
    base = jax.tree.map(lambda *a: jnp.concatenate(a), *families)
    out = []
    for e1, e2 in epsilon_starts:
        la, e, R, t, d = base
        out.append((la, jnp.broadcast_to(jnp.asarray([e1, e2], points.dtype), e.shape), R, t, d))
    return jax.tree.map(lambda *a: jnp.concatenate(a), *out)


def switched(state):
    """The two EMS 'switching' alternatives of a solution: the x or the y axis becomes z."""
    la, e, R, t, d = state
    # x -> z: columns (z, y, -x); y -> z: columns (x, z, -y); sizes follow, exponents swap.
    Rx = jnp.stack([R[:, 2], R[:, 1], -R[:, 0]], 1)
    Ry = jnp.stack([R[:, 0], R[:, 2], -R[:, 1]], 1)
    las = jnp.stack([take(la, (2, 1, 0)), take(la, (0, 2, 1))])
    es = jnp.stack([e[::-1], e[::-1]])
    return las, es, jnp.stack([Rx, Ry]), jnp.stack([t, t]), jnp.stack([d, d])


_BEND_ROUNDS = 3
"""Rounds of `bend_starts`' estimate: each unbends the points by the bend so far and adds the
curvature left in their centre line (the parabola is a second-order reading of the bend; one round
reads 55-80% of it on sampled bent surfaces, three 75-110%)."""


def _each_axis_as_z(state):
    """An undeformed state (log a, e, R, t, d) with each of its axes in turn as z: itself and its two
    `switched` forms, stacked (3, ...): (log a, e, R) and the shared centre t."""
    la, e, R, t, _ = state
    sw = switched(state)
    stack = lambda v, i: jnp.concatenate([v[None], sw[i]])
    return stack(la, 0), stack(e, 1), stack(R, 2), t


def bend_starts(state, points, mask):
    """Bent candidates of an undeformed solution (log a, e, R, t, d): each of its axes in turn as the
    bending axis z (itself and the two `switched` forms), bent as the points' centre line runs.

    To second order a bend of curvature k in the plane at angle alpha moves the model-frame axis to
    (x, y) = (k / 2) z^2 (cos alpha, sin alpha). So the points' lateral coordinates (x, y) in each
    candidate's frame are regressed on (1, z, z^2): the z^2 coefficients c2 give k = 2 |c2| and alpha =
    atan2(c2y, c2x), and the constant moves the centre onto that line. From the unbent optimum itself
    LM cannot find a bend: at k = 0 the cost does not depend on alpha, and a bend out of the plane
    alpha = 0 has no first-order gain. Returns a stacked state (3, ...) with d = (0, 0, k, alpha)."""
    las, es, Rs, t = _each_axis_as_z(state)
    w = mask.astype(points.dtype)

    def one(la, R):
        x = R.T @ (points - t[:, None])  # (3, N) model frame
        a3 = jnp.exp(la[2])
        b, shift = jnp.zeros(2, points.dtype), jnp.zeros(2, points.dtype)  # k (cos alpha, sin alpha); centre
        for _ in range(_BEND_ROUNDS):
            k, alpha = jnp.sqrt(jnp.sum(b * b)), jnp.arctan2(b[1], b[0])
            xu = unbend((x - jnp.concatenate([shift, jnp.zeros(1, x.dtype)])[:, None]).T, jnp.stack([k, alpha])).T
            z = xu[2] / a3  # unit half-length: a well-conditioned fit
            A = jnp.stack([jnp.ones_like(z), z, z * z], 1) * w[:, None]  # (N, 3)
            AtA = A.T @ A + 1e-6 * jnp.eye(3, dtype=points.dtype) * jnp.maximum(jnp.sum(w), 1.0)
            c = jnp.linalg.solve(AtA, A.T @ (xu[:2] * w).T)  # (3, 2): constant, slope, curvature terms
            b, shift = b + 2.0 * c[2] / (a3 * a3), shift + c[0]
        k, alpha = jnp.sqrt(jnp.sum(b * b)), jnp.arctan2(b[1], b[0])
        # the unbent solution is wider than the part by the sag of its centre line, (k / 2) a3^2
        sag = 0.5 * k * a3 * a3 * jnp.abs(jnp.stack([jnp.cos(alpha), jnp.sin(alpha)]))
        lateral = jnp.log(jnp.maximum(jnp.exp(la[:2]) - 0.5 * sag, 0.5 * jnp.exp(la[:2])))
        d = jnp.stack([jnp.zeros((), k.dtype), jnp.zeros((), k.dtype), k, alpha])
        return la.at[:2].set(lateral), t + R[:, :2] @ shift, d

    las, ts, ds = jax.vmap(one)(las, Rs)
    return las, es, Rs, ts, ds


TAPER_START_LIMIT = 0.9
"""`taper_starts` clips its estimate to |K| <= this, inside the valid range |K| < 1 (`solver._off_bounds`)."""


TAPER_BINS = 8
"""Slices of the part's height in which `taper_starts` measures the cross-section's reach."""


def taper_starts(state, points, mask):
    """Tapered candidates of an undeformed solution (log a, e, R, t, d): each of its axes in turn as the
    tapering axis z (itself and the two `switched` forms), tapered as the points' width runs along z.

    Tapering scales the cross-section at height z by (1 + K z / a3) (`deformation.taper_points`), and
    the untapered profile g(z) = (1 - |z / a3|^(2/e1))^(e1/2) scales it too. So in the part's frame the
    lateral second moments of the points, regressed on (g^2, g^2 z / a3), change with z along the
    part's own x and y axes: the eigenvectors of their slope turn the undeformed solution's lateral
    axes onto the part's (an untapered fit of a nearly round cross-section has them anywhere, and
    tapers of opposite sign along x and y cancel in a frame turned 45 degrees from it). Then the
    cross-section's reach along each turned axis, the largest |x| in each of `TAPER_BINS` slices of z,
    regressed on (g, g z / a3), has slope / intercept = K. From the untapered optimum LM finds neither
    the turn nor a taper along another axis, and the multistart starts untapered. Returns a stacked
    state (3, ...) with d = (Kx, Ky, 0, 0), |K| <= `TAPER_START_LIMIT`, lateral sizes those of the
    points untapered by K."""
    las, es, Rs, t = _each_axis_as_z(state)
    w = mask.astype(points.dtype)
    dtype = points.dtype

    def regress(g, z, values, weight):  # weighted least squares of values (M, n) on (g, g z): (2, M)
        A = jnp.stack([g, g * z], 1) * weight[:, None]
        AtA = A.T @ A + 1e-6 * jnp.eye(2, dtype=dtype) * jnp.maximum(jnp.sum(weight), 1.0)
        return jnp.linalg.solve(AtA, A.T @ (values * weight).T)

    def one(la, e, R):
        x = R.T @ (points - t[:, None])  # (3, N) model frame
        z = x[2] / jnp.exp(la[2])
        # the untapered profile: the cross-section's scale at height z, (1 - |z|^(2/e1))^(e1/2)
        profile = lambda z: jnp.maximum(1.0 - jnp.clip(jnp.abs(z), 0.0, 1.0) ** (2.0 / e[0]), 0.0) ** (0.5 * e[0])
        g = profile(z)
        slope = regress(g * g, z, jnp.stack([x[0] * x[0], x[1] * x[1], x[0] * x[1]]), w)[1]
        phi = 0.5 * jnp.arctan2(2.0 * slope[2], slope[0] - slope[1])  # the slope's eigenvectors
        c, s = jnp.cos(phi), jnp.sin(phi)
        turn = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype)
        lateral = turn[:2, :2].T @ x[:2]
        # the reach at the slices' centres (a mean of |x| would not do: where y is the wider, more of
        # the perimeter lies on the sides along x, and a taper of 0.5 read as 0.34)
        B = TAPER_BINS
        bins = jnp.clip(jnp.floor((z + 1.0) * (B / 2)), 0, B - 1).astype(jnp.int32)
        reach = jax.ops.segment_max(jnp.where(mask, jnp.abs(lateral), -jnp.inf).T, bins, num_segments=B)  # (B, 2)
        filled = jnp.isfinite(reach[:, 0])
        zb = (jnp.arange(B, dtype=dtype) + 0.5) * (2.0 / B) - 1.0
        fit = regress(profile(zb), zb, jnp.where(filled[:, None], reach, 0.0).T, filled.astype(dtype))  # (2, 2)
        K = fit[1] / jnp.maximum(fit[0], jnp.finfo(dtype).tiny)
        K = jnp.clip(jnp.where(jnp.isfinite(K), K, 0.0), -TAPER_START_LIMIT, TAPER_START_LIMIT)
        # the untapered solution is as wide as the part's widest end: the lateral reach of the points
        # untapered by K (no wider than it)
        reach = jnp.max(jnp.abs(lateral / jnp.maximum(1.0 + K[:, None] * z, 1.0 - TAPER_START_LIMIT)) * w, axis=1)
        width = jnp.exp(la[:2])
        width = jnp.where(jnp.abs(c) >= jnp.abs(s), width, width[::-1])  # turned by more than 45 degrees
        la = la.at[:2].set(jnp.log(jnp.clip(reach, 0.25 * width, width)))
        return la, R @ turn, jnp.concatenate([K, jnp.zeros(2, dtype)])

    las, Rs, ds = jax.vmap(one)(las, es, Rs)
    return las, es, Rs, jnp.broadcast_to(t, (3, 3)), ds


# ----------------------------------------------------------------------------------------------------
# [host] segmentation's starts of point sets


def one_view_starts(points: np.ndarray, regions: list, origin: np.ndarray | None = None) -> np.ndarray:
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
    rotations = to_device(pad_rows(R, bucket(K, 32), np.eye(3)), jax.dtypes.canonicalize_dtype(np.float64))
    w = np.asarray(_log_rotations(rotations), np.float64)[:K]
    out = [np.concatenate([np.log(np.maximum(thin, 1e-3 * thin.max(1, keepdims=True))), np.ones((K, 2)), w, centre], 1)]
    for e in (1.0, 0.3):
        out.append(np.concatenate([np.log(half), np.full((K, 2), e), w, centre + back], 1))
    return np.stack(out)


_log_rotations = persistent_kernel(kernel_jit(so3.log))
