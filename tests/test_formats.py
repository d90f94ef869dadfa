"""Tests for sqjax.formats: round trips, LZF / binary_compressed PCD, real data files, and clear errors."""

import json
import re
import struct

import numpy as np
import pytest

from sqjax.formats import read_points, read_range_image, write_points, write_range_image
from sqjax.pcd import fit_pinhole, lzf_decompress
from sqjax.rangeimage import OrthographicCamera, PinholeCamera, RangeImage

from helpers import data_path

CAM = PinholeCamera(50.0, 52.0, 15.5, 11.5)


# ------------------------------------------------------------------------------------------ helpers
def lzf_compress_literals(data: bytes) -> bytes:
    """The trivial valid LZF stream: literal runs of at most 32 bytes (control byte = run length - 1)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i : i + 32]
        out += bytes([len(chunk) - 1]) + chunk
    return bytes(out)


def lzf_compress_greedy(data: bytes) -> bytes:
    """A small LZF compressor with back references (incl. overlapping ones) to exercise the decoder."""
    out, lit, i, last = bytearray(), bytearray(), 0, {}

    def flush():
        for k in range(0, len(lit), 32):
            out.extend(bytes([len(lit[k : k + 32]) - 1]) + lit[k : k + 32])
        lit.clear()

    while i < len(data):
        ref = last.get(data[i : i + 3]) if i + 3 <= len(data) else None
        if i + 3 <= len(data):
            last[data[i : i + 3]] = i
        if ref is not None and 0 < i - ref <= 8192:
            n = 0
            while i + n < len(data) and n < 264 and data[ref + n] == data[i + n]:
                n += 1
            if n >= 3:
                flush()
                off, ln = i - ref - 1, n - 2
                if ln < 7:
                    out += bytes([(ln << 5) | (off >> 8), off & 0xFF])
                else:
                    out += bytes([(7 << 5) | (off >> 8), ln - 7, off & 0xFF])
                i += n
                continue
        lit.append(data[i])
        i += 1
    flush()
    return bytes(out)


def make_image(h=24, w=32, labels=True, camera=CAM, seed=0):
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.5, 3.0, (h, w)).astype(np.float32)
    depth[0, 0], depth[3, 5], depth[7, 2] = np.nan, 0.0, np.inf
    lab = rng.integers(0, 5, (h, w)) if labels else None
    return RangeImage(depth, camera, lab)


def pcd_header(fields, sizes, types, w, h, data, counts=None):
    counts = counts or [1] * len(fields)
    return (
        f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {' '.join(fields)}\n"
        f"SIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\nCOUNT {' '.join(map(str, counts))}\n"
        f"WIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {w * h}\nDATA {data}\n"
    ).encode()


def compressed_pcd(xyz, label, w, h, compress=lzf_compress_literals):
    """mOSD-style binary_compressed PCD: FIELDS label x y z rgba, stored column-wise."""
    n = w * h
    cols = [label.astype("<u4"), *(xyz[:, i].astype("<f4") for i in range(3)), np.zeros(n, "<u4")]
    raw = b"".join(c.tobytes() for c in cols)
    comp = compress(raw)
    head = pcd_header(["label", "x", "y", "z", "rgba"], [4] * 5, "U F F F U".split(), w, h, "binary_compressed")
    return head + struct.pack("<II", len(comp), len(raw)) + comp


def same(a, b):
    return np.array_equal(a, b, equal_nan=True)


# -------------------------------------------------------------------------------------------- LZF
@pytest.mark.parametrize("compress", [lzf_compress_literals, lzf_compress_greedy])
def test_lzf_round_trip(compress):
    rng = np.random.default_rng(1)
    data = bytes(rng.integers(0, 4, 5000, dtype=np.uint8)) + b"abc" * 400 + b"\0" * 1000 + rng.bytes(3000)
    comp = compress(data)
    assert lzf_decompress(comp, len(data)) == data
    if compress is lzf_compress_greedy:
        assert len(comp) < 0.8 * len(data)  # back references were used


def test_lzf_overlapping_and_long_back_references():
    # literal "ab", then copy 9 bytes from 2 back (overlapping), then 3 bytes from 1 back
    stream = bytes([1]) + b"ab" + bytes([7 << 5, 9 - 2 - 7, 1]) + bytes([1 << 5, 0])
    assert lzf_decompress(stream, 14) == b"ab" + b"ababababa" + b"aaa"


@pytest.mark.parametrize("stream,size", [(b"\x05ab", 6), (bytes([0x20, 0]), 3), (b"\x00a\x20", 3), (b"\x00a", 5)])
def test_lzf_corrupt(stream, size):
    with pytest.raises(ValueError, match="LZF stream corrupt"):
        lzf_decompress(stream, size)


# ------------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("camera", [CAM, OrthographicCamera(0.01, 3.0, 4.0)])
@pytest.mark.parametrize("labels", [True, False])
def test_npz_round_trip(tmp_path, camera, labels):
    img = make_image(camera=camera, labels=labels)
    write_range_image(tmp_path / "a.npz", img)
    back = read_range_image(tmp_path / "a.npz")
    assert back.camera == camera and same(back.depth, img.depth) and same(back.points, img.points)
    assert (back.labels is None) if not labels else np.array_equal(back.labels, img.labels)
    other = PinholeCamera(1.0, 1.0, 0.0, 0.0)
    assert read_range_image(tmp_path / "a.npz", camera=other).camera == other  # the argument wins


def test_npz_keeps_points_override(tmp_path):
    img = make_image()
    pts = img.points + 0.01  # not an exact projection
    img = RangeImage(img.depth, img.camera, img.labels, np.nan_to_num(pts))
    write_range_image(tmp_path / "a.npz", img)
    assert same(read_range_image(tmp_path / "a.npz").points, img.points)


def test_npy_needs_camera(tmp_path):
    depth = make_image().depth
    np.save(tmp_path / "d.npy", depth)
    assert same(read_range_image(tmp_path / "d.npy", camera=CAM).depth, depth)
    with pytest.raises(ValueError, match=r"d\.npy.*pass camera="):
        read_range_image(tmp_path / "d.npy")


@pytest.mark.parametrize("data", ["binary", "ascii"])
def test_pcd_round_trip(tmp_path, data):
    img = make_image()
    path = tmp_path / f"a_{data}.pcd"
    write_range_image(path, img, data=data)
    assert f"\nDATA {data}\n".encode() in path.read_bytes()[:400]
    back = read_range_image(path)  # intrinsics fitted from the organised cloud
    assert back.shape == img.shape and same(back.depth, img.depth) and np.array_equal(back.labels, img.labels)
    for k in ("fx", "fy", "cx", "cy"):
        assert getattr(back.camera, k) == pytest.approx(getattr(CAM, k), abs=1e-3)
    np.testing.assert_allclose(back.points, img.points, rtol=1e-6, equal_nan=True)
    assert read_range_image(path, camera=CAM).camera == CAM
    pts, lab = read_points(path, with_labels=True)
    assert pts.shape == (img.valid.sum(), 3) and np.array_equal(lab, img.labels[img.valid])


def test_pcd_without_labels_and_scale(tmp_path):
    img = make_image(labels=False)
    write_range_image(tmp_path / "a.pcd", img)
    back = read_range_image(tmp_path / "a.pcd", depth_scale=1000.0)  # Open3D: units per metre, divides
    assert back.labels is None
    np.testing.assert_allclose(back.depth, img.depth / 1000, rtol=1e-6, equal_nan=True)
    assert back.camera.fx == pytest.approx(CAM.fx, abs=1e-3)  # scaling xyz keeps the intrinsics


def test_png_round_trip_with_scale(tmp_path):
    img = make_image()
    write_range_image(tmp_path / "d.png", img, depth_scale=1000)
    back = read_range_image(tmp_path / "d.png", camera=CAM, depth_scale=1000)
    assert np.array_equal(back.valid, img.valid) and back.labels is None
    assert np.nanmax(np.abs(back.depth - img.depth)) <= 0.0005 + 1e-6
    raw = read_range_image(tmp_path / "d.png", camera=CAM)  # default: stored integers
    assert np.array_equal(raw.depth[img.valid], np.round(img.depth[img.valid] * 1000))


def test_png_depth_out_of_range(tmp_path):
    with pytest.raises(ValueError, match=r"d\.png.*do not fit"):
        write_range_image(tmp_path / "d.png", make_image(), depth_scale=1e5)


@pytest.mark.parametrize("ext", [".ply", ".xyz", ".txt", ".npy"])
def test_points_round_trip(tmp_path, ext):
    pts = np.random.default_rng(2).normal(size=(100, 3)) * 1e3
    write_points(tmp_path / f"p{ext}", pts)
    assert np.array_equal(read_points(tmp_path / f"p{ext}"), pts)


def test_points_text_variants_and_nan(tmp_path):
    (tmp_path / "a.txt").write_text("# x y z r g b\n1 2 3 255 0 0\n\n4\t5  6 1 1 1 \nnan 1 1 0 0 0\n")
    (tmp_path / "b.xyz").write_text("1,2,3\n4, 5, 6,7\n")
    assert np.array_equal(read_points(tmp_path / "a.txt"), [[1, 2, 3], [4, 5, 6]])
    assert np.array_equal(read_points(tmp_path / "b.xyz"), [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "e.txt").write_text("")
    assert read_points(tmp_path / "e.txt").shape == (0, 3)
    # a spreadsheet's CSV: one header row; and written back as CSV
    (tmp_path / "c.csv").write_text("x,y,z,intensity\n1,2,3,0.5\n4,5,6,0.1\n")
    assert np.array_equal(read_points(tmp_path / "c.csv"), [[1, 2, 3], [4, 5, 6]])
    for ext in (".xyz", ".txt"):  # the header of a space-separated file (the README allows it for all three)
        (tmp_path / f"h{ext}").write_text("x y z\n1 2 3\n4 5 6\n")
        assert np.array_equal(read_points(tmp_path / f"h{ext}"), [[1, 2, 3], [4, 5, 6]])
    pts = np.random.default_rng(0).normal(size=(5, 3))
    write_points(tmp_path / "w.csv", pts)
    assert "," in (tmp_path / "w.csv").read_text() and np.array_equal(read_points(tmp_path / "w.csv"), pts)
    (tmp_path / "bad.csv").write_text("x,y,z\n1,2\n")
    with pytest.raises(ValueError, match="3 numeric columns"):
        read_points(tmp_path / "bad.csv")


def test_read_input_keeps_every_row_of_a_cloud(tmp_path):
    """`read_points` drops NaN rows; `read_input` (what `sqjax segment` reads) keeps them, so that the
    labels of a cloud belong to the file's rows. A .npy of 3 to 7 columns is a cloud (x y z first)."""
    from sqjax.formats import read_input

    (tmp_path / "a.txt").write_text("1 2 3\nnan 0 0\n4 5 6\n")
    assert read_points(tmp_path / "a.txt").shape == (2, 3)
    pts, kind = read_input(tmp_path / "a.txt")
    assert kind == "point_cloud" and pts.shape == (3, 3) and np.isnan(pts[1, 0]) and pts[2, 0] == 4
    xyzrgb = np.random.default_rng(0).normal(size=(20, 6))
    np.save(tmp_path / "c.npy", xyzrgb)
    assert np.array_equal(read_input(tmp_path / "c.npy")[0], xyzrgb[:, :3])
    assert np.array_equal(read_points(tmp_path / "c.npy"), xyzrgb[:, :3])
    np.save(tmp_path / "d.npy", np.ones((20, 8)))  # 8 columns: a depth image, which needs a camera
    with pytest.raises(ValueError, match="stores no camera") as refused:
        read_input(tmp_path / "d.npy")
    assert "beside" not in str(refused.value)
    (tmp_path / "camera_params.json").write_text('{"fx": 1, "fy": 1, "cx": 0, "cy": 0}')  # as UOIS's folder
    with pytest.raises(ValueError, match=r"--intrinsics FILE\.json.*\(camera_params\.json is beside it\)"):
        read_input(tmp_path / "d.npy")
    frame = {"depth": np.ones((4, 5), np.float32), "rgb": np.zeros((4, 5, 3), np.uint8)}
    np.save(tmp_path / "f.npy", np.array(frame, dtype=object), allow_pickle=True)  # UOIS's pickled frames
    with pytest.raises(ValueError, match=r"f\.npy: holds an RGB-D frame .*not an \(N, 3\) point array"):
        read_points(tmp_path / "f.npy")
    np.save(tmp_path / "e.npy", np.ones((4, 5, 6)))  # neither: the shape is named, not the camera
    with pytest.raises(ValueError, match=r"e\.npy: holds an array of shape \(4, 5, 6\)"):
        read_input(tmp_path / "e.npy")
    # a cloud given a camera is still a cloud, not a depth image 3 pixels wide
    with pytest.raises(ValueError, match=r"c\.npy: --camera / --ortho apply to range images, and this is a point"):
        read_input(tmp_path / "c.npy", camera=PinholeCamera(150.0, 150.0, 80.0, 60.0))
    np.save(tmp_path / "t.npy", xyzrgb[:, :3].T)  # a transposed cloud is named as one
    with pytest.raises(ValueError, match=r"t\.npy: holds an array of shape \(3, 20\).*transposed cloud"):
        read_input(tmp_path / "t.npy")
    (tmp_path / "z.npy").write_bytes(b"")  # an empty file is said to be one, not a depth image without camera
    with pytest.raises(ValueError, match=r"z\.npy: not a NumPy \.npy file"):
        read_input(tmp_path / "z.npy")


