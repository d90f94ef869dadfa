"""How results are judged (METHOD.md §5): Hoover region scores, volume IoU, explained pixels, parameter errors.

Host side (numpy) except the volume-IoU kernel, which is one jitted, vmapped JAX call over pairs of models.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from .cache import kernel_jit
from .padding import bucket
from .superquadric import Superquadric, contains, distance

# ----------------------------------------------------------------------------------------------------
# Hoover et al. (1996) region classification


@dataclasses.dataclass(frozen=True)
class HooverScore:
    """Instance counts of Hoover et al. (1996) at one tolerance, with the regions behind each count.

    `correct` pairs, `over` truth regions split into >= 2 found regions, `under` found regions covering
    >= 2 truth regions, `missed` truth regions and `noise` found regions. Rates: correct, over and missed
    per truth region; under and noise per found region (NaN when there is none).
    """

    correct: int
    over: int
    under: int
    missed: int
    noise: int
    n_truth: int
    n_found: int
    tolerance: float
    correct_pairs: tuple[tuple[int, int], ...] = ()
    over_groups: tuple[tuple[int, tuple[int, ...]], ...] = ()
    under_groups: tuple[tuple[int, tuple[int, ...]], ...] = ()
    missed_ids: tuple[int, ...] = ()
    noise_ids: tuple[int, ...] = ()

    @staticmethod
    def _rate(k, n):
        return k / n if n else float("nan")

    @property
    def correct_rate(self) -> float:
        return self._rate(self.correct, self.n_truth)

    @property
    def over_rate(self) -> float:
        return self._rate(self.over, self.n_truth)

    @property
    def missed_rate(self) -> float:
        return self._rate(self.missed, self.n_truth)

    @property
    def under_rate(self) -> float:
        return self._rate(self.under, self.n_found)

    @property
    def noise_rate(self) -> float:
        return self._rate(self.noise, self.n_found)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["correct_pairs"] = [list(p) for p in self.correct_pairs]
        d["over_groups"] = [[m, list(ns)] for m, ns in self.over_groups]
        d["under_groups"] = [[n, list(ms)] for n, ms in self.under_groups]
        d["missed_ids"], d["noise_ids"] = list(self.missed_ids), list(self.noise_ids)
        rates = ("correct_rate", "over_rate", "under_rate", "missed_rate", "noise_rate")
        d.update({k: getattr(self, k) for k in rates})
        return d


def hoover(truth, found, *, tolerance: float = 0.8, ignore=None) -> HooverScore:
    """Classify regions as correct, over-, under-segmented, missed or noise (Hoover et al. 1996, PAMI 18(7)).

    **Arguments:**
    - `truth`, `found`: (H, W) int label images; label 0 is "no region" in both (in `truth` it marks
      pixels without ground truth, which are left out, as are pixels where `ignore` (H, W) bool is True).
      Found label 0 inside truth regions counts as unexplained: it is in M_m but in no found region.
    - `tolerance`: T in (0, 1], 0.8 by default; comparisons are `>=`.

    With O_mn the overlap of truth region m (M_m pixels) and found region n (R_n pixels): correct when
    O_mn >= T M_m and O_mn >= T R_n; over-segmentation of m into n_1..n_x (x >= 2) when every
    O_mn_i >= T R_n_i and sum_i O_mn_i >= T M_m; under-segmentation of n into m_1..m_x (x >= 2) when every
    O_m_i n >= T M_m_i and sum_i O_m_i n >= T R_n. Classified in this order, a region classified once is
    not used again; the rest of the truth regions are missed, the rest of the found regions noise.
    """
    truth, found = np.asarray(truth), np.asarray(found)
    if truth.shape != found.shape:
        raise ValueError(f"hoover: truth shape {truth.shape} != found shape {found.shape}")
    if not 0.0 < tolerance <= 1.0:
        raise ValueError(f"hoover: tolerance must be in (0, 1], got {tolerance}")
    use = truth > 0
    if ignore is not None:
        use &= ~np.asarray(ignore, bool)
    t, f = truth[use], found[use]
    tid, ti = np.unique(t, return_inverse=True)
    fid = np.unique(f[f > 0])
    fi = np.searchsorted(fid, f)  # valid only where f > 0
    M = np.bincount(ti, minlength=len(tid))
    R = np.bincount(fi[f > 0], minlength=len(fid))
    O = np.zeros((len(tid), len(fid)), np.int64)  # noqa: E741  (O_mn: the overlap matrix of Hoover et al.)
    np.add.at(O, (ti[f > 0], fi[f > 0]), 1)
    ge = lambda o, size: o >= tolerance * size * (1 - 1e-12) - 1e-9  # o >= T size, rounding-safe
    big_t = ge(O, M[:, None])  # O_mn >= T M_m
    big_f = ge(O, R[None, :])  # O_mn >= T R_n
    free_t, free_f = np.ones(len(tid), bool), np.ones(len(fid), bool)

    pairs = []
    for m, n in sorted(zip(*np.nonzero(big_t & big_f & (O > 0))), key=lambda mn: -O[mn]):
        if free_t[m] and free_f[n]:
            pairs.append((int(tid[m]), int(fid[n])))
            free_t[m] = free_f[n] = False
    over = []
    for m in np.nonzero(free_t)[0]:
        ns = np.nonzero(free_f & big_f[m] & (O[m] > 0))[0]
        if len(ns) >= 2 and ge(O[m, ns].sum(), M[m]):
            over.append((int(tid[m]), tuple(int(fid[n]) for n in ns)))
            free_t[m], free_f[ns] = False, False
    under = []
    for n in np.nonzero(free_f)[0]:
        ms = np.nonzero(free_t & big_t[:, n] & (O[:, n] > 0))[0]
        if len(ms) >= 2 and ge(O[ms, n].sum(), R[n]):
            under.append((int(fid[n]), tuple(int(tid[m]) for m in ms)))
            free_f[n], free_t[ms] = False, False
    missed = tuple(int(tid[m]) for m in np.nonzero(free_t)[0])
    noise = tuple(int(fid[n]) for n in np.nonzero(free_f)[0])
    return HooverScore(
        len(pairs),
        len(over),
        len(under),
        len(missed),
        len(noise),
        len(tid),
        len(fid),
        float(tolerance),
        tuple(pairs),
        tuple(over),
        tuple(under),
        missed,
        noise,
    )


# ----------------------------------------------------------------------------------------------------
# volume IoU (Monte Carlo, one jitted vmapped kernel)


def bounding_box(sq: Superquadric):
    """World-axis-aligned box (lo (3,), hi (3,)) enclosing one superquadric, tapering and bending included."""
    k = jnp.abs(sq.bend[..., 0])
    ex = sq.size[..., 0] * (1.0 + jnp.abs(sq.taper[..., 0]))
    ey = sq.size[..., 1] * (1.0 + jnp.abs(sq.taper[..., 1]))
    a3 = sq.size[..., 2]
    grow = 1.0 + k * jnp.hypot(ex, ey)  # |1/k - r| k <= 1 + k rho
    shift = jnp.minimum(0.5 * k * a3 * a3, 2.0 / jnp.maximum(k, 1e-12)) * grow  # (1/k - r)(1 - cos kz)
    half = jnp.stack([ex + shift, ey + shift, a3 * grow], -1)
    world = jnp.einsum("...ij,...j->...i", jnp.abs(sq.rotation), half)
    return sq.translation - world, sq.translation + world


def _iou_pair(a: Superquadric, b: Superquadric, u):
    lo_a, hi_a = bounding_box(a)
    lo_b, hi_b = bounding_box(b)
    lo, hi = jnp.minimum(lo_a, lo_b), jnp.maximum(hi_a, hi_b)
    pts = lo + u * (hi - lo)
    ia, ib = contains(a, pts), contains(b, pts)
    inter, union = jnp.sum(ia & ib), jnp.sum(ia | ib)
    return jnp.where(union > 0, inter / jnp.maximum(union, 1), 0.0)


@functools.partial(kernel_jit, static_argnames="n")
def _iou_kernel(a: Superquadric, b: Superquadric, key, n: int):
    u = jax.random.uniform(key, (n, 3), a.size.dtype)
    return jax.vmap(_iou_pair, in_axes=(0, 0, None))(a, b, u)


def volume_iou_batch(a: Superquadric, b: Superquadric, *, n: int = 100_000, seed: int = 0) -> np.ndarray:
    """Monte Carlo volume IoU of K pairs (leading axis K on both) -> (K,) numpy.

    `n` uniform points in the union of the two models' bounding boxes (the same unit samples for every
    pair), each tested with `contains`. Identical models give exactly 1, disjoint ones exactly 0.
    """
    b = jax.tree_util.tree_map(lambda x: x.astype(a.size.dtype), b)
    return np.asarray(_iou_kernel(a, b, jax.random.PRNGKey(seed), int(n)), float)


def volume_iou(a: Superquadric, b: Superquadric, *, n: int = 100_000, seed: int = 0) -> float:
    """Monte Carlo volume IoU of two superquadrics (see `volume_iou_batch`)."""
    expand = lambda s: jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], s)
    return float(volume_iou_batch(expand(a), expand(b), n=n, seed=seed)[0])


# ----------------------------------------------------------------------------------------------------
# explained pixels


def model_distances(points, labels, models) -> np.ndarray:
    """(H, W) distance (eq. 10) of each pixel's point to the model of its label (label i + 1 = models[i]).

    NaN where the label is 0 or the point is missing.
    """
    points, labels = np.asarray(points, float), np.asarray(labels)
    out = np.full(labels.shape, np.nan)
    for i, sq in enumerate(models):
        sel = (labels == i + 1) & np.isfinite(points).all(-1)
        n = int(sel.sum())
        if n:  # padded to a power of two so that few shapes are ever compiled
            pts = np.broadcast_to(np.asarray(sq.translation, float), (bucket(n, 256), 3)).copy()
            pts[:n] = points[sel]
            out[sel] = np.asarray(distance(sq, jnp.asarray(pts, sq.size.dtype)), float)[:n]
    return out


def explained_fraction(valid, labels, distances, threshold: float) -> float:
    """Fraction of the valid pixels that carry a model label (> 0) and lie within `threshold` of it.

    **Arguments:** `valid` (H, W) bool, `labels` (H, W) int (0 = no model), `distances` (H, W) float
    distance of each pixel to its model (e.g. `model_distances`; NaN counts as not explained).
    """
    valid = np.asarray(valid, bool)
    ok = valid & (np.asarray(labels) > 0) & (np.nan_to_num(np.asarray(distances, float), nan=np.inf) <= threshold)
    return float(ok.sum() / valid.sum()) if valid.any() else float("nan")


# ----------------------------------------------------------------------------------------------------
# parameter errors


def parameter_errors(truth: Superquadric, fit: Superquadric, *, iou_samples: int = 100_000) -> dict:
    """Errors of a fitted superquadric against the truth, resolving the axis-permutation symmetry.

    Fitted axes are matched to true axes by direction (the permutation maximising sum |cos|), so an
    equivalent model with its axes relabelled scores as the same model. Returns a dict of floats:
    `size_rel_error` (mean |a_fit - a_true| / a_true over matched axes), `size_rel_error_max`,
    `size_rel_error_sorted` (the same on sorted sizes, orientation-free), `epsilon_abs_error` (mean
    |e_fit - e_true|), `axes_permuted` (1.0 when the fit's z axis is not the true z axis: then its exponents
    describe other sections), `axis_angle_deg` (mean angle between matched axes), `centre_error`,
    `centre_rel_error` (over the largest true size) and `volume_iou`.
    """
    at, af = np.asarray(truth.size, float), np.asarray(fit.size, float)
    rt, rf = np.asarray(truth.rotation, float), np.asarray(fit.rotation, float)
    cos = np.abs(rt.T @ rf)  # (true axis, fitted axis)
    perm = max(itertools.permutations(range(3)), key=lambda p: cos[[0, 1, 2], list(p)].sum())
    perm = np.asarray(perm)
    rel = np.abs(af[perm] - at) / at
    ct, cf = np.asarray(truth.translation, float), np.asarray(fit.translation, float)
    angles = np.degrees(np.arccos(np.clip(cos[[0, 1, 2], perm], 0.0, 1.0)))
    return {
        "size_rel_error": float(rel.mean()),
        "size_rel_error_max": float(rel.max()),
        "size_rel_error_sorted": float((np.abs(np.sort(af) - np.sort(at)) / np.sort(at)).mean()),
        "epsilon_abs_error": float(np.abs(np.asarray(fit.epsilon, float) - np.asarray(truth.epsilon, float)).mean()),
        "axes_permuted": float(perm[2] != 2),
        "axis_angle_deg": float(angles.mean()),
        "centre_error": float(np.linalg.norm(cf - ct)),
        "centre_rel_error": float(np.linalg.norm(cf - ct) / at.max()),
        "volume_iou": volume_iou(truth, fit, n=iou_samples),
    }
