"""Tests for sqjax.rangeimage: exact back-projection, missing pixels, crop / subsample, validation."""

import numpy as np
import pytest

from sqjax.rangeimage import OrthographicCamera, PinholeCamera, RangeImage, camera_from_dict

CAMERAS = {"pinhole": PinholeCamera(60.0, 58.0, 20.3, 14.7), "ortho": OrthographicCamera(0.01, 19.5, 14.5)}


def random_depth(h=30, w=40, seed=0):
    return np.random.default_rng(seed).uniform(0.5, 4.0, (h, w))


@pytest.mark.parametrize("name", CAMERAS)
def test_back_projection_is_exact(name):
    cam, depth = CAMERAS[name], random_depth()
    pts = cam.back_project(depth)
    assert pts.shape == depth.shape + (3,)
    uv, z = cam.project(pts)
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]]
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-9)
    np.testing.assert_array_equal(z, depth)
    np.testing.assert_allclose(RangeImage(depth, cam).points, pts, rtol=0, atol=0)


def test_back_projection_formulas():
    depth = random_depth()
    r, c = 7, 31
    p = CAMERAS["pinhole"].back_project(depth)[r, c]
    cam = CAMERAS["pinhole"]
    z = depth[r, c]
    np.testing.assert_allclose(p, [(c - cam.cx) * z / cam.fx, (r - cam.cy) * z / cam.fy, z])
    o, ortho = CAMERAS["ortho"].back_project(depth)[r, c], CAMERAS["ortho"]
    np.testing.assert_allclose(o, [(c - ortho.cx) * ortho.pixel_size, (r - ortho.cy) * ortho.pixel_size, depth[r, c]])


def _with_holes(dtype=np.float64):
    depth = random_depth().astype(dtype)
    holes = np.zeros(depth.shape, bool)
    for (r, c), value in zip([(0, 0), (3, 4), (10, 11), (29, 39)], [np.nan, 0.0, np.inf, -np.inf]):
        depth[r, c], holes[r, c] = value, True
    return depth, holes


@pytest.mark.parametrize("name", CAMERAS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_missing_pixels(name, dtype):
    depth, holes = _with_holes(dtype)
    img = RangeImage(depth, CAMERAS[name], labels=np.ones(depth.shape, int))
    assert img.depth.dtype == dtype
    np.testing.assert_array_equal(img.valid, ~holes)
    assert np.isnan(img.depth[holes]).all() and np.isfinite(img.depth[~holes]).all()
    assert np.isnan(img.points[holes][:, 2]).all() and np.isfinite(img.points[~holes]).all()
    assert (img.labels == 1).all()  # labels untouched


def test_missing_pixels_pinhole_points_all_nan():
    depth, holes = _with_holes()
    assert np.isnan(RangeImage(depth, CAMERAS["pinhole"]).points[holes]).all()


def test_missing_pixels_ortho_points_all_nan():
    depth, holes = _with_holes()
    assert np.isnan(RangeImage(depth, CAMERAS["ortho"]).points[holes]).all()


def test_missing_pixels_with_points_override():
    depth, holes = _with_holes()
    override = np.random.default_rng(1).normal(size=depth.shape + (3,))
    img = RangeImage(depth, CAMERAS["pinhole"], points_override=override)
    assert np.isnan(img.points[holes]).all()
    np.testing.assert_array_equal(img.points[~holes], override[~holes])


def test_integer_depth_is_float():
    img = RangeImage(np.array([[0, 1000], [65535, 7]], np.uint16), CAMERAS["pinhole"])
    assert img.depth.dtype == np.float32 and img.valid.sum() == 3


def _images():
    depth, _ = _with_holes()
    labels = np.arange(depth.size).reshape(depth.shape)
    for name, cam in CAMERAS.items():
        yield name, RangeImage(depth, cam, labels)
    override = CAMERAS["pinhole"].back_project(depth) + np.random.default_rng(2).normal(0, 0.01, depth.shape + (3,))
    yield "override", RangeImage(depth, CAMERAS["pinhole"], labels, np.nan_to_num(override))


def _check_same_pixels(part, whole, rows, cols):
    """part[i, j] must be whole[rows[i], cols[j]]: depth, labels and 3-D point."""
    sel = np.ix_(rows, cols)
    assert part.shape == (len(rows), len(cols))
    np.testing.assert_array_equal(part.depth, whole.depth[sel])
    np.testing.assert_array_equal(part.labels, whole.labels[sel])
    np.testing.assert_allclose(part.points, whole.points[sel], rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name,img", list(_images()), ids=[n for n, _ in _images()])
def test_crop_keeps_points(name, img):
    for r0, r1, c0, c1 in [(0, 30, 0, 40), (5, 17, 3, 40), (10, 11, 20, 21), (0, 100, 7, 200)]:
        part = img.crop(r0, r1, c0, c1)
        _check_same_pixels(part, img, np.arange(r0, min(r1, 30)), np.arange(c0, min(c1, 40)))


@pytest.mark.parametrize("name,img", list(_images()), ids=[n for n, _ in _images()])
def test_subsample_keeps_points(name, img):
    for step in (1, 2, 3, 7):
        _check_same_pixels(img.subsample(step), img, np.arange(0, 30, step), np.arange(0, 40, step))
    # crop then subsample, and subsample then crop
    _check_same_pixels(img.crop(3, 29, 5, 38).subsample(4), img, np.arange(3, 29, 4), np.arange(5, 38, 4))
    _check_same_pixels(img.subsample(3).crop(2, 8, 1, 9), img, np.arange(6, 24, 3), np.arange(3, 27, 3))


def test_crop_negative_start():
    img = RangeImage(random_depth(), CAMERAS["pinhole"], labels=np.zeros((30, 40)))
    _check_same_pixels(img.crop(-5, 30, 0, 40), img, np.arange(25, 30), np.arange(40))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(fx=0, fy=1, cx=0, cy=0),
        dict(fx=1, fy=-2, cx=0, cy=0),
        dict(fx=np.nan, fy=1, cx=0, cy=0),
        dict(fx=np.inf, fy=1, cx=0, cy=0),
        dict(fx=1, fy=1, cx=np.nan, cy=0),
        dict(fx=1, fy=1, cx=0, cy=np.inf),
    ],
)
def test_bad_pinhole(kwargs):
    with pytest.raises(ValueError, match="PinholeCamera"):
        PinholeCamera(**kwargs)