def test_binary_compressed_pcd(tmp_path):
    h, w = 3, 4
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    z = np.linspace(1, 2, h * w).reshape(h, w)
    xyz = np.stack([(u - 1.5) * z / 10, (v - 1.0) * z / 11, z], -1).reshape(-1, 3)
    xyz[5] = np.nan
    label = np.arange(h * w) % 3
    label[5] = 0
    for compress in (lzf_compress_literals, lzf_compress_greedy):
        (tmp_path / "c.pcd").write_bytes(compressed_pcd(xyz, label, w, h, compress))
        img = read_range_image(tmp_path / "c.pcd")
        assert img.shape == (h, w) and img.valid.sum() == h * w - 1 and np.array_equal(img.labels.ravel(), label)
        np.testing.assert_allclose(img.points.reshape(-1, 3), xyz, rtol=1e-6, equal_nan=True)
        for k, ref in zip(("fx", "fy", "cx", "cy"), (10, 11, 1.5, 1.0)):
            assert getattr(img.camera, k) == pytest.approx(ref, abs=1e-4)
    # unorganised: not a range image, but fine as points
    (tmp_path / "u.pcd").write_bytes(compressed_pcd(xyz, label, h * w, 1))
    with pytest.raises(ValueError, match=r"u\.pcd.*unorganised.*read_points"):
        read_range_image(tmp_path / "u.pcd")
    pts, lab = read_points(tmp_path / "u.pcd", with_labels=True)
    assert pts.shape == (h * w - 1, 3) and np.array_equal(lab, np.delete(label, 5))


