"""The scene as the kernels see it: the sensor noise, the points on the device, and the two batched
kernels that every step of recover-and-select calls: eq. 10 distances of (model, point) pairs and the
refits of many regions at once.

Host orchestration in numpy around jit-compiled kernels, in calls of a few fixed sizes (`padding`), so a
growth step recompiles only when it first meets a new size. Distances are computed only for the
(model, point) pairs that are read (a region and the ring of candidates around it). The models live in
a frame centred on the data (`Workspace.centre`), so float32 keeps its precision near the points.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import jax
import jax.numpy as jnp
import numpy as np

from . import parallel
from . import rotation as so3
from .cache import kernel_jit, persistent_kernel
from .chart import EPSILON, LOG_SIZE, ROTATION, TRANSLATION
from .domain import Domain, noise_scale, robust_centre
from .numerics import to_device
from .padding import calls, fit_calls, pad_rows, pair_split, point_rows, refit_points
from .solver import fit_padded, fit_padded_sharded
from .superquadric import distance_from_log, log_inside_outside_and_gradient
from .visibility import seen_through

if TYPE_CHECKING:
    from .options import SegmentOptions

_QUEUE = 3
"""Distance chunks in flight while one is read back."""


@dataclasses.dataclass(frozen=True)
class Noise:
    """The sensor noise every distance is measured in.

    `sigma` is the noise std at depth `z_ref`, `tau` the admission distance (eq. 10). With `exponent`
    k > 0 (range images) the noise is sigma (z / z_ref)^k, and each point's distance is divided by its
    (z / z_ref)^k, so that tau and the selection weights count in units of the local noise."""

    sigma: float
    tau: float
    exponent: float = 0.0
    z_ref: float = 1.0

    @property
    def margin(self) -> float:
        """How far a point must lie behind a model's surface before the model is said to block its ray."""
        return 2.0 * self.tau

    def scale(self, points: np.ndarray) -> np.ndarray | None:
        """(P,) float32 local noise over `sigma` of camera-frame points (P, 3); None for one noise."""
        return None if self.exponent == 0 else noise_scale(points, self.exponent, self.z_ref).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class Workspace:
    """A domain, its noise and options, and the device buffers of its points (see the module doc).

    `host_points` (P, 3) float64 and `points`, `views` (padded rows, `padding.point_rows`) on the device
    are in the frame centred on `centre`; theta rows (M, 11) of models are in that frame too."""

    dom: Domain
    opts: SegmentOptions
    noise: Noise
    dtype: Any
    centre: np.ndarray
    host_points: np.ndarray
    points: jax.Array
    views: jax.Array
    scale: np.ndarray | None

    @classmethod
    def create(cls, dom: Domain, opts: SegmentOptions, noise: Noise, dtype=jnp.float32, centre=None) -> Workspace:
        centre = robust_centre(dom.points) if centre is None else np.asarray(centre, np.float64)
        host = dom.points - centre
        rows = point_rows(dom.points.shape[0])
        views = np.zeros_like(host) if dom.views is None else dom.views
        return cls(
            dom,
            opts,
            noise,
            dtype,
            centre,
            host,
            to_device(pad_rows(host, rows, np.zeros(3)), dtype),
            to_device(pad_rows(views, rows, np.zeros(3)), dtype),
            noise.scale(dom.points),
        )

    def with_noise(self, noise: Noise) -> Workspace:
        """The same workspace measured in another noise (the device buffers are shared)."""
        return dataclasses.replace(self, noise=noise, scale=noise.scale(self.dom.points))

    @property
    def P(self) -> int:
        return self.dom.points.shape[0]

    @property
    def tau(self) -> float:
        return self.noise.tau

    @property
    def camera(self) -> np.ndarray | None:
        """The camera centre in the workspace frame (range images), None for clouds."""
        return -self.centre if self.dom.views is not None else None

    def distances(self, theta, model, point, within: float | np.ndarray = np.inf):
        """Eq. 10 distances (E,) float32 of the pairs (point[e] to model theta[model[e]]), whether
        each point is inside its model enlarged (E,) bool and whether the model's surface there faces
        away from the camera (E,) bool (see `_pair_distances`). theta (K, 11); model, point (E,).
        Distances are in units of the local noise over `noise.sigma` (`Noise.scale`); with
        `ExtraOptions.visibility` a point the camera saw through the model to reach
        (`visibility.seen_through`, tested where the surface faces away) is at distance inf: no model
        explains what it would hide. That test runs only on pairs nearer than `within` (a scalar or
        (E,)): a caller that thresholds the distances at `within` or below decides alike, and a
        farther pair keeps its distance.

        Only the pairs asked for are computed, in calls of a few fixed sizes (`padding.calls`), a few queued
        ahead of the one read back. Each pair gets its model's row of theta, gathered here, so the
        kernel compiles once per chunk size whatever the number of models.
        """
        E = model.size
        d, inside, away = np.empty(E, np.float32), np.empty(E, bool), np.empty(E, bool)
        if E == 0:
            return d, inside, away
        theta = np.asarray(theta, np.dtype(self.dtype))
        host = np.dtype(self.dtype)  # numpy inputs: the kernel call transfers them (no eager device ops)
        args = (host.type(self.opts.growth.enlarge), host.type(self.noise.margin))
        split = (True, False, False, True, False, False)  # the pairs' rows and indices; the points whole

        def read(s, m, out):
            for dst, src in zip((d, inside, away), out):
                dst[s : s + m] = np.asarray(src)[:m]

        pending = []
        for s, n in calls(E):
            kernel = parallel.sharded_kernel(_pair_distances, split) if pair_split(n) else _pair_distances
            m = min(n, E - s)
            mi, pi = np.zeros(n, np.int64), np.zeros(n, np.int32)
            mi[:m], pi[:m] = model[s : s + m], point[s : s + m]
            pending.append((s, m, kernel(theta[mi], self.points, self.views, pi, *args)))
            if len(pending) > _QUEUE:
                read(*pending.pop(0))
        for item in pending:
            read(*item)
        if self.scale is not None:
            d /= self.scale[point]
        test = away & (d < within)
        if self.opts.extras.visibility and test.any():
            # visibility: a point whose ray passes through the model's solid (deeper than the noise)
            # is not on the surface the camera saw of it, however near its back face: not explained
            a = np.flatnonzero(test)
            d[a[seen_through(self, theta, model[a], point[a])]] = np.inf
        return d, inside, away

    def fit(self, regions, theta0, size_bound=False):
        """Fit each region (index array, subsampled to max_points) from theta0 (K, 11), or with the
        fitter's own multistart (moment axes + EMS switches) when theta0 is None -> theta (K, 11), NaN
        rows where a fit failed.

        The regions go to the batch kernel in calls of a few sizes (`padding.fit_calls`), each of
        `padding.refit_points` points. Kernels compiled on CPU: one per (N, call size, start or
        multistart), 3-9 s each the first time. The calls are queued before any result is read back. The size
        bound is traced, not compiled in: growth (which extrapolates) and the bounded part refits share
        one kernel per shape.
        """
        K = len(regions)
        max_points = self.opts.growth.max_points
        N = refit_points(max(r.size for r in regions), max_points)
        opts = dataclasses.replace(self.opts.fit, multistart=theta0 is None, size_bound=np.asarray(size_bound))
        pts = np.zeros((K, N, 3))
        msk = np.zeros((K, N), bool)
        host = np.dtype(self.dtype)  # numpy inputs: the kernel call transfers them
        for i, r in enumerate(regions):
            if r.size > max_points:
                r = r[np.linspace(0, r.size - 1, max_points).astype(np.int64)]
            pts[i, : r.size], msk[i, : r.size] = self.host_points[r], True
        pending = []
        for s, n in fit_calls(K, N, quarter=theta0 is not None):
            r = np.arange(s, s + n)
            r = np.where(r < K, r, 0)  # padding: copies of problem 0, dropped below
            kernel = fit_padded_sharded if parallel.splits(n) else fit_padded
            pending.append(
                kernel(pts[r].astype(host), msk[r], None if theta0 is None else theta0[r].astype(host), opts)[0]
            )
        theta = np.concatenate([np.asarray(t) for t in pending])[:K].astype(np.float64)
        return np.where(np.isfinite(theta).all(1, keepdims=True), theta, np.nan)


