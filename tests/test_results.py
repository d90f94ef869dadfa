"""Results written by `write_segmentation` and read back: models.json round trip, labels_id.png, glTF Y-up,
batched meshing, and the safety of the writes (atomic, no symlink following, writability checked first).

No segmentation runs here: a small stand-in `Segmentation` of known superquadrics is written.
"""

from __future__ import annotations

import json
import os
import types

import numpy as np
import pytest
import trimesh
from PIL import Image

from sqjax import export
from sqjax.export import GLTF_FROM_CAMERA, parts_to_scene, read_segmentation, write_segmentation
from sqjax.files import atomic_paths, check_writable_dir
from sqjax.rangeimage import PinholeCamera, RangeImage
from sqjax.superquadric import Superquadric


def _sqs():
    return [
        Superquadric.create((0.2, 0.1, 0.15), (0.5, 0.8), euler=(0.3, 0.6, -0.4), translation=(0.1, -0.2, 2.0)),
        Superquadric.create((0.1, 0.1, 0.3), (1.0, 1.0), euler=(0.0, 1.2, 0.2), translation=(-0.3, 0.1, 2.5)),
    ]


def _fake():
    """(segmentation stand-in, RangeImage) with two parts and a 12 x 16 label image."""
    labels = np.zeros((12, 16), np.int32)
    labels[2:6, 2:8], labels[6:10, 8:14] = 1, 2
    parts = [
        types.SimpleNamespace(
            superquadric=sq,
            region=np.flatnonzero(labels == i + 1),
            error=0.01 * (i + 1),
            num_points=int((labels == i + 1).sum()),
            num_explained=int((labels == i + 1).sum()),
        )
        for i, sq in enumerate(_sqs())
    ]
    seg = types.SimpleNamespace(
        parts=parts,
        labels=labels,
        history=[],
        noise=0.002,
        threshold=0.006,
        timings={"total": 1.0, "compile": 0.5, "run": 0.5},
        stats={"seeds": 4},
    )
    depth = np.full((12, 16), 2.0, np.float32)
    depth[0] = np.nan
    return seg, RangeImage(depth, PinholeCamera(20.0, 20.0, 7.5, 5.5))


def _close(a: Superquadric, b: Superquadric):
    for f in ("size", "epsilon", "rotation", "translation", "taper", "bend"):
        np.testing.assert_allclose(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)), atol=1e-5, err_msg=f)


# ----------------------------------------------------------------------------------------------------
# reading back


def test_models_json_round_trip(tmp_path):
    seg, image = _fake()
    written = write_segmentation(seg, image, tmp_path / "out", figure=False)
    assert {"models.json", "labels.npy", "labels.png", "labels_id.png", "parts.glb", "parts.ply"} <= written.keys()
    back = read_segmentation(tmp_path / "out")
    assert len(back.superquadrics) == 2 and back.camera == image.camera
    for a, b in zip(back.superquadrics, _sqs()):
        _close(a, b)
    assert np.array_equal(back.labels, seg.labels)
    assert [p["label"] for p in back.parts] == [1, 2]


def test_superquadric_from_dict_takes_euler_or_rotation_and_ignores_extras():
    sq = _sqs()[0]
    d = {**sq.to_dict(), "label": 3, "color": [1, 2, 3], "num_points": 10}
    _close(Superquadric.from_dict(d), sq)
    d.pop("rotation")  # euler_zyz only
    _close(Superquadric.from_dict(d), sq)
    with pytest.raises(ValueError, match="size"):
        Superquadric.from_dict({"epsilon": [1, 1]})
    with pytest.raises(ValueError, match="translation"):
        Superquadric.from_dict({"size": [1, 1, 1], "translation": [0, 0]})