def test_organised_cloud_keeps_its_points(tmp_path):
    img = make_image(labels=False)
    jitter = np.random.default_rng(3).normal(0, 1e-3, img.points.shape)
    img = RangeImage(img.depth, CAM, None, np.nan_to_num(img.points + jitter))
    write_range_image(tmp_path / "j.pcd", img)
    back = read_range_image(tmp_path / "j.pcd", camera=CAM)
    np.testing.assert_allclose(back.points, img.points, rtol=1e-6, equal_nan=True)


def test_fit_pinhole_needs_points():
    with pytest.raises(ValueError, match="pass camera="):
        fit_pinhole(np.full((4, 4, 3), np.nan))


# ---------------------------------------------------------------------------------------- real data
MOSD = {  # file: (required labels, allowed labels) from mosd/README.md
    **{
        f: ({0, 1, 20, 30}, {0, 1, 20, 30, 31})
        for f in ("learn/learn0", "test/test0", "test/test5", "test/test10", "learn/learn25", "test/test24")
    },
    **{f: ({0, 1, 20, 30}, {0, 1, 20, 30, 40}) for f in ("learn/learn17", "test/test16", "test/test20")},
    **{
        f: ({0, 1, 20}, {0, *range(1, 10), *range(20, 62)})
        for f in ("learn/learn33", "test/test31", "test/test35", "test/test40")
    },
    "test/test44": ({0, 1, 20}, {0, *range(1, 10), *range(20, 61)}),
}