@persistent_kernel
@kernel_jit
def _pair_distances(theta, points, views, point, enlarge, margin):
    """Eq. 10 distance of `points[point[e]]` to the model `theta[e]`, whether the point lies inside
    that model enlarged (a1..a3 times `enlarge`, plus `margin`), and whether the model's outward
    normal there turns away from the camera (n . view > 0.2 for the unit viewing ray `views` (P, 3) of
    the point; zero rays = unknown, never away).

    theta (E, 11) (one row per pair: the shapes depend on E only), points (P, 3), point (E,) int32
    -> (E,) distances, (E,) bool, (E,) bool. Undeformed models only (segmentation fits none): eq. 10 is
    rotation-invariant, so it is evaluated in the model frame in closed form (`distance_from_log`).
    """
    rot = jax.vmap(so3.exp)(theta[:, ROTATION])
    x = jnp.einsum("ei,eij->ej", points[point] - theta[:, TRANSLATION], rot)
    view = jnp.einsum("ei,eij->ej", views[point], rot)
    la, e = theta[:, LOG_SIZE], theta[:, EPSILON]
    log_f, log_gnorm, normal = log_inside_outside_and_gradient(x, la, e)
    d = distance_from_log(log_f, log_gnorm)
    big, _, _ = log_inside_outside_and_gradient(x, jnp.log(jnp.exp(la) * enlarge + margin), e)
    return d, big <= 0.0, jnp.sum(normal * view, -1) > 0.2