def test_read_segmentation_errors_name_the_file(tmp_path):
    (tmp_path / "models.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"models\.json.*JSON object"):
        read_segmentation(tmp_path)
    (tmp_path / "models.json").write_text('{"parts": [{"size": [1, "x", 1]}]}')
    with pytest.raises(ValueError, match=r"models\.json: part 1"):
        read_segmentation(tmp_path)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        read_segmentation(tmp_path / "nowhere")


def test_labels_id_png_is_16_bit_ids(tmp_path):
    seg, image = _fake()
    write_segmentation(seg, image, tmp_path, figure=False)
    with Image.open(tmp_path / "labels_id.png") as im:
        ids = np.asarray(im)
    assert ids.dtype == np.uint16 and np.array_equal(ids, seg.labels)


# ----------------------------------------------------------------------------------------------------
# meshes


def test_gltf_is_y_up_and_ply_camera_frame(tmp_path):
    seg, image = _fake()
    write_segmentation(seg, image, tmp_path, figure=False)
    glb = trimesh.load(tmp_path / "parts.glb")
    camera = parts_to_scene(seg.parts)  # camera frame (y down, z forward)
    # the part centres: z forward (positive) in the camera frame, toward -z (in front of a glTF viewer)
    centre_glb = glb.dump(concatenate=True).bounds.mean(0)
    centre_cam = camera.dump(concatenate=True).bounds.mean(0)
    np.testing.assert_allclose(centre_glb, centre_cam * [1, -1, -1], atol=1e-4)
    assert centre_cam[2] > 0 and centre_glb[2] < 0
    ply = trimesh.load(tmp_path / "parts.ply")
    np.testing.assert_allclose(ply.bounds.mean(0), centre_cam, atol=1e-4)
    assert np.allclose(GLTF_FROM_CAMERA[:3, :3] @ GLTF_FROM_CAMERA[:3, :3], np.eye(3))


def test_parts_to_scene_meshes_a_batched_superquadric():
    sqs = _sqs()
    import jax

    batched = jax.tree_util.tree_map(lambda *x: np.stack(x), *sqs)
    scene = parts_to_scene(batched, resolution=12)
    assert sorted(scene.geometry) == ["part_1", "part_2"]
    single = parts_to_scene(sqs, resolution=12)
    for name in scene.geometry:
        np.testing.assert_allclose(scene.geometry[name].vertices, single.geometry[name].vertices, atol=1e-6)


# ----------------------------------------------------------------------------------------------------
# safe writes


def test_failed_write_leaves_earlier_outputs_and_no_partial_files(tmp_path, monkeypatch):
    seg, image = _fake()
    out = tmp_path / "out"
    write_segmentation(seg, image, out, figure=False)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export, "parts_to_mesh", boom)
    seg.labels[:] = 0  # would change labels.npy / models.json if anything were written
    with pytest.raises(OSError):
        write_segmentation(seg, image, out, figure=False)
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after == before  # nothing replaced, no temporary folder left


def test_symlinks_in_out_are_replaced_not_followed(tmp_path):
    seg, image = _fake()
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "precious.txt"
    victim.write_text("keep me")
    os.symlink(victim, out / "models.json")
    os.symlink(victim, out / "figure.png")  # stale output of an earlier run: the link goes, not the target
    write_segmentation(seg, image, out, figure=False)
    assert victim.read_text() == "keep me"
    assert not (out / "models.json").is_symlink() and json.loads((out / "models.json").read_text())["parts"]
    assert not os.path.lexists(out / "figure.png")


def test_unwritable_output_is_reported_naming_it(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OSError, match=r"file: exists and is not a folder"):
        check_writable_dir(tmp_path / "file")
    with pytest.raises(OSError, match=r"/proc/sqjax-test"):
        check_writable_dir("/proc/sqjax-test")


def test_atomic_paths_remove_temporaries_on_failure(tmp_path):
    target = tmp_path / "a.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_paths(target) as (tmp,):
            tmp.write_text("half")
            raise RuntimeError("stop")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]


def test_atomic_files_get_the_usual_permissions(tmp_path):
    mask = os.umask(0o022)
    try:
        with atomic_paths(tmp_path / "a.json") as (tmp,):
            tmp.write_text("{}")
    finally:
        os.umask(mask)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o644


def test_cloud_figure_panels_keep_to_the_data_when_a_model_is_swollen():
    """3-D axes do not clip: a growth model 100x the data's size must not shrink the data to a dot.
    The cloud panels span the data's box (with a fifth around it) and leave out what reaches beyond."""
    from types import SimpleNamespace

    from matplotlib.figure import Figure

    from sqjax.plot import draw_superquadrics, figure_sequence

    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (400, 3)) + (0, 0, 5)
    small = Superquadric.create([0.5, 0.5, 0.5], translation=[0, 0, 5])
    huge = Superquadric.create([100.0, 0.1, 0.1], translation=[0, 0, 5])
    box = np.array([[-2.0, 2.0, -2.0], [2.0, 8.0, 2.0]])  # the plotted frame: x, depth, up
    ax = Figure().add_subplot(projection="3d")
    kept = draw_superquadrics(ax, [huge, small], clip=box)
    assert len(kept) and np.all((kept >= box[0]) & (kept <= box[1]))  # the small model, whole
    seg = SimpleNamespace(
        labels=np.ones(400, np.int32), parts=[SimpleNamespace(superquadric=small)], history=[[huge, small]] * 3
    )
    fig = figure_sequence(pts, seg)
    for ax in fig.axes[1:4]:  # the model panels
        assert np.ptp(ax.get_xlim()) < 4.0, ax.get_xlim()