def test_mosd_listing_is_complete():
    """The clouds present are those the folder's SHA256SUMS lists (and include the ones checked below)."""
    listed = {
        line.split()[-1].lstrip("*").removeprefix("./").removesuffix(".pcd")
        for line in data_path("mosd", "SHA256SUMS").read_text().splitlines()
        if line.strip().endswith(".pcd")
    }
    present = {f"{p.parent.name}/{p.stem}" for p in data_path("mosd").glob("*/*.pcd")}
    assert present == listed and set(MOSD) <= present


@pytest.mark.parametrize("name", sorted(MOSD))
def test_mosd(name):
    img = read_range_image(data_path("mosd", name + ".pcd"))
    assert img.shape == (480, 640)
    required, allowed = MOSD[name]
    found = set(np.unique(img.labels).tolist())
    assert required <= found <= allowed, found
    assert not (img.labels[~img.valid]).any()  # invalid pixels carry label 0
    assert img.valid.sum() == np.isfinite(img.points_override[..., 2]).sum() > 100_000
    for k, ref in zip(("fx", "fy", "cx", "cy"), (525.0, 525.0, 319.5, 239.5)):
        assert getattr(img.camera, k) == pytest.approx(ref, abs=1e-2)
    np.testing.assert_allclose(img.points, img.camera.back_project(img.depth.astype(float)), atol=1e-5)


