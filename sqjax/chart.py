"""The parameter vector theta of a superquadric (the global chart the fitter and segmentation share).

    theta = [log a1, log a2, log a3, e1, e2, w (rotation vector, 3), t (translation, 3), (Kx, Ky, k, alpha)]

Sizes as logs (positive by construction), the rotation as a rotation vector (`rotation.exp` / `log`),
the four deformation parameters only with `deform`. Address it by the named slices below, never by
bare numbers. The fitter's LM state is the unpacked tuple (log a, e, R, t, d), whose rotation is updated
on the manifold, R <- R exp(dw).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import rotation as so3
from .cache import kernel_jit, persistent_kernel
from .deformation import max_curvature
from .numerics import to_device
from .superquadric import Superquadric

NUM_PARAMS = 11
"""Parameters of an undeformed superquadric (the paper's N_i); also the fewest points a fit needs."""
NUM_DEFORM = 4
"""Tapering Kx, Ky and bending k, alpha."""

LOG_SIZE = slice(0, 3)
EPSILON = slice(3, 5)
ROTATION = slice(5, 8)
TRANSLATION = slice(8, 11)
TAPER = slice(11, 13)
BEND = slice(13, 15)
DEFORMATION = slice(11, 15)


def num_params(deform: bool) -> int:
    """Length of theta: 11, or 15 with deformations."""
    return NUM_PARAMS + (NUM_DEFORM if deform else 0)


def unpack(theta, deform: bool):
    """theta (P,) -> the LM state (log a (3,), e (2,), R (3, 3), t (3,), d (4,)); d = 0 without `deform`."""
    d = theta[DEFORMATION] if deform else jnp.zeros(NUM_DEFORM, theta.dtype)
    return theta[LOG_SIZE], theta[EPSILON], so3.exp(theta[ROTATION]), theta[TRANSLATION], d


def pack(la, e, R, t, d, deform: bool):
    """The LM state -> theta (P,), the inverse of `unpack`."""
    parts = [la, e, so3.log(R), t] + ([d] if deform else [])
    return jnp.concatenate(parts)


def clip_deformation(d, log_size, epsilon):
    """Deformation d (4,) = (Kx, Ky, k, alpha) within its valid range: tapering in [-1, 1], bending
    curvature in [0, `deformation.max_curvature`] of the model (log a (3,), e (2,)); alpha as given."""
    taper = jnp.clip(d[:2], -1.0, 1.0)
    k = jnp.clip(d[2], 0.0, max_curvature(log_size, epsilon[1], taper, d[3]))
    return jnp.concatenate([taper, k[None], d[3:]])


def project(theta, epsilon_range, deform: bool):
    """theta (P,) with its exponents in `epsilon_range` and its deformation in its valid range
    (`clip_deformation`)."""
    lo, hi = epsilon_range
    theta = theta.at[EPSILON].set(jnp.clip(theta[EPSILON], lo, hi))
    if deform:
        theta = theta.at[DEFORMATION].set(clip_deformation(theta[DEFORMATION], theta[LOG_SIZE], theta[EPSILON]))
    return theta


def to_superquadric(theta, deform: bool | None = None) -> Superquadric:
    """theta (..., P) -> `Superquadric` (P = 11, or 15 with deformations; `deform` None: from P)."""
    deform = theta.shape[-1] == num_params(True) if deform is None else deform
    if theta.ndim > 1:
        return jax.vmap(lambda t: to_superquadric(t, deform))(theta)
    la, e, R, t, d = unpack(theta, deform)
    return Superquadric(jnp.exp(la), e, R, t, d[0:2], d[2:4])


def from_fields(fields, epsilon_range, deform: bool):
    """Batched fields (size, epsilon, rotation, translation, taper, bend), each (K, ...) -> theta (K, P)
    and a (K,) flag of the valid ones; invalid ones (non-finite, size <= 0) become a unit sphere."""
    size, eps, R, t, taper, bend = fields
    ok = (
        jnp.all(jnp.isfinite(size) & (size > 0), -1)
        & jnp.all(jnp.isfinite(eps), -1)
        & jnp.all(jnp.isfinite(R), (-2, -1))
        & jnp.all(jnp.isfinite(t), -1)
    )
    if deform:
        ok = ok & jnp.all(jnp.isfinite(taper), -1) & jnp.all(jnp.isfinite(bend), -1)
    lo, hi = epsilon_range
    safe = lambda v, d: jnp.where(ok.reshape(ok.shape + (1,) * (v.ndim - 1)), v, d)
    size = safe(size, 1.0)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=R.dtype), R.shape)
    parts = [jnp.log(size), jnp.clip(safe(eps, 1.0), lo, hi), so3.log(safe(R, eye)), safe(t, 0.0)]
    if deform:
        parts += [safe(taper, 0.0), safe(bend, 0.0)]
    return jnp.concatenate(parts, -1), ok


@kernel_jit
def _world(theta, centre) -> Superquadric:
    sq = to_superquadric(theta)
    return Superquadric(sq.size, sq.epsilon, sq.rotation, sq.translation + centre, sq.taper, sq.bend)


def to_world(theta: np.ndarray, centre: np.ndarray) -> Superquadric:
    """Host theta (M, 11) about `centre` (3,) -> one batched float32 `Superquadric` in the data's frame.

    Rows are padded to a power of two (at least 32) so that few shapes compile; the result has M rows."""
    from .padding import bucket, pad_rows

    M = len(theta)
    th = to_device(pad_rows(theta, bucket(M, 32), theta[0]), np.float32)
    sq = _world(th, to_device(centre, np.float32))
    return jax.tree.map(lambda v: v[:M], jax.tree.map(np.asarray, sq))


@persistent_kernel
@kernel_jit
def _volumes(theta):
    return to_superquadric(theta).volume


def volumes(theta: np.ndarray) -> np.ndarray:
    """Volumes (M,) of the undeformed models theta (M, 11) (padded like `to_world`)."""
    from .padding import bucket, pad_rows

    M = len(theta)
    return np.asarray(_volumes(to_device(pad_rows(theta, bucket(M, 32), theta[0]), np.float32)))[:M]
