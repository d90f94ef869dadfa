"""The label palette shared by `labels.png`, the part meshes and the figures, and label images as PNG.

Distinct, colour-blind-aware first colours (Okabe-Ito and Tableau), then golden-angle hues; 0 (no label)
is black, valid pixels no model explains grey.
"""

from __future__ import annotations

import colorsys
from pathlib import Path

import numpy as np

_BASE = np.array(
    [
        (230, 159, 0),
        (86, 180, 233),
        (0, 158, 115),
        (213, 94, 0),
        (204, 121, 167),
        (0, 114, 178),
        (240, 228, 66),
        (148, 103, 189),
        (140, 86, 75),
        (188, 189, 34),
        (23, 190, 207),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (127, 127, 127),
        (31, 119, 180),
    ],
    np.uint8,
)

BACKGROUND = (0, 0, 0)
"""labels.png colour of pixels without data."""

UNEXPLAINED = (96, 96, 96)
"""labels.png colour of valid pixels that no part explains (label 0)."""


def label_colors(n: int) -> np.ndarray:
    """`(n, 3)` uint8 RGB colours of parts 1..n (row i is label i + 1); the same for every n (a prefix)."""
    n = int(n)
    if n < 0:
        raise ValueError(f"label_colors: n must be >= 0, got {n}")
    if n <= len(_BASE):
        return _BASE[:n].copy()
    extra = []
    for k in range(n - len(_BASE)):
        h = (0.11 + 0.618033988749895 * k) % 1.0
        s, v = (0.65, 0.95) if k % 2 == 0 else (0.9, 0.7)
        extra.append([round(255 * c) for c in colorsys.hsv_to_rgb(h, s, v)])
    return np.concatenate([_BASE, np.asarray(extra, np.uint8)])


def colorize_labels(labels, valid=None) -> np.ndarray:
    """Label image `(H, W)` int (0 = none) -> `(H, W, 3)` uint8 RGB with `label_colors`.

    Label 0 is `BACKGROUND` (black), or `UNEXPLAINED` (grey) where `valid` `(H, W)` bool is True.
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"colorize_labels: labels must be an (H, W) integer array, got {labels.dtype} {labels.shape}")
    if labels.size and labels.min() < 0:
        raise ValueError("colorize_labels: labels must be >= 0")
    n = int(labels.max()) if labels.size else 0
    lut = np.concatenate([np.array([BACKGROUND], np.uint8), label_colors(n)])
    rgb = lut[labels]
    if valid is not None:
        rgb[(labels == 0) & np.asarray(valid, bool)] = UNEXPLAINED
    return rgb


def labels_to_png(labels, path, valid=None) -> Path:
    """Write a label image `(H, W)` as an RGB PNG coloured by `label_colors` (see `colorize_labels`)."""
    from PIL import Image

    path = Path(path)
    Image.fromarray(colorize_labels(labels, valid)).save(path, format="PNG")
    return path


def labels_to_id_png(labels, path) -> Path:
    """Write a label image `(H, W)` as a 16-bit greyscale PNG of the label ids (0 = unlabelled)."""
    from PIL import Image

    labels = np.asarray(labels)
    if labels.ndim != 2 or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{path}: labels must be an (H, W) integer array, got {labels.dtype} {labels.shape}")
    if labels.size and (labels.min() < 0 or labels.max() > 65535):
        raise ValueError(f"{path}: label ids must lie in 0..65535 for a 16-bit PNG")
    path = Path(path)
    Image.fromarray(labels.astype(np.uint16)).save(path, format="PNG")
    return path