def test_mosd_as_points():
    pts, lab = read_points(data_path("mosd", "test", "test44.pcd"), with_labels=True)
    assert pts.shape == (172274, 3) and np.isfinite(pts).all() and lab.min() >= 1


@pytest.mark.parametrize(
    "name,intrinsics",
    [
        ("milk_cartoon_all_small_clorox.pcd", (525, 525, 319.5, 239.5)),
        ("grabber_frame_20121214T142255.814212.pcd", (525, 525, 320, 240)),
        ("table_scene_mug_stereo_textured.pcd", (964.4, 964.4, 319.8, 223.4)),
    ],
)
def test_pcl_test_clouds(name, intrinsics):
    img = read_range_image(data_path("pcl_test_clouds", name))
    assert img.shape == (480, 640) and img.labels is None and 0.5 < img.valid.mean() < 1
    for k, ref in zip(("fx", "fy", "cx", "cy"), intrinsics):
        assert getattr(img.camera, k) == pytest.approx(ref, abs=0.1)


def test_pcl_unorganised():
    path = data_path("pcl_test_clouds", "milk.pcd")
    with pytest.raises(ValueError, match="milk.pcd.*unorganised.*read_points"):
        read_range_image(path)
    assert read_points(path).shape == (13704, 3)


@pytest.mark.parametrize("name,n,nlabels", [("room1_gt_fine.pcd", 237907, 45), ("room2_gt_coarse.pcd", 123692, 14)])
def test_bobkov_labelled_points(name, n, nlabels):  # binary and ascii PCDs
    pts, lab = read_points(data_path("bobkov_indoor_parts", name), with_labels=True)
    assert pts.shape == (n, 3) and len(np.unique(lab)) == nlabels and 0.45 < (lab == 0).mean() < 0.5


