"""The per-dtype thresholds of every safe branch, in one table (after jaxlie's `get_epsilon`).

Each is used where an operand is made safe *before* a singular operation (a `log` of 0, a division by
0, an `exp` that would overflow), so that values and gradients stay finite for every finite input.
"""

from __future__ import annotations

import numpy as np

_EPSILON = {
    # name: (float32, float64)
    "rotation": (1e-5, 1e-10),  # squared angle below which exp / log of rotations take their series
    "ratio": (1e-10, 1e-20),  # |x / a| floored at this before its logarithm (eq. 5)
    "log_f_cap": (20.0, 60.0),  # log F capped here: far beyond any data, yet (F - 1)^2 cannot overflow
    "log_f_floor": (-20.0, -40.0),  # log F floored here in distances (within ~1e-9 a of the centre)
    "grad_floor": (1e-18, 1e-150),  # |grad log F| floored here (beyond the cap of F, far outside)
    "divisor": (1e-6, 1e-12),  # |denominator| of the tapering map floored here
    "bend": (1e-12, 1e-30),  # denominator of the inverse bending's in-plane shift floored here
}


def eps(name: str, dtype) -> float:
    """The threshold `name` of the table above for `dtype` (float32, else float64)."""
    f32, f64 = _EPSILON[name]
    return f32 if np.dtype(dtype) == np.float32 else f64


def is_real(dtype) -> bool:
    """Whether `dtype` holds real numbers (integers or floats): not bool, not strings or objects, and not
    complex, whose cast to float would drop the imaginary part with only numpy's warning."""
    return bool(np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating))


def to_device(x, dtype):
    """Host data (array-like) -> a device array of `dtype`, converted by numpy on the host.

    `jnp.asarray(x, dtype)` compiles a small conversion for every new shape (and reads it back from the
    persistent cache in every later process, ~20 ms each); a command that meets a dozen shapes loses a
    few tenths of a second to them. Traced values (under jit / grad) go through `jnp.asarray`.
    """
    import jax
    import jax.numpy as jnp

    if isinstance(x, jax.core.Tracer):  # pyright: ignore[reportAttributeAccessIssue]
        return jnp.asarray(x, dtype)
    if isinstance(x, jax.Array) and x.dtype == dtype:
        return x
    return jax.device_put(np.asarray(x, dtype))
