"""Evaluation: Hoover region scores on hand-made label images, volume IoU, explained pixels, parameter errors."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sqjax import Superquadric
from sqjax.evaluate import (
    bounding_box,
    explained_fraction,
    hoover,
    model_distances,
    parameter_errors,
    volume_iou,
    volume_iou_batch,
)
from sqjax.mesh import surface_grid
from sqjax.scenes import paper_scene


def _five_regions():
    """Truth: five 4x5 regions side by side. Found: one of each Hoover category.

    truth 1 -> found 1 (18 px): correct; truth 2 -> found 2 (8 px) + found 3 (10 px): over-segmented;
    truth 3 + truth 4 -> found 4: under-segmented; truth 5 -> nothing: missed; found 6 (2 px in truth 1,
    2 px in truth 2): noise.
    """
    truth = np.zeros((4, 25), np.int32)
    for k in range(5):
        truth[:, 5 * k : 5 * k + 5] = k + 1
    found = np.zeros_like(truth)
    found[:, 0:5] = 1
    found[0, 3:7] = 6
    found[0:2, 5:10] = np.where(found[0:2, 5:10] == 0, 2, found[0:2, 5:10])
    found[2:4, 5:10] = 3
    found[:, 10:20] = 4
    return truth, found


def test_hoover_each_category():
    truth, found = _five_regions()
    s = hoover(truth, found)
    assert (s.correct, s.over, s.under, s.missed, s.noise) == (1, 1, 1, 1, 1)
    assert (s.n_truth, s.n_found) == (5, 5)
    assert s.correct_pairs == ((1, 1),)
    assert s.over_groups == ((2, (2, 3)),)
    assert s.under_groups == ((4, (3, 4)),)
    assert s.missed_ids == (5,) and s.noise_ids == (6,)
    assert s.correct_rate == pytest.approx(0.2) and s.noise_rate == pytest.approx(0.2)
    d = json.loads(json.dumps(s.to_dict()))
    assert d["correct"] == 1 and d["over_groups"] == [[2, [2, 3]]]


def test_hoover_identity_and_relabelling():
    truth, _ = _five_regions()
    relabelled = np.where(truth > 0, 10 * truth + 7, 0)
    s = hoover(truth, relabelled)
    assert s.correct == 5 and s.over == s.under == s.missed == s.noise == 0
    assert s.correct_pairs == tuple((k, 10 * k + 7) for k in range(1, 6))


def test_hoover_tolerance_boundary():
    """Truth region of 10 px, found region covering 8 of them: correct at T = 0.8 (>=), not above."""
    truth = np.ones((2, 5), np.int32)
    found = np.ones_like(truth)
    found[1, 3:] = 0
    assert hoover(truth, found, tolerance=0.8).correct == 1
    s = hoover(truth, found, tolerance=0.81)
    assert (s.correct, s.missed, s.noise) == (0, 1, 1)
    # a found region that spills over: O = 10, R = 12 -> needs T <= 10 / 12
    truth = np.concatenate([np.ones((2, 5)), 2 * np.ones((2, 5))], 1).astype(np.int32)
    found = np.where(truth == 1, 1, 2)
    found[0, 5:7] = 1
    assert hoover(truth, found, tolerance=10 / 12).correct_pairs[0] == (1, 1)
    assert (1, 1) not in hoover(truth, found, tolerance=10 / 12 + 0.01).correct_pairs


def test_hoover_over_needs_two_regions_and_ignore_mask():
    truth = np.ones((2, 10), np.int32)
    found = np.zeros_like(truth)
    found[:, :7] = 1  # one region with 70 %: neither correct nor over-segmentation
    s = hoover(truth, found)
    assert (s.correct, s.over, s.missed, s.noise) == (0, 0, 1, 1)
    ignore = np.zeros(truth.shape, bool)
    ignore[:, 7:] = True  # the unexplained pixels are left out: now a correct detection
    assert hoover(truth, found, ignore=ignore).correct == 1


def test_hoover_truth_zero_is_left_out():
    truth = np.zeros((3, 6), np.int32)
    truth[:, :3] = 1
    found = np.ones_like(truth)
    found[:, 3:] = 2  # found region 2 lies only where there is no ground truth
    s = hoover(truth, found)
    assert (s.correct, s.n_found, s.noise) == (1, 1, 0)
    with pytest.raises(ValueError):
        hoover(truth, found[:, :5])


BOX = Superquadric.create((0.5, 0.3, 0.4), (0.1, 0.1), euler=(0.3, 0.5, 0.2), translation=(1.0, 2.0, 3.0))


def test_volume_iou_identical_disjoint_shifted():
    assert volume_iou(BOX, BOX) == 1.0
    far = Superquadric.create((0.5, 0.3, 0.4), (0.1, 0.1), euler=(0.3, 0.5, 0.2), translation=(3.0, 2.0, 3.0))
    assert volume_iou(BOX, far) == 0.0
    # an axis-aligned box against itself shifted by half its width: IoU = (V / 2) / (3 V / 2) = 1 / 3
    box = Superquadric.create((0.5, 0.3, 0.4), (0.1, 0.1), translation=(0.0, 0.0, 5.0))
    shifted = Superquadric.create((0.5, 0.3, 0.4), (0.1, 0.1), translation=(0.5, 0.0, 5.0))
    assert volume_iou(box, shifted) == pytest.approx(1 / 3, abs=0.01)


def test_volume_iou_batch_matches_single():
    stack = lambda *ms: jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *ms)
    box = Superquadric.create((0.5, 0.3, 0.4), (0.1, 0.1), translation=(0.0, 0.0, 5.0))
    shifted = Superquadric.create((0.5, 0.3, 0.4), (0.1, 0.1), translation=(0.5, 0.0, 5.0))
    ball = Superquadric.create((0.25, 0.25, 0.25), (1.0, 1.0), translation=(0.0, 0.0, 5.0))
    a, b = stack(box, box, ball), stack(box, shifted, box)
    got = volume_iou_batch(a, b)
    assert got.shape == (3,) and got[0] == 1.0
    assert got[1] == volume_iou(box, shifted)
    # a ball inside the box: IoU = ball volume / box volume
    assert got[2] == pytest.approx(float(ball.volume / box.volume), abs=0.01)


def test_bounding_box_encloses_deformed_models():
    sq = Superquadric.create(
        (0.5, 0.3, 0.8),
        (0.3, 0.6),
        euler=(0.3, 1.0, -0.4),
        translation=(1.0, 0.0, 2.0),
        taper=(0.5, -0.7),
        bend=(0.8, 0.6),
    )
    lo, hi = (np.asarray(v) for v in bounding_box(sq))
    pts = surface_grid(sq, 32).reshape(-1, 3)
    assert (pts >= lo - 1e-5).all() and (pts <= hi + 1e-5).all()


def test_explained_fraction_on_a_rendered_scene():
    image, parts = paper_scene("sphere_cylinder", shape=(60, 80))
    d = model_distances(image.points, image.labels, parts)
    assert np.isfinite(d[image.valid]).all() and np.isnan(d[~image.valid]).all()
    assert explained_fraction(image.valid, image.labels, d, 1e-3) == 1.0
    labels = np.where(image.labels == 2, 0, image.labels)  # the cylinder left unexplained
    frac = explained_fraction(image.valid, labels, d, 1e-3)
    assert frac == pytest.approx((image.labels == 1).sum() / image.valid.sum())


def test_parameter_errors_axis_permutation():
    r = np.asarray(BOX.rotation)
    # axes 1 and 2 swapped (and the third flipped, to stay a rotation): the same solid
    same = Superquadric.create(
        (0.3, 0.5, 0.4), (0.1, 0.1), rotation=r[:, [1, 0, 2]] * [1, 1, -1], translation=(1.0, 2.0, 3.0)
    )
    e = parameter_errors(BOX, same, iou_samples=100_000)
    assert e["size_rel_error"] < 1e-6 and e["axes_permuted"] == 0.0 and e["centre_error"] < 1e-6
    assert e["volume_iou"] > 0.99
    bigger = Superquadric.create((0.55, 0.3, 0.4), (0.2, 0.1), rotation=r, translation=(1.0, 2.0, 3.1))
    e = parameter_errors(BOX, bigger, iou_samples=100_000)
    assert e["size_rel_error"] == pytest.approx(0.1 / 3, rel=1e-4)
    assert e["size_rel_error_max"] == pytest.approx(0.1, rel=1e-4)
    assert e["epsilon_abs_error"] == pytest.approx(0.05, rel=1e-4)
    assert e["centre_error"] == pytest.approx(0.1, rel=1e-4)
    assert 0.5 < e["volume_iou"] < 1.0