@pytest.mark.parametrize(
    "folder,name,n",
    [
        ("robotology_find_superquadric", "box.txt", 1546),
        ("robotology_find_superquadric", "cylinder.txt", 3077),
        ("robotology_superquadric_lib", "example-drill.txt", 1432),  # 7 columns, trailing blanks
        ("pyvista_examples", "ant.ply", 486),
        ("ems_superquadric_examples", "multi_superquadrics/cat.ply", 6114),
    ],
)
def test_real_point_files(folder, name, n):
    pts = read_points(data_path(folder, name))
    assert pts.shape == (n, 3) and np.isfinite(pts).all() and np.ptp(pts, 0).max() > 0


def test_real_mesh_vertices():
    assert read_points(data_path("trimesh_models", "teapot.stl")).shape == (480, 3)  # distinct corners


def test_uois_pickled_npy(tmp_path):
    """The UOIS .npy files are pickled dicts of arrays (depth in mm, rgb): read without running any code
    the file names, equal to a trusted np.load, with their colours; also usable via npz / png."""
    folder = data_path("uois_realsense_tabletop")
    frame = np.load(folder / "image_0000.npy", allow_pickle=True).item()  # trusted test data
    depth_mm = frame["depth"]
    img = read_range_image(folder / "image_0000.npy", camera=CAM, depth_scale=1000)
    assert img.shape == (480, 640) and np.array_equal(img.colors, frame["rgb"])
    assert np.array_equal(np.where(img.valid, img.depth * 1000, 0).round(), depth_mm)
    p = json.loads((folder / "camera_params.json").read_text())
    cam = dict(fx=p["fx"], fy=p["fy"], cx=p["x_offset"], cy=p["y_offset"])
    np.savez(tmp_path / "u.npz", depth=depth_mm, **cam)
    img = read_range_image(tmp_path / "u.npz", depth_scale=1000)
    assert img.camera == PinholeCamera(**cam) and img.shape == (480, 640)
    assert img.valid.sum() == (depth_mm > 0).sum() and 0.85 < img.valid.mean() < 0.97
    assert 0.2 < np.nanmedian(img.depth) < 3.0  # metres
    write_range_image(tmp_path / "u.png", img, depth_scale=1000)
    back = read_range_image(tmp_path / "u.png", camera=img.camera, depth_scale=1000)
    assert same(back.depth, img.depth)


