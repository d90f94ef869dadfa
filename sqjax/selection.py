"""Model selection (Leonardis): maximise F(m) = m^T Q m over presence variables m in {0, 1}^M.

Host side, numpy. `Q` comes from the regions, errors and parameter counts of the hypotheses (eqs. 1–4);
the paper's greedy solver picks, at each stage, the model whose addition raises F most.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from .hypotheses import mask_pairs


@dataclasses.dataclass(frozen=True)
class SelectionWeights:
    """K1 (benefit per explained point), K2 (cost per unit squared distance), K3 (cost per parameter).

    `SelectionWeights.for_threshold(tau)` sets K2 so that a point at the admission distance `tau` is
    worth half a point: K2 = K1 / (2 tau^2).
    """

    k1: float = 1.0
    k2: float = 1.0
    k3: float = 1.0

    @classmethod
    def for_threshold(cls, tau: float, k1: float = 1.0, k3: float = 1.0) -> SelectionWeights:
        return cls(k1, 0.5 * k1 / float(tau) ** 2, k3)


def build_q(regions, sq_dist, num_params, weights: SelectionWeights) -> np.ndarray:
    """The symmetric (M, M) matrix Q of eqs. 2–4.

    **Arguments:** `regions` (M, P) bool (R_i over P data points); `sq_dist` the squared eq. 10
    distances d_i^2, either (M, P) (used only inside R_i) or a list of M arrays, the i-th holding
    d_i^2 of R_i's points in index order (`np.flatnonzero(regions[i])`); `num_params` (M,) N_i.
    """
    from scipy import sparse  # here: its import is paid by the first selection, not by `sqjax --help`

    regions = np.asarray(regions, bool)
    M, P = regions.shape
    # Regions are sparse (a few hundred of P points each): the overlaps as sparse products cost the
    # sum over points of (models covering it)^2, not M^2 P (5.6x faster than dense on mOSD scenes).
    model, point = mask_pairs(regions)  # row-major: each model's points in index order, as sq_dist
    if isinstance(sq_dist, np.ndarray) and sq_dist.ndim == 2:
        d = sq_dist[model, point].astype(np.float64)
    else:
        d = np.concatenate([np.asarray(x, np.float64).ravel() for x in sq_dist]) if M else np.zeros(0)
    n = np.bincount(model, minlength=M).astype(np.float64)
    xi = np.bincount(model, d, minlength=M)
    B = sparse.csr_matrix((np.ones(model.size), (model, point)), shape=(M, P))
    D = sparse.csr_matrix((d, (model, point)), shape=(M, P))
    overlap = (B @ B.T).toarray()  # |R_i ∩ R_j| (its diagonal is not used)
    s = (D @ B.T).toarray()  # s_ij = sum over R_i ∩ R_j of d_i^2
    xi_ij = np.maximum(s, s.T)  # eq. 4
    Q = (-weights.k1 * overlap + weights.k2 * xi_ij) / 2.0  # eq. 3
    np.fill_diagonal(Q, weights.k1 * n - weights.k2 * xi - weights.k3 * np.asarray(num_params, np.float64))  # eq. 2
    return Q


def objective(Q: np.ndarray, m: np.ndarray) -> float:
    """F(m) = m^T Q m."""
    m = np.asarray(m, np.float64)
    return float(m @ Q @ m)


def select_greedy(Q: np.ndarray) -> np.ndarray:
    """The paper's greedy solver: add the model with the largest gain while some gain is positive.

    Returns the (M,) bool presence vector. Ties break towards the lower index (deterministic).
    """
    M = Q.shape[0]
    m = np.zeros(M, bool)
    gain = np.diag(Q).copy()  # gain of adding i to the empty set
    for _ in range(M):
        cand = np.where(m, -np.inf, gain)
        i = int(np.argmax(cand))
        if not cand[i] > 0:
            break
        m[i] = True
        gain += 2.0 * Q[:, i]  # adding i changes every other gain by 2 c_ji
    return m


def improve_local(Q: np.ndarray, m: np.ndarray, max_rounds: int = 100) -> np.ndarray:
    """Local search from `m`: apply the best single flip (add or drop) or swap while F increases."""
    m = m.copy()
    for _ in range(max_rounds):
        x = m.astype(np.float64)
        lin = Q @ x
        # flip i: delta = (1 - 2 x_i) (2 lin_i - 2 Q_ii x_i + Q_ii)
        flip = (1 - 2 * x) * (2 * lin - 2 * np.diag(Q) * x + np.diag(Q))
        best_i = int(np.argmax(flip))
        best = flip[best_i]
        swap = None
        on, off = np.nonzero(m)[0], np.nonzero(~m)[0]
        if on.size and off.size:
            # swap (drop a, add b): flip a then b
            da = flip[on][:, None]
            # after dropping a, the gain of adding b changes by -2 Q_ab
            db = flip[off][None, :] - 2 * Q[np.ix_(on, off)]
            tot = da + db
            a, b = np.unravel_index(int(np.argmax(tot)), tot.shape)
            if tot[a, b] > best:
                best, swap = tot[a, b], (on[a], off[b])
        if not best > 1e-9 * max(1.0, abs(objective(Q, m))):
            break
        if swap is None:
            m[best_i] = ~m[best_i]
        else:
            m[swap[0]], m[swap[1]] = False, True
    return m


def select_exact(Q: np.ndarray, max_models: int = 16) -> np.ndarray:
    """Exhaustive maximisation of m^T Q m (only for M <= `max_models`)."""
    M = Q.shape[0]
    if M > max_models:
        raise ValueError(f"select_exact: {M} models is too many for enumeration (max {max_models})")
    best, best_m = 0.0, np.zeros(M, bool)
    for chunk in _chunks(M):
        vals = np.einsum("bi,ij,bj->b", chunk, Q, chunk)
        k = int(np.argmax(vals))
        if vals[k] > best + 1e-9:
            best, best_m = vals[k], chunk[k].astype(bool)
    return best_m


def _chunks(M, size=4096):
    it = itertools.product((0.0, 1.0), repeat=M)
    while True:
        block = list(itertools.islice(it, size))
        if not block:
            return
        yield np.asarray(block)


SELECTORS = ("greedy", "local", "exact")


def select(Q: np.ndarray, method: str = "greedy") -> tuple[np.ndarray, dict]:
    """Select models: `method` in {"greedy" (the paper), "local" (greedy + local search), "exact"}.

    Returns the presence vector and stats: objective values, and whether greedy was worse than the
    returned solution (`greedy_gap` > 0).
    """
    greedy = select_greedy(Q)
    fg = objective(Q, greedy)
    if method == "greedy":
        m = greedy
    elif method == "local":
        m = improve_local(Q, greedy)
    elif method == "exact":
        m = select_exact(Q) if Q.shape[0] <= 16 else improve_local(Q, greedy)
    else:
        raise ValueError(f"select: method must be one of {SELECTORS}, got {method!r}")
    f = objective(Q, m)
    return m, {"objective": f, "greedy_objective": fg, "greedy_gap": f - fg}