def test_figure_point_panels_span_the_scene_not_its_flying_points():
    """A few flying points metres behind the scene (stereo and RealSense frames have them) must not
    shrink the points' 3-D panel to a dot: the panel spans the bulk of the points and its title counts
    the far ones it leaves out. Clouds and range images alike."""
    from types import SimpleNamespace

    from sqjax.plot import figure_sequence

    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform(-1, 1, (2000, 3)) + (0, 0, 5), [[0, 0, 900.0], [400.0, 0, 5], [0, -300.0, 5]]])
    part = Superquadric.create([0.5, 0.5, 0.5], translation=[0, 0, 5])
    seg = SimpleNamespace(
        labels=np.ones(len(pts), np.int32), parts=[SimpleNamespace(superquadric=part)], history=[[part]] * 3
    )
    ax = figure_sequence(pts, seg).axes[0]
    assert max(np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()), np.ptp(ax.get_zlim())) < 6.0
    assert "3 far points not drawn" in ax.get_title()

    depth = np.full((40, 50), 2.0)
    depth[5, 7] = 500.0  # one flying pixel
    image = RangeImage(depth, PinholeCamera(60.0, 60.0, 25.0, 20.0))
    part = Superquadric.create([0.5, 0.5, 0.1], translation=[0, 0, 2])
    seg = SimpleNamespace(
        labels=np.ones(depth.shape, np.int32), parts=[SimpleNamespace(superquadric=part)], history=[[part]] * 3
    )
    ax = figure_sequence(image, seg).axes[2]  # (a) and its colour bar, then (b)
    assert "(b)" in ax.get_title() and "1 far point not drawn" in ax.get_title()
    assert np.ptp(ax.get_ylim()) < 5.0  # depth: the plot's y


def test_cloud_figure_matches_model_colours_on_a_bounded_sample(monkeypatch):
    """The colours of a cloud's earlier models come from their overlap with the final parts, counted on
    at most `MATCH_POINTS` points: a million-point cloud's figure took 15 s testing every model on every
    point. Each model still takes the colour of the part it lies on."""
    import sqjax.plot as plot
    import sqjax.superquadric as sqmod

    monkeypatch.setattr(plot, "MATCH_POINTS", 500)
    sizes = []
    contains = sqmod.contains

    def counting(sq, points):
        sizes.append(len(points))
        return contains(sq, points)

    monkeypatch.setattr(sqmod, "contains", counting)
    rng = np.random.default_rng(0)
    left, right = rng.uniform(-1, 1, (3000, 3)) + (-5, 0, 0), rng.uniform(-1, 1, (3000, 3)) + (5, 0, 0)
    pts = np.concatenate([left, right])
    final = np.repeat(np.array([1, 2], np.int32), 3000)
    models = [Superquadric.create([1.0, 1.0, 1.0], translation=[x, 0, 0]) for x in (5.0, -5.0)]
    idx = plot._match_cloud(models, pts, final, 2)
    assert sizes and max(sizes) <= 500
    assert idx.tolist() == [1, 0]  # the parts they lie on: the right one (colour 1), the left one (colour 0)


@pytest.mark.parametrize("shape", [(1, 16), (12, 1)])
def test_model_images_of_a_one_pixel_wide_image_are_shaded(shape):
    """A range image one pixel high or wide (a scan line) segments; its figure's model panel shades
    with no gradient across the missing axis instead of failing inside numpy."""
    from sqjax.plot import render_models

    sq = Superquadric.create((0.5, 0.5, 0.5), translation=(0.0, 0.0, 2.0))
    camera = PinholeCamera(20.0, 20.0, (shape[1] - 1) / 2, (shape[0] - 1) / 2)
    img, labels = render_models([sq], camera, shape)
    assert img.shape[:2] == shape and np.all(np.isfinite(img))
    assert (labels == 1).any()  # the model is drawn, not a blank panel


def test_model_panels_cut_a_swollen_model_at_the_data_s_box():
    """A growth model many times the data's size in front of the data covered the whole model panel
    (box.STL, view 2); cut at the data's box it leaves the model behind it in view. The model of a
    clipped-away part gets no pixels, and the labels still name the models' own indices."""
    from sqjax.plot import render_models

    small = Superquadric.create((0.3, 0.3, 0.3), translation=(0.0, 0.0, 3.0))
    sheet = Superquadric.create((50.0, 50.0, 0.05), translation=(0.0, 0.0, 2.0))  # in front of everything
    far = Superquadric.create((0.1, 0.1, 0.1), translation=(5.0, 0.0, 3.0))  # outside the box
    camera = PinholeCamera(60.0, 60.0, 15.5, 15.5)
    _, whole = render_models([small, sheet, far], camera, (32, 32))
    assert np.all(whole == 2)  # the sheet hides everything
    box = np.array([[-0.5, -0.5, 2.5], [0.5, 0.5, 3.5]])  # the data: around the small model
    img, cut = render_models([small, sheet, far], camera, (32, 32), clip=box)
    assert (cut == 1).sum() > 50 and not (cut == 2).any() and not (cut == 3).any()
    assert np.all(np.isfinite(img))