class _Payload:
    """Unpickling it would run code (create a file); a reader must refuse it, not run it."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_pickled_npy_that_names_code_is_refused_and_nothing_runs(tmp_path):
    marker = tmp_path / "ran"
    frame = {"depth": np.ones((4, 4), np.uint16), "hook": _Payload(marker)}
    np.save(tmp_path / "evil.npy", np.array(frame, dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"evil\.npy.*not only arrays"):
        read_range_image(tmp_path / "evil.npy", camera=CAM)
    assert not marker.exists()
    np.save(tmp_path / "ok.npy", np.array({"depth": np.full((4, 5), 2.0)}, dtype=object), allow_pickle=True)
    img = read_range_image(tmp_path / "ok.npy", camera=CAM)
    assert img.shape == (4, 5) and np.all(img.depth == 2.0) and img.colors is None


# ------------------------------------------------------------------------------------------- errors
GOOD = pcd_header(["x", "y", "z"], [4, 4, 4], "FFF", 2, 2, "binary") + np.zeros(12, "<f4").tobytes()
COMP_RAW = np.ones(12, "<f4").tobytes()


def _comp(stream, usize=48):
    head = pcd_header(["x", "y", "z"], [4] * 3, "FFF", 2, 2, "binary_compressed")
    return head + struct.pack("<II", len(stream), usize) + stream


CORRUPT = {
    "no_data.pcd": b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\n",
    "binary_garbage.pcd": bytes(range(256)) * 10,
    "no_fields.pcd": b"VERSION 0.7\nSIZE 4\nTYPE F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1\n",
    "sizes.pcd": pcd_header(["x", "y", "z"], [4, 4], "FFF", 2, 2, "ascii"),
    "type.pcd": pcd_header(["x", "y", "z"], [4, 4, 3], "FFF", 2, 2, "ascii"),
    "points.pcd": GOOD.replace(b"POINTS 4", b"POINTS 5"),
    "width.pcd": GOOD.replace(b"WIDTH 2", b"WIDTH two"),
    "kind.pcd": GOOD.replace(b"DATA binary", b"DATA zipped"),
    "truncated_binary.pcd": GOOD[:-5],
    "no_xyz.pcd": pcd_header(["a", "b", "c"], [4, 4, 4], "FFF", 2, 2, "ascii") + b"1 2 3\n" * 4,
    "short_ascii.pcd": pcd_header(["x", "y", "z"], [4, 4, 4], "FFF", 2, 2, "ascii") + b"1 2 3\n" * 3,
    "text_ascii.pcd": pcd_header(["x", "y", "z"], [4, 4, 4], "FFF", 2, 2, "ascii") + b"1 2 3\n1 2 x\n" * 2,
    "truncated_compressed.pcd": _comp(lzf_compress_literals(COMP_RAW))[:-10],
    "no_size_words.pcd": _comp(b"")[:-8] + b"\x01",
    "wrong_usize.pcd": _comp(lzf_compress_literals(COMP_RAW), usize=40),
    "lzf_bad_ref.pcd": _comp(b"\x00a" + bytes([0xE0, 40, 200]) + b"\x00" * 4),
    "lzf_short.pcd": _comp(lzf_compress_literals(COMP_RAW[:40])),
    "bad.npy": b"this is not numpy",
    "bad.npz": b"PK\x03\x04 not really a zip",
    "bad.png": b"\x89PNG\r\n\x1a\n" + b"\0" * 20,
    "bad.ply": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n",
}


@pytest.mark.parametrize("name", sorted(CORRUPT))
def test_corrupt_files(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(CORRUPT[name])
    reader = read_points if name.endswith(".ply") else lambda p: read_range_image(p, camera=CAM)
    with pytest.raises(ValueError, match=re.escape(str(path))):
        reader(path)


def test_corrupt_file_messages(tmp_path):
    cases = {
        "truncated_binary.pcd": "truncated",
        "lzf_bad_ref.pcd": "LZF stream corrupt",
        "points.pcd": "POINTS 5",
        "short_ascii.pcd": r"shape \(3, 3\)",
        "no_xyz.pcd": "no x y z",
        "bad.npy": "not a NumPy",
    }
    for name, msg in cases.items():
        (tmp_path / name).write_bytes(CORRUPT[name])
        with pytest.raises(ValueError, match=msg):
            read_range_image(tmp_path / name, camera=CAM)


def test_damaged_npz_and_npy(tmp_path):
    write_range_image(tmp_path / "a.npz", make_image())
    np.save(tmp_path / "a.npy", make_image().depth)
    good_npz, good_npy = (tmp_path / "a.npz").read_bytes(), (tmp_path / "a.npy").read_bytes()
    damaged = {"cut.npz": good_npz[:-100], "cut.npy": good_npy[:-100]}
    for start in (60, 200, 400, 1000):  # zeroed bytes inside the deflate stream / headers
        damaged[f"zero{start}.npz"] = good_npz[:start] + bytes(60) + good_npz[start + 60 :]
    for name, content in damaged.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=re.escape(str(tmp_path / name))):
            read_range_image(tmp_path / name, camera=CAM)


def test_bad_arrays(tmp_path):
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4)))
    np.save(tmp_path / "pts2.npy", np.zeros((5, 2)))
    np.savez(tmp_path / "nodepth.npz", d=np.zeros((2, 2)))
    np.savez(tmp_path / "halfcam.npz", depth=np.ones((2, 2)), fx=1.0, fy=1.0)
    np.savez(tmp_path / "badcam.npz", depth=np.ones((2, 2)), fx=-1.0, fy=1.0, cx=0.0, cy=0.0)
    np.savez(tmp_path / "labels.npz", depth=np.ones((2, 2)), labels=np.ones((3, 2)), pixel_size=1.0)
    np.save(tmp_path / "obj.npy", np.array([{"depth": 1}]), allow_pickle=True)
    from PIL import Image

    Image.new("RGB", (4, 4)).save(tmp_path / "rgb.png")
    cases = [
        ("cube.npy", "numeric \\(H, W\\)"),
        ("nodepth.npz", "no 'depth'"),
        ("halfcam.npz", "incomplete camera"),
        ("badcam.npz", "fx, fy must be finite"),
        ("labels.npz", "labels shape"),
        ("obj.npy", "pickled"),
        ("rgb.png", "not a 16-bit"),
    ]
    for name, msg in cases:
        with pytest.raises(ValueError, match=f"{name}.*{msg}"):
            read_range_image(tmp_path / name, camera=None if name.endswith(".npz") else CAM)
    with pytest.raises(ValueError, match=r"pts2\.npy.*\(N, 3\)"):
        read_points(tmp_path / "pts2.npy")
    # complex numbers would lose their imaginary part in the cast to float: refused, as by segment and fit
    np.save(tmp_path / "complex.npy", np.ones((30, 3), complex))
    np.save(tmp_path / "complex_depth.npy", np.ones((4, 4), complex))
    with pytest.raises(ValueError, match=r"complex\.npy.*real numeric \(N, 3\).*complex128"):
        read_points(tmp_path / "complex.npy")
    with pytest.raises(ValueError, match=r"complex_depth\.npy.*real numeric \(H, W\)"):
        read_range_image(tmp_path / "complex_depth.npy", camera=CAM)
    with pytest.raises(ValueError, match=r"real numeric \(N, 3\)"):
        write_points(tmp_path / "out.ply", np.ones((30, 3), complex))
    (tmp_path / "two.txt").write_text("1 2\n3 4\n")
    (tmp_path / "words.xyz").write_text("x y z\n1 2 3\nfour five six\n")  # a header row is fine, a later one not
    for name in ("two.txt", "words.xyz"):
        with pytest.raises(ValueError, match=f"{name}.*3 numeric columns"):
            read_points(tmp_path / name)


def test_unsupported_missing_and_wrong_kind(tmp_path):
    for fn in (read_range_image, read_points):
        with pytest.raises(ValueError, match=r"x\.tiff.*unsupported file extension"):
            fn(tmp_path / "x.tiff")
        with pytest.raises(FileNotFoundError, match="missing"):
            fn(tmp_path / "missing.pcd")
    for name in ("a.ply", "a.xyz", "a.txt"):
        with pytest.raises(ValueError, match=f"{name}.*not a range image.*read_points"):
            read_range_image(tmp_path / name)
    with pytest.raises(ValueError, match="a.stl.*mesh"):
        read_range_image(tmp_path / "a.stl")
    with pytest.raises(ValueError, match="a.npz.*read_range_image"):
        read_points(tmp_path / "a.npz")


def test_writer_errors(tmp_path):
    img = make_image()
    with pytest.raises(ValueError, match=r"a\.npy.*\.npz"):
        write_range_image(tmp_path / "a.npy", img)
    with pytest.raises(ValueError, match=r"a\.bmp.*unsupported"):
        write_range_image(tmp_path / "a.bmp", img)
    with pytest.raises(ValueError, match="'ascii' or 'binary'"):
        write_range_image(tmp_path / "a.pcd", img, data="binary_compressed")
    with pytest.raises(ValueError, match=r"p\.ply.*\(N, 3\)"):
        write_points(tmp_path / "p.ply", np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"p\.pcd.*cannot write"):
        write_points(tmp_path / "p.pcd", np.zeros((4, 3)))
    with pytest.raises(TypeError):
        write_range_image(tmp_path / "a.npz", img.depth)
    with pytest.raises(ValueError, match="depth_scale"):
        read_range_image(tmp_path / "a.npz", depth_scale=0)
