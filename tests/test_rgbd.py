"""RGB-D frames in: depth PNG + colour image + intrinsics JSON -> RangeImage with colours; PCD colours;
Open3D's depth-scale convention; reading failures that name the file (PNG bombs, Latin-1 OBJ)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from sqjax.formats import read_points, read_range_image, read_rgbd, write_range_image
from sqjax.rangeimage import PinholeCamera, RangeImage
from sqjax.rgbd import read_intrinsics

from helpers import data_path

CAM = PinholeCamera(50.0, 52.0, 15.5, 11.5)


def _frame(tmp_path, h=24, w=32):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 2.0, (h, w)).astype(np.float32)
    depth[0, :3] = np.nan
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    write_range_image(tmp_path / "depth.png", RangeImage(depth, CAM), depth_scale=1000)
    Image.fromarray(rgb).save(tmp_path / "color.png")
    return depth, rgb


@pytest.mark.parametrize("form", ["plain", "uois", "open3d", "K"])
def test_read_rgbd_with_intrinsics_json(tmp_path, form):
    depth, rgb = _frame(tmp_path)
    doc = {
        "plain": {"fx": CAM.fx, "fy": CAM.fy, "cx": CAM.cx, "cy": CAM.cy},
        "uois": {"img_width": 32, "img_height": 24, "fx": CAM.fx, "fy": CAM.fy, "x_offset": CAM.cx, "y_offset": CAM.cy},
        "open3d": {
            "width": 32,
            "height": 24,
            "intrinsic_matrix": [CAM.fx, 0, 0, 0, CAM.fy, 0, CAM.cx, CAM.cy, 1],
        },  # column-major
        "K": {"K": [[CAM.fx, 0, CAM.cx], [0, CAM.fy, CAM.cy], [0, 0, 1]]},
    }[form]
    (tmp_path / "cam.json").write_text(json.dumps(doc))
    img = read_rgbd(tmp_path / "depth.png", tmp_path / "color.png", intrinsics=tmp_path / "cam.json")
    assert img.camera == CAM
    assert np.nanmax(np.abs(img.depth - depth)) <= 0.0005 + 1e-6  # millimetres -> metres
    assert np.array_equal(img.valid, np.isfinite(depth))
    assert img.colors.dtype == np.uint8 and np.array_equal(img.colors, rgb)
    assert np.array_equal(img.subsample(2).colors, rgb[::2, ::2])


def test_read_rgbd_errors_name_the_file(tmp_path):
    _frame(tmp_path)
    (tmp_path / "cam.json").write_text(json.dumps({"width": 64, "height": 48, "fx": 1, "fy": 1, "cx": 0, "cy": 0}))
    with pytest.raises(ValueError, match=r"depth\.png.*32x24.*64x48"):
        read_rgbd(tmp_path / "depth.png", intrinsics=tmp_path / "cam.json")
    (tmp_path / "bad.json").write_text('{"fx": 1}')
    with pytest.raises(ValueError, match=r"bad\.json.*fx, fy, cx, cy"):
        read_intrinsics(tmp_path / "bad.json")
    Image.fromarray(np.zeros((5, 5, 3), np.uint8)).save(tmp_path / "small.png")
    with pytest.raises(ValueError, match=r"small\.png.*5x5"):
        read_rgbd(tmp_path / "depth.png", tmp_path / "small.png", camera=CAM)


def test_uois_realsense_frame(tmp_path):
    """A real RealSense frame (the UOIS pickles, unpacked here) with its camera_params.json."""
    folder = data_path("uois_realsense_tabletop")
    frame = np.load(folder / "image_0000.npy", allow_pickle=True).item()  # trusted test data
    Image.fromarray(frame["depth"]).save(tmp_path / "depth.png")
    Image.fromarray(frame["rgb"]).save(tmp_path / "rgb.png")
    img = read_rgbd(tmp_path / "depth.png", tmp_path / "rgb.png", intrinsics=folder / "camera_params.json")
    assert img.shape == (480, 640) and img.camera.fx == pytest.approx(612.937)
    assert 0.2 < np.nanmedian(img.depth) < 3.0  # metres
    assert np.array_equal(img.colors, frame["rgb"])


def test_depth_scale_below_one_is_the_old_convention(tmp_path):
    _frame(tmp_path)
    with pytest.raises(ValueError, match=r"Open3D.*pass 1000"):
        read_range_image(tmp_path / "depth.png", camera=CAM, depth_scale=0.001)


def _pcd_with_rgb(path, h=4, w=5):
    rng = np.random.default_rng(1)
    xyz = np.stack(np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)), -1)
    xyz = np.concatenate([xyz.reshape(-1, 2) * 0.01, np.full((h * w, 1), 1.0, np.float32)], 1)
    rgb = rng.integers(0, 256, (h * w, 3), dtype=np.uint32)
    packed = ((rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]).astype(np.uint32)
    rec = np.empty(h * w, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["rgb"] = packed.view(np.float32)  # PCL stores rgb as a float holding the packed bytes
    path.write_bytes(
        (
            f"VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {w}\n"
            f"HEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {h * w}\nDATA binary\n"
        ).encode()
        + rec.tobytes()
    )
    return rgb.astype(np.uint8).reshape(h, w, 3)


def test_organised_pcd_rgb_becomes_colors(tmp_path):
    rgb = _pcd_with_rgb(tmp_path / "c.pcd")
    img = read_range_image(tmp_path / "c.pcd", camera=CAM)
    assert np.array_equal(img.colors, rgb)
    write_range_image(tmp_path / "c.npz", img)  # npz keeps them
    assert np.array_equal(read_range_image(tmp_path / "c.npz").colors, rgb)


def test_real_pcd_with_rgba_reads(tmp_path):
    pts = read_points(data_path("pcl_test_clouds", "milk_color.pcd"))
    assert pts.shape[1] == 3 and len(pts) > 1000


# ----------------------------------------------------------------------------------------------------
# failures that must name the file


@pytest.mark.parametrize("factor", [1.5, 3.0])  # PIL warns above MAX_IMAGE_PIXELS, raises above twice that
def test_png_decompression_bomb_is_a_clear_error(tmp_path, monkeypatch, factor):
    from PIL import Image as PILImage

    Image.fromarray(np.ones((20, 20), np.uint16)).save(tmp_path / "bomb.png")
    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", int(400 / factor))
    with pytest.raises(ValueError, match=r"bomb\.png.*decompression bomb"):
        read_range_image(tmp_path / "bomb.png", camera=CAM)


def test_latin1_obj_reads(tmp_path):
    text = "# mod\u00e8le \u00e9crit en Latin-1\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n"
    (tmp_path / "m.obj").write_bytes(text.encode("latin-1"))
    pts = read_points(tmp_path / "m.obj")
    assert pts.shape == (4, 3)


def test_real_mosd_pcd_keeps_its_rgba():
    folder = data_path("mosd", "test")
    image = read_range_image(sorted(folder.glob("*.pcd"))[0])
    assert image.colors is not None and image.colors.shape == image.shape + (3,)
    assert 50 < image.colors.mean() < 230 and image.colors.std() > 10  # a real photo, not zeros


def test_intrinsics_from_sqjax_json(tmp_path):
    """`sqjax render --json` and a result's models.json carry the camera: --intrinsics reads them, size included."""
    _frame(tmp_path)
    doc = {"version": 1, "image_size": [24, 32], "camera": {"model": "pinhole", **vars(CAM)}, "parts": []}
    (tmp_path / "render.json").write_text(json.dumps(doc))
    assert read_rgbd(tmp_path / "depth.png", intrinsics=tmp_path / "render.json").camera == CAM
    (tmp_path / "other.json").write_text(json.dumps({**doc, "image_size": [48, 64]}))
    with pytest.raises(ValueError, match=r"depth\.png.*32x24.*64x48"):
        read_rgbd(tmp_path / "depth.png", intrinsics=tmp_path / "other.json")
    ortho = {**doc, "camera": {"model": "orthographic", "pixel_size": 0.01, "cx": 15.5, "cy": 11.5}}
    (tmp_path / "ortho.json").write_text(json.dumps(ortho))
    with pytest.raises(ValueError, match=r"ortho\.json.*orthographic, not pinhole.*--ortho"):
        read_intrinsics(tmp_path / "ortho.json")
    (tmp_path / "cloud.json").write_text(json.dumps({**doc, "image_size": None, "camera": None}))
    with pytest.raises(ValueError, match=r"cloud\.json: a point cloud's result, with no camera"):
        read_intrinsics(tmp_path / "cloud.json")
