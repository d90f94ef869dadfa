"""The set of hypotheses on the host: parameters, regions and the distances of their points.

A hypothesis is a superquadric theta (11,) (in the workspace's centred frame, `chart`), the region of
points it explains (within tau), and the eq. 10 distances of those points. Regions are (M, P) bool; the
kernels take (model, point) pairs (`pairs`), and their per-pair outputs come back split by model
(`split_by_model`).
"""

from __future__ import annotations

import numpy as np

from .chart import NUM_PARAMS


def pairs(regions: list):
    """Index arrays (one per hypothesis) -> (model, point) pairs, as `np.nonzero` of the masks gives."""
    sizes = np.array([r.size for r in regions], np.int64)
    return np.repeat(np.arange(len(regions)), sizes), np.concatenate(regions) if regions else np.zeros(0, np.int64)


def mask_pairs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the True entries of a 2-D bool mask, row-major, as `np.nonzero` gives them:
    14x faster on a (400, 19200) mask of regions (1.1 against 15.6 ms), where `np.nonzero` pays for
    its n-dimensional walk."""
    return np.divmod(np.flatnonzero(mask), mask.shape[1])


def split_by_model(values, model, k):
    """Values (E,) of pairs sorted by model -> list of k arrays, one per model."""
    return np.split(values, np.cumsum(np.bincount(model, minlength=k))[:-1])


class Models:
    """The hypotheses on the host: parameters theta (M, 11), regions (M, P) bool, and for each model
    the eq. 10 distances of its region's points (`dist[i]` aligned with `np.flatnonzero(regions[i])`,
    float32); flags `active` (still growing) and `loose` (admission at admit_factor * tau), and
    `failed_at`, the region's size when a step in the other admission than `loose` last failed (-1: none)."""

    def __init__(self, theta, regions, dist):
        self.theta, self.regions, self.dist = theta, regions, list(dist)
        self.active = np.ones(len(theta), bool)
        self.loose = np.ones(len(theta), bool)
        self.failed_at = np.full(len(theta), -1, np.int64)

    def concat(self, other: Models) -> Models:
        """These hypotheses followed by `other`'s, flags included."""
        out = Models(
            np.concatenate([self.theta, other.theta]),
            np.concatenate([self.regions, other.regions]),
            self.dist + other.dist,
        )
        out.active = np.concatenate([self.active, other.active])
        out.loose = np.concatenate([self.loose, other.loose])
        out.failed_at = np.concatenate([self.failed_at, other.failed_at])
        return out

    @classmethod
    def empty(cls, P: int) -> Models:
        """No hypothesis, over P points."""
        return cls(np.zeros((0, NUM_PARAMS)), np.zeros((0, P), bool), [])

    def take(self, keep):
        """Keep the hypotheses `keep` (a bool mask or indices, in that order), in place."""
        keep = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep)
        self.dist = [self.dist[i] for i in keep]
        for name in ("theta", "regions", "active", "loose", "failed_at"):
            setattr(self, name, getattr(self, name)[keep])