@pytest.mark.parametrize("pixel_size", [0.0, -0.1, np.nan, np.inf])
def test_bad_orthographic(pixel_size):
    with pytest.raises(ValueError, match="OrthographicCamera"):
        OrthographicCamera(pixel_size)


@pytest.mark.parametrize(
    "depth",
    [
        np.ones(5),
        np.ones((2, 3, 4)),
        np.ones((0, 4)),
        np.ones((4, 0)),
        np.float64(1.0),
        np.array([["a", "b"], ["c", "d"]]),
        np.ones((2, 2), bool),
        np.ones((2, 2), complex),
    ],
)
def test_bad_depth(depth):
    with pytest.raises(ValueError, match="RangeImage: depth"):
        RangeImage(depth, CAMERAS["pinhole"])


def test_negative_depths_are_refused_by_a_pinhole_camera_only():
    """A negative depth back-projected through a pinhole lands behind the camera, mirrored; it was
    accepted silently. An orthographic image's depth is a z coordinate (negative is fine), and an
    organised cloud's own points (`points_override`) are used as given."""
    depth = random_depth()
    depth[3, 4], depth[5, 6] = -1.0, np.nan
    with pytest.raises(ValueError, match="RangeImage: 1 of 1200 depths are negative"):
        RangeImage(depth, CAMERAS["pinhole"])
    assert RangeImage(depth, CAMERAS["ortho"]).points[3, 4, 2] == -1.0
    pts = CAMERAS["pinhole"].back_project(np.abs(depth))
    assert RangeImage(depth, CAMERAS["pinhole"], points_override=pts).valid.sum() == 1199


def test_bad_labels_points_and_step():
    cam = CAMERAS["pinhole"]
    with pytest.raises(ValueError, match="labels shape"):
        RangeImage(np.ones((3, 4)), cam, labels=np.ones((4, 3)))
    with pytest.raises(ValueError, match="points shape"):
        RangeImage(np.ones((3, 4)), cam, points_override=np.ones((3, 4, 2)))
    with pytest.raises(ValueError, match="step"):
        RangeImage(np.ones((3, 4)), cam).subsample(0)
    with pytest.raises(ValueError, match="non-empty"):
        RangeImage(np.ones((3, 4)), cam).crop(3, 5, 0, 4)


@pytest.mark.parametrize("name", CAMERAS)
def test_camera_dict_round_trip(name):
    cam = CAMERAS[name]
    assert camera_from_dict(cam.to_dict()) == cam
