"""The quality of a fit as data, not as an exception (after optimistix's `RESULTS`): `Status` flags per
problem, combined bitwise in `Fit.status`.
"""

from __future__ import annotations

import enum

from .chart import NUM_PARAMS


class Status(enum.IntFlag):
    """Quality flags of one fit, combined bitwise in `Fit.status` (0 = `OK`). Data, never an exception.

    - `MAX_STEPS`: the last LM steps still lowered the cost (not converged in `max_steps`).
    - `BOUND_ACTIVE`: an exponent sits on its bound (a deformation never does: one on its bound is
      not kept, `FitOptions.deform`).
    - `LARGE_RESIDUAL`: the median eq. 10 distance exceeds 3x the given `noise` (without one: 2 % of
      the mean size of the model).
    - `DEGENERATE`: the points are identical or collinear, or the warm start is not finite / positive.
    - `TOO_FEW_POINTS`: fewer than `chart.NUM_PARAMS` valid points (only under tracing; on the host it raises).
    - `NONFINITE`: the cost or a parameter came out non-finite (replaced by the start).
    - `FAR_POINTS`: points farther than `far_factor` x the median radius from the median centre were
      dropped (a depth pixel at 1e30, say); their weight is 0.
    """

    OK = 0
    MAX_STEPS = 1
    BOUND_ACTIVE = 2
    LARGE_RESIDUAL = 4
    DEGENERATE = 8
    TOO_FEW_POINTS = 16
    NONFINITE = 32
    FAR_POINTS = 64

    @classmethod
    def describe(cls, code) -> str:
        """Human-readable names of the flags set in one status code, e.g. "MAX_STEPS|BOUND_ACTIVE"."""
        code = int(code)
        return "OK" if code == 0 else "|".join(f.name for f in cls if f.value and code & f.value)  # pyright: ignore[reportCallIssue, reportArgumentType]  (members have names)


FAILED = Status.DEGENERATE | Status.TOO_FEW_POINTS | Status.NONFINITE
"""Flags under which `converged` is False whatever the LM steps did."""


def status_flags(xp, opts, size, eps, conv, median_distance, n, degenerate, init_ok, finite, far, noise):
    """Per-problem `Status` flags (K,) int32 from the kernel outputs (numpy on the host, jnp when traced):
    sizes (K, 3), exponents (K, 2), converged (K,), the median distance of each problem's
    points (K,), their count n (K,), the degenerate / valid-start / finite / far-point flags (K,)."""
    lo, hi = opts.epsilon_range
    tol = 1e-3 * (hi - lo)
    bound = xp.any((eps <= lo + tol) | (eps >= hi - tol), -1)
    limit = 3.0 * noise if noise is not None else 0.02 * xp.mean(size, -1)
    flags = [
        (~conv, Status.MAX_STEPS),
        (bound, Status.BOUND_ACTIVE),
        (median_distance > limit, Status.LARGE_RESIDUAL),
        (degenerate | ~init_ok, Status.DEGENERATE),
        (n < NUM_PARAMS, Status.TOO_FEW_POINTS),
        (~finite, Status.NONFINITE),
        (far, Status.FAR_POINTS),
    ]
    status = xp.zeros(n.shape, xp.int32)
    for cond, flag in flags:
        status = status | xp.where(cond, int(flag), 0).astype(xp.int32)
    return status
