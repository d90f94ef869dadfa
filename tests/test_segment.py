"""Recover-and-select on the paper's scenes, clouds and degenerate inputs."""

import numpy as np
import pytest

import sqjax
from sqjax import PinholeCamera, RangeImage, Superquadric, hoover, segment
from sqjax.evaluate import volume_iou
from sqjax.mesh import sample_surface
from sqjax.padding import PAIR_SIZES, calls
from sqjax.scenes import paper_scene, random_scene

from helpers import data_path, mosd_image, mosd_truth


@pytest.fixture(scope="module", params=["sphere_cylinder", "two_cylinders", "occluded_block"])
def paper_result(request):
    image, truth = paper_scene(request.param, noise=0.002)
    return request.param, image, truth, segment(image)


def test_paper_scenes_right_parts_and_hoover_correct(paper_result):
    """The paper's Figures 1-3: every part found once, each a correct detection at T = 0.8
    (the occluded block, which the image shows in two pieces, as one part)."""
    name, image, truth, seg = paper_result
    score = hoover(image.labels, seg.labels, tolerance=0.8)
    assert len(seg.parts) == len(truth), name
    assert score.correct == len(truth), (name, score.to_dict())
    assert score.over == score.under == score.missed == score.noise == 0


def test_paper_scene_models_are_finite_and_consistent(paper_result):
    name, image, truth, seg = paper_result
    assert seg.labels.shape == image.shape and seg.labels.dtype == np.int32
    assert set(np.unique(seg.labels)) <= set(range(len(seg.parts) + 1))
    assert not np.any(seg.labels[~image.valid])
    for i, part in enumerate(seg.parts):
        for leaf in (
            part.superquadric.size,
            part.superquadric.epsilon,
            part.superquadric.rotation,
            part.superquadric.translation,
        ):
            assert np.isfinite(np.asarray(leaf)).all()
        # parts and labels agree: every part owns labelled pixels, num_points counts them
        assert part.num_points == int(np.sum(seg.labels == i + 1)) > 0
        assert part.num_explained == part.region.size  # num_points may exceed it (`propagate`)
        assert np.all(seg.labels.ravel()[part.region] >= 1)
        assert np.isfinite(part.error) and part.error <= part.num_explained * seg.threshold**2
    # the history holds the models after each selection and ends with the final ones
    assert len(seg.history) >= 2 and len(seg.history[-1]) == len(seg.parts)
    assert set(seg.timings) >= {"total", "compile", "run"} and seg.timings["run"] >= 0
    d = seg.to_dict()
    assert len(d["parts"]) == len(seg.parts) and {"size", "epsilon", "rotation", "translation"} <= set(d["parts"][0])


def test_parts_explain_the_truth_volumes(paper_result):
    """Each found part overlaps its true superquadric (volume IoU) reasonably: one view only."""
    name, image, truth, seg = paper_result
    score = hoover(image.labels, seg.labels)
    for t, f in score.correct_pairs:
        iou = volume_iou(truth[t - 1], seg.parts[f - 1].superquadric, n=20_000)
        assert iou > 0.3, (name, t, iou)


def test_deterministic():
    image, _ = paper_scene("sphere_cylinder", noise=0.002)
    a, b = segment(image), segment(image)
    np.testing.assert_array_equal(a.labels, b.labels)
    for p, q in zip(a.parts, b.parts):
        np.testing.assert_array_equal(np.asarray(p.superquadric.size), np.asarray(q.superquadric.size))


def test_flat_plane_is_one_part():
    d = np.full((60, 80), 5.0)
    seg = segment(RangeImage(d, PinholeCamera(100, 100, 40, 30)))
    assert len(seg.parts) == 1 and (seg.labels > 0).mean() > 0.95


def test_unorganised_cloud_with_knn_adjacency():
    a = sqjax.Superquadric.create([1, 1, 1])
    b = sqjax.Superquadric.create([1, 0.5, 0.7], [0.3, 0.3], translation=[4, 0, 0])
    pts = np.concatenate([sample_surface(a, 1500, seed=1, noise=0.005), sample_surface(b, 1500, seed=2, noise=0.005)])
    seg = segment(pts)
    assert len(seg.parts) == 2 and seg.labels.shape == (3000,)
    la, lb = np.bincount(seg.labels[:1500]).argmax(), np.bincount(seg.labels[1500:]).argmax()
    assert la != lb and la > 0 and lb > 0
    assert (seg.labels[:1500] == la).mean() > 0.95 and (seg.labels[1500:] == lb).mean() > 0.95


@pytest.mark.parametrize(
    "depth, message",
    [
        (np.full((30, 40), np.nan), "no valid pixel"),
        (np.zeros((30, 40)), "no valid pixel"),
        (np.where(np.arange(1200).reshape(30, 40) == 7, 5.0, np.nan), "1 valid pixels"),
        (np.full((3, 3), 5.0), "9 valid pixels"),
    ],
)
def test_degenerate_images_get_a_clear_error(depth, message):
    with pytest.raises(ValueError, match=message):
        segment(RangeImage(depth, PinholeCamera(50, 50, 20, 15)))


@pytest.mark.parametrize(
    "data",
    [
        np.zeros((5, 4)),
        (np.zeros((5, 3)), "point_cloud"),
        "cloud.ply",
        [[1.0, 2.0, 3.0], [1.0, 2.0]],
        np.ones((50, 3), complex),
    ],
)
def test_bad_input_type(data):
    """A wrong shape, a (points, kind) pair, a path, ragged rows or complex numbers: an error naming
    what segment takes."""
    with pytest.raises(ValueError, match="RangeImage or an"):
        segment(data)


@pytest.mark.parametrize("copies", [30, 500])
def test_a_cloud_of_copies_of_few_points_says_so(copies):
    """Valid rows that repeat too few positions (a point written many times) are not "1 valid point":
    the error counts both."""
    with pytest.raises(ValueError, match=rf"{copies} valid points, but 1 distinct position"):
        segment(np.ones((copies, 3)))


def test_each_refit_is_a_few_kernel_calls_of_fixed_shapes(monkeypatch):
    """A refit of K hypotheses (one per growth step, one per seed start) is a few calls of the batch
    kernel, each of one of the few fixed batch sizes (`padding.fit_calls`), so growth steps do not
    recompile."""
    from sqjax import padding, workspace

    calls, refits = [], []
    real, real_refit = workspace.fit_padded, workspace.Workspace.fit

    def record(points, mask, theta0, opts):
        calls.append(points.shape[:2])
        return real(points, mask, theta0, opts)

    def record_refit(self, regions, theta0, **kw):
        before = len(calls)
        out = real_refit(self, regions, theta0, **kw)
        refits.append((len(regions), calls[before:], theta0 is not None))
        return out

    monkeypatch.setattr(workspace, "fit_padded", record)
    monkeypatch.setattr(workspace.Workspace, "fit", record_refit)
    image, _ = paper_scene("two_cylinders", noise=0.002)
    seg = segment(image, merge=False)
    # points: 128 when every region fits (seed windows), else max_points = 256
    assert all(N in (128, 256) for _, N in calls), sorted(set(calls))
    assert all(K in padding.fit_call_sizes(N) for K, N in calls), sorted(set(calls))  # CPU: two chunk sizes
    for K, made, warm in refits:  # one N per refit, the calls of the padding policy
        N = made[0][1]
        assert len({n for _, n in made}) == 1 and [k for k, _ in made] == [k for _, k in padding.fit_calls(K, N, warm)]
    assert sum(len(made) for _, made, _ in refits) == len(calls)
    assert any(len(made) > 1 for _, made, _ in refits)  # the seeds: more than one call
    rounds = 1 + min(seg.stats["reseeded"], sqjax.SegmentOptions().extras.reseed)  # seeds, and each reseeding round
    # the three starts of the seeds, then a step each, then the five starts of the parts' volumes
    assert len(refits) <= 3 * rounds + seg.stats["growth_steps"] + 5
    assert len(set(calls)) <= 6, sorted(set(calls))
    # a max_points far above the data's size pads no refit beyond its largest region's bucket: 1e8
    # asked for 375 GiB, and 1e5 took 25x the time of the default on a 3,072-pixel image
    assert padding.refit_points(3000, 100_000) == 4096 and padding.refit_points(3000, 10**8) == 4096
    assert padding.refit_points(100, 10**8) == 128 and padding.refit_points(200, 256) == 256
    calls.clear()
    small = image.subsample(2)
    assert len(segment(small, merge=False, max_points=10**8).parts) >= 1
    assert max(N for _, N in calls) <= padding.bucket(small.valid.sum(), 32), sorted(set(calls))


def test_free_components_follow_the_adjacency():
    """Connected unexplained pieces along the (cut) adjacency, filtered by size."""
    from sqjax.domain import free_components

    # a chain 0-1-2, a cut, then 3-4, and 5 alone
    nb = np.array([[1, -1], [0, 2], [1, -1], [4, -1], [3, -1], [-1, -1]])
    free = np.ones(6, bool)
    assert [c.tolist() for c in free_components(free, nb, 1, 10)] == [[0, 1, 2], [3, 4], [5]]
    assert [c.tolist() for c in free_components(free, nb, 2, 2)] == [[3, 4]]
    free[1] = False  # explained point splits the chain
    assert [c.tolist() for c in free_components(free, nb, 1, 10)] == [[0], [2], [3, 4], [5]]
    assert free_components(np.zeros(6, bool), nb, 1) == []
    assert [c.tolist() for c in free_components(free, np.zeros((6, 0), int), 1)] == [[0], [2], [3], [4], [5]]


def test_cloud_regions_dilate_along_the_neighbour_lists():
    """A cloud region grown by r rings holds the points within r steps along each point's neighbour list
    (a breadth-first reference), for 20 regions at once (three packed bytes); -1 entries join nothing."""
    from sqjax.domain import Domain

    rng = np.random.default_rng(5)
    P, k = 300, 6
    nb = rng.integers(-1, P, (P, k))
    dom = Domain(rng.normal(size=(P, 3)), nb, np.arange(P), (P,))
    regions = rng.random((20, P)) < 0.01
    for rings in (1, 3):
        expected = regions.copy()
        for _ in range(rings):
            grown = expected.copy()
            for j in range(k):
                ok = nb[:, j] >= 0
                grown[:, ok] |= expected[:, nb[ok, j]]
            expected = grown
        assert np.array_equal(dom.dilate(regions, rings), expected)


def test_free_components_are_the_connected_pieces_of_the_free_points():
    """On a symmetric adjacency (an image grid with cuts), the pieces are the connected components of the
    graph the free points induce (scipy's), ordered by their first point."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from sqjax.domain import free_components

    rng = np.random.default_rng(3)
    H, W = 40, 50
    idx = np.arange(H * W).reshape(H, W)
    nb = np.full((H * W, 4), -1)
    nb[idx[:, 1:].ravel(), 0], nb[idx[:, :-1].ravel(), 1] = idx[:, :-1].ravel(), idx[:, 1:].ravel()
    nb[idx[1:].ravel(), 2], nb[idx[:-1].ravel(), 3] = idx[:-1].ravel(), idx[1:].ravel()
    for free in (rng.random(H * W) < 0.6, rng.random(H * W) < 0.05):
        ids = np.flatnonzero(free)
        p, j = np.nonzero((nb[ids] >= 0) & free[np.maximum(nb[ids], 0)])
        local = np.searchsorted(ids, nb[ids][p, j])
        graph = coo_matrix((np.ones(p.size), (p, local)), shape=(ids.size, ids.size))
        _, comp = connected_components(graph, directed=False)
        expected = sorted((ids[comp == c] for c in np.unique(comp)), key=lambda c: c[0])
        got = free_components(free, nb, 1)
        assert [c.tolist() for c in got] == [c.tolist() for c in expected]


def test_reseeding_finds_a_part_whose_hypotheses_lost_early():
    """With reseeding off (the paper's single pass) a part may end unexplained; the second chance
    never loses a correct detection and only adds parts that explain data."""
    image, truth = random_scene(40, n_parts=(2, 6), shape=(120, 160), noise=0.005)
    single = segment(image, reseed=0)
    again = segment(image)
    s1, s2 = hoover(image.labels, single.labels), hoover(image.labels, again.labels)
    assert s2.correct >= s1.correct and s2.correct == len(truth), (s1.to_dict(), s2.to_dict())
    assert again.stats["reseeded"] > 0 and single.stats["reseeded"] == 0


def _mosd_scores(name: str, tolerances=(0.8,)) -> list:
    """Hoover scores of one segmentation of mOSD scene `name` at 160 x 120, one per tolerance."""
    image, truth = mosd_image(name)
    found = segment(image).labels
    return [hoover(truth, found, tolerance=t) for t in tolerances]


def test_mosd_plate_under_a_box_is_found():
    """mOSD learn17: a plate with a box on it. What the box leaves visible of the plate is a strip
    no seed window fits in; reseeding it as a whole connected piece finds the plate: all three objects
    (the table included) found at T = 0.5, none merged with another.

    (It asserted T = 0.8 while the method was tuned on this scene; with the quadtree seeds, which gain
    28 correct objects over the 59 mOSD scenes (benchmarks/RESULTS.md), the plate's region here
    overlaps its truth by between 50% and 80%.)"""
    (score,) = _mosd_scores("learn17", (0.5,))
    assert score.correct == score.n_truth == 3 and score.under == 0, score.to_dict()


def test_mosd_unexplained_surface_takes_the_label_it_joins():
    """mOSD test7 (boxes): a superquadric does not follow a real box's rounded rim, so its model leaves
    a third of one box unexplained. With `propagate` those pixels, joined to the box's labelled ones
    without a depth jump, take its label: the labels of explained pixels are unchanged, more pixels
    are labelled, and no object is detected worse.

    (It also asserted all three boxes correct; that held only on some machines: the segmentation of
    a real scene changes with float32 rounding, a relative change of 1e-6 in the depths changes the
    label image of learn2, test7 and test24, benchmarks/RESULTS.md, so one scene's count is no
    property.)"""
    image, truth = mosd_image("test7")
    plain, filled = segment(image, propagate=False).labels, segment(image).labels
    assert np.array_equal(filled[plain > 0], plain[plain > 0])
    assert (filled > 0).sum() > (plain > 0).sum() and not np.any(filled[~image.valid])
    before, after = hoover(truth, plain), hoover(truth, filled)
    assert after.correct >= before.correct and after.n_truth == 3, after.to_dict()


@pytest.mark.parametrize("name, n_objects", [("test16", 4), ("test35", 5), ("test5", 3)])
def test_mosd_touching_parts_stay_apart(name, n_objects):
    """mOSD scenes of parts touching with no depth jump: no found region takes in two of them (no
    under-segmentation at T = 0.8 or 0.5). test16: a block on a handle standing on a plate; test35: a
    block standing on a cylinder on a wider one; test5: two boxes side by side with nearly coplanar
    fronts. One superquadric explains most of two such parts, and each one's model reaches into the
    other with its far faces. What keeps them apart: a merge must explain each of the two, and each
    pixel goes to the model that explains it from the camera's side, comparing distances averaged
    over a small neighbourhood.

    (It asserted every object correct at T = 0.8, on the scenes the method was tuned on; that held
    only on some machines (float32 rounding) and not with the quadtree seeds, which gain 28 correct
    objects over the 59 mOSD scenes; benchmarks/segment.py measures the detection rate.)"""
    for score in _mosd_scores(name, (0.8, 0.5)):
        assert score.n_truth == n_objects and score.under == 0, score.to_dict()


@pytest.mark.parametrize(
    "field, value",
    [
        ("noise", -1.0),
        ("noise", float("nan")),
        ("noise", 0.0),
        ("threshold", -1.0),
        ("threshold", float("inf")),
        ("window", -5),
        ("window", 4),
        ("stride", -1),
        ("rings", -1),
        ("max_steps", -3),
        ("keep_fraction", 2.0),
        ("max_points", 0),
        ("enlarge", 0.0),
        ("selector", "greedyy"),
        ("subsample", 0),
        ("fit_steps", 0),
        ("seed_inlier_fraction", 0.0),
        ("min_exclusive", 1.5),
        ("window", 2.5),
        ("merge", "yes"),
        ("subdivide", "yes"),
        ("propagate", "yes"),
    ],
)
def test_bad_options_are_refused_at_construction_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"Options\.{field} must be|must be .*\(option {field}\)"):
        sqjax.SegmentOptions.create(**{field: value})
    with pytest.raises(ValueError, match=field):  # the same through segment's keywords, before any work
        segment(np.full((3, 3, 3), np.nan), **{field: value})


def test_quadtree_seeds_reach_parts_smaller_than_a_window():
    """Seeds at several scales (issue 11): a 9 x 9 pixel part has no 10 x 10 window clear of its depth
    edges, so whole windows never seed it; the quadrants of the windows that fail do, down to the
    smallest window that holds min_seed_points, and no seed straddles a depth edge."""
    from sqjax.seeds import seed_windows

    H, W, window, stride, min_seed = 40, 50, 10, 5, 22
    idmap = np.arange(H * W).reshape(H, W)
    part = np.zeros((H, W), bool)
    part[13:22, 17:26] = True  # 9 x 9 pixels, not aligned with the window grid
    broken = np.zeros((H, W), bool)  # pixels joined to a neighbour across the part's edge
    for axis in (0, 1):
        for shift in (1, -1):
            broken |= part != np.roll(part, shift, axis)
    broken = broken.ravel()
    whole, fine, smallest = seed_windows(idmap, broken, window, stride, min_seed, subdivide=False)
    assert fine == [] and smallest == window
    assert not any(part.ravel()[ids].any() for ids in whole)
    whole2, fine, smallest = seed_windows(idmap, broken, window, stride, min_seed, subdivide=True)
    assert len(whole2) == len(whole) and all(np.array_equal(a, b) for a, b in zip(whole, whole2, strict=True))
    assert smallest == int(np.ceil(np.sqrt(min_seed))) == 5
    inside = [ids for ids in fine if part.ravel()[ids].all()]
    assert inside, "no quadrant seed inside the small part"
    for ids in whole2 + fine:
        assert ids.size >= min_seed and not broken[ids].any()


def test_knn_is_exact():
    """The k-d tree neighbours are the brute-force nearest ones, the point itself excluded."""
    from sqjax.domain import knn

    P = np.random.default_rng(0).normal(size=(500, 3))
    nb = knn(P, 6)
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_array_equal(np.sort(nb, 1), np.sort(np.argsort(d, 1)[:, :6], 1))
    assert not np.any(nb == np.arange(500)[:, None])
    assert knn(P[:3], 6).shape == (3, 6) and np.all(knn(P[:3], 6)[:, 2:] == -1)


def test_cloud_labels_stay_aligned_with_the_input_rows():
    """NaN rows of a cloud get label 0 and every other row keeps its own label (and region indices
    are rows of the input)."""
    a = sqjax.Superquadric.create([1, 1, 1])
    b = sqjax.Superquadric.create([1, 0.5, 0.7], [0.3, 0.3], translation=[4, 0, 0])
    pts = np.concatenate([sample_surface(a, 800, seed=1, noise=0.005), sample_surface(b, 800, seed=2, noise=0.005)])
    holed = pts.copy()
    holed[::7] = np.nan
    seg = segment(holed)
    assert seg.labels.shape == (1600,) and np.all(seg.labels[::7] == 0)
    la, lb = np.bincount(seg.labels[1:800]).argmax(), np.bincount(seg.labels[801:]).argmax()
    keep = np.isfinite(holed).all(1)
    assert la != lb and (seg.labels[:800][keep[:800]] == la).mean() > 0.95
    assert (seg.labels[800:][keep[800:]] == lb).mean() > 0.95
    for i, part in enumerate(seg.parts):
        assert np.all(keep[part.region]) and part.num_points == np.sum(seg.labels == i + 1)


def test_large_clouds_are_segmented_on_a_working_subset_and_labelled_in_full(monkeypatch):
    """A cloud above the working budget is segmented on one in `step` of its points, with the noise
    measured on all of them, and every input row is labelled by the final models: the same parts as
    the exact path, labels aligned with the rows (NaN rows 0), parts that own their labels."""
    import sqjax.segmentation as S
    from sqjax.domain import cloud_noise

    a = sqjax.Superquadric.create([1, 1, 1])
    b = sqjax.Superquadric.create([1, 0.5, 0.7], [0.3, 0.3], translation=[4, 0, 0])
    pts = np.concatenate([sample_surface(a, 1500, seed=1, noise=0.005), sample_surface(b, 1500, seed=2, noise=0.005)])
    pts[::11] = np.nan
    keep = np.isfinite(pts).all(1)
    exact = segment(pts)
    monkeypatch.setattr(S, "WORKING_POINTS", 900)
    seg = segment(pts)
    assert exact.stats["subsample"] == 1 and seg.stats["subsample"] == 3
    assert seg.noise == pytest.approx(cloud_noise(pts[keep], 48))
    assert seg.labels.shape == (3000,) and np.all(seg.labels[~keep] == 0)
    assert len(seg.parts) == len(exact.parts) == 2
    la, lb = np.bincount(seg.labels[:1500]).argmax(), np.bincount(seg.labels[1500:]).argmax()
    assert la != lb and (seg.labels[:1500][keep[:1500]] == la).mean() > 0.95
    assert (seg.labels[1500:][keep[1500:]] == lb).mean() > 0.95
    for i, part in enumerate(seg.parts):
        assert np.all(keep[part.region]) and part.num_points == np.sum(seg.labels == i + 1) > 0
    assert segment(pts, subsample=1).stats["subsample"] == 1  # the exact path on request


def test_a_closed_cloud_is_not_left_in_pieces():
    """A sphere on a box, sampled all round (a cloud of a whole object, not one view): the sphere's
    seeds grow as caps that stop short of each other, and one pairwise merge joined two of them, so the
    sphere came out as 11 parts. Unions that the selection keeps grow on, and merging repeats."""
    sphere = Superquadric.create((0.1, 0.1, 0.1))
    box = Superquadric.create((0.2, 0.15, 0.1), (0.1, 0.1), translation=(0.0, 0.0, -0.2))
    pts = np.concatenate([sample_surface(q, 4000, seed=s, noise=0.002) for q, s in ((sphere, 1), (box, 11))])
    seg = segment(pts)
    assert len(seg.parts) == 2
    for truth, part in zip((sphere, box), sorted(seg.parts, key=lambda q: -float(q.superquadric.translation[2]))):
        assert volume_iou(truth, part.superquadric, n=4000) > 0.9
    # Where the sphere sits on the box, points within a few noise widths of the contact go to either
    # part, as rounding decides (59-123 of the sphere's under input scalings of 1 + 1e-6 .. 1e-5): a
    # piece would lie elsewhere. So every point off its half's label lies at the contact (z = -0.1).
    for half, p in ((seg.labels[:4000], pts[:4000]), (seg.labels[4000:], pts[4000:])):
        off = half != np.bincount(half).argmax()
        assert off.mean() <= 0.05 and np.all(np.abs(p[off, 2] + 0.1) <= 5 * 0.002)


def test_a_cloud_keeps_two_coplanar_slabs_that_do_not_touch_apart():
    """Two boxy slabs side by side in one plane, sampled all round, 0.05-0.2 apart (the backs of two
    chairs in a row): one slab explains both, and before unions were limited to touching regions the
    merge made them one part (each gap). A cloud has no camera to tell an occluded gap from an empty
    one, so its pieces join only where they touch (`postprocess.touching`)."""
    from sqjax.postprocess import touching

    for gap in (0.05, 0.2):
        slabs = [
            Superquadric.create((0.3, 0.2, 0.03), (0.2, 0.2), translation=(s * (0.3 + gap / 2), 0, 0)) for s in (-1, 1)
        ]
        pts = np.concatenate([sample_surface(q, 3000, seed=k, noise=0.002) for k, q in enumerate(slabs)])
        seg = segment(pts)
        assert len(seg.parts) == 2
        first, second = (np.bincount(half, minlength=3) for half in (seg.labels[:3000], seg.labels[3000:]))
        assert first.argmax() != second.argmax() and min(first.max(), second.max()) >= 0.97 * 3000
    regions = np.zeros((3, 6), bool)
    regions[0, :2], regions[1, 2:4], regions[2, [3, 5]] = True, True, True
    neighbours = np.array([[1], [2], [-1], [-1], [-1], [-1]])  # 1 -> 2 joins regions 0 and 1
    assert touching(regions, neighbours) == {(0, 1), (1, 2)}  # 1 and 2 share point 3; 0 and 2 do not touch


def test_repeated_points_are_segmented_once_and_labelled_alike():
    """A cloud with every third point written twice segments as the distinct cloud does (k nearest
    neighbours among copies join nothing: 50 points written 40 times each gave 25 parts of zero size),
    and each copy gets its original's label."""
    a = Superquadric.create((0.3, 0.2, 0.1))
    b = Superquadric.create((0.1, 0.1, 0.25), translation=(0.6, 0.0, 0.0))
    pts = np.concatenate([sample_surface(a, 1500, seed=1, noise=0.003), sample_surface(b, 1500, seed=2, noise=0.003)])
    once, twice = segment(pts), segment(np.concatenate([pts, pts[::3]]))
    assert len(once.parts) == len(twice.parts) == 2 and twice.labels.shape == (4000,)
    assert np.array_equal(twice.labels[:3000], once.labels) and np.array_equal(twice.labels[3000:], once.labels[::3])
    assert [p.num_points for p in twice.parts] == [int(np.sum(twice.labels == i + 1)) for i in range(2)]


def test_merge_candidates_grow_linearly_with_the_models():
    """A scene of many selected pieces must not cost a union fit per pair (28k on a 239-piece plane)."""
    from sqjax.postprocess import MERGE_NEIGHBOURS, merge_candidates

    pts = np.random.default_rng(1).normal(size=(4000, 3))
    regions = np.zeros((200, 4000), bool)
    regions[np.arange(4000) % 200, np.arange(4000)] = True
    pairs = merge_candidates(pts, regions)
    assert len(pairs) <= 2 * MERGE_NEIGHBOURS * 200 and {i for p in pairs for i in p} == set(range(200))
    assert len(merge_candidates(pts, regions[:5])) == 10  # few models: every pair, as before


def test_merge_candidates_pair_pieces_whose_points_are_near():
    """In a range image, two pieces 0.1 apart (an object an occluder split) are a candidate pair although
    the bounding spheres of long rods passing 0.5 away overlap theirs (a table's sphere holds every
    object on it)."""
    from sqjax.postprocess import MERGE_NEIGHBOURS, merge_candidates

    rng = np.random.default_rng(0)
    blob = lambda c: c + 0.01 * rng.normal(size=(30, 3))
    t = np.linspace(-2, 2, 200)[:, None]
    rods = [
        np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.0]) + t * np.array([-np.sin(a), np.cos(a), 0.0])
        for a in np.linspace(0, np.pi, 2 * MERGE_NEIGHBOURS + 1)
    ]
    sets = [blob(np.zeros(3)), blob(np.array([0.0, 0.0, 0.1])), *rods]
    pts = np.concatenate(sets)
    regions = np.zeros((len(sets), len(pts)), bool)
    start = np.cumsum([0] + [len(s) for s in sets])
    for k in range(len(sets)):
        regions[k, start[k] : start[k + 1]] = True
    pairs = merge_candidates(pts, regions)
    assert (0, 1) in pairs
    assert (0, 1) not in merge_candidates(pts, regions, one_view=False)  # a cloud: the spheres' list alone
    assert {(0, k) for k in range(2, len(sets))} & set(pairs)  # the rods, nearest by their spheres
    # a later merge round reuses the gaps measured before: the same pairs, nothing measured again,
    # and a new region's pairs measured anew
    known: dict = {}
    assert merge_candidates(pts, regions, known=known) == pairs and known
    measured = dict(known)
    assert merge_candidates(pts, regions, known=known) == pairs and known == measured
    moved = regions.copy()
    moved[1] = np.roll(regions[1], 1)
    merge_candidates(pts, moved, known=known)
    assert len(known) > len(measured) and all(known[p] == measured[p] for p in measured)


def test_a_failed_growth_step_is_tried_once_in_the_other_admission():
    """Loose fails -> strict steps from the same state (and on after they succeed); strict fails in a
    new state -> one loose step; both failed in one state, or a loose step admitted nothing -> stop."""
    from sqjax.growth import _failed
    from sqjax.hypotheses import Models

    models = Models(np.zeros((3, 11)), np.zeros((3, 5), bool), [[], [], []])
    _failed(models, np.array([0, 1]), np.array([10, 10]))  # loose steps failed at 10 points
    assert models.active.all() and not models.loose[:2].any() and models.loose[2]
    _failed(models, np.array([0]), np.array([10]))  # model 0: strict failed at 10 as well
    assert not models.active[0]
    # model 1 grew strictly to 14 and its strict step then failed: loose again, from 14
    _failed(models, np.array([1]), np.array([14]))
    assert models.active[1] and models.loose[1]
    _failed(models, np.array([1]), np.array([14]))  # the loose step failed there too
    assert not models.active[1]
    _failed(models, np.array([2]), np.array([7]), admitted=False)  # loose admitted nothing: strict would not
    assert not models.active[2]


def test_working_step_follows_the_valid_pixels():
    """The working step brings a full frame near 160 x 120, and is finer while the working image keeps
    at most `WORKING_VALID` valid pixels: an object in a large frame is not subsampled like a frame."""
    from sqjax.segmentation import WORKING_VALID, working_step

    assert [working_step(s) for s in ((120, 160), (240, 320), (480, 640), (1080, 1920))] == [1, 2, 4, 10]
    for shape in ((120, 160), (240, 320), (480, 640)):
        assert working_step(shape, np.ones(shape, bool)) == working_step(shape)  # every pixel valid
    rng = np.random.default_rng(0)
    kinect = rng.random((480, 640)) < 0.55  # a table-top frame: half its pixels valid, all over it
    assert working_step(kinect.shape, kinect) == 4
    valid = np.zeros((240, 320), bool)
    valid[60:150, 100:220] = True  # an object: 10,800 valid pixels
    assert working_step(valid.shape, valid) == 1
    valid = np.zeros((480, 640), bool)
    valid[100:300, 200:400] = True  # 40,000 valid pixels: 10,000 at step 2
    assert working_step(valid.shape, valid) == 2 and valid[::2, ::2].sum() <= WORKING_VALID < valid.sum()
    assert working_step((480, 640), np.zeros((480, 640), bool)) == 1


def test_large_images_are_segmented_at_a_working_resolution_and_labelled_in_full():
    """A 480 x 640 image (an eighth of it valid) is segmented at 240 x 320 (step 2) and every
    full-size pixel is labelled by the final models: the same parts are found, with labels at the
    input's size."""
    image, truth = random_scene(3, n_parts=3, shape=(480, 640), noise=0.005)
    seg = segment(image)
    assert seg.stats["subsample"] == 2 and seg.labels.shape == (480, 640)
    score = hoover(image.labels, seg.labels, tolerance=0.8)
    assert score.correct == len(truth) == len(seg.parts), score.to_dict()
    assert (seg.labels[image.valid] > 0).mean() > 0.95
    for i, part in enumerate(seg.parts):
        assert part.num_points == np.sum(seg.labels == i + 1) > 0


def test_full_size_pixels_between_the_working_rows_are_labelled_along_the_surface():
    """A 480 x 640 plane (segmented at step 4) whose rows between the working rows lie 5 noise nearer
    the camera, as a Kinect's depth bands do: no model explains them (tau is 3 noise) and their working
    pixels are explained, so they were left unlabelled (44% of the pixels). The full-size surface
    joins them to the labelled rows (a step of 5 noise is no depth discontinuity): every valid pixel
    gets the plane's label. A second plane behind a depth jump keeps its own."""
    from sqjax.scenes import default_camera

    H, W = 480, 640
    sigma = 0.002
    r = np.mgrid[:H, :W][0]
    depth = 5.0 + 0.001 * r - 5 * sigma * (r % 4 != 0) + np.random.default_rng(0).normal(0, sigma, (H, W))
    depth[:, W // 2 :] += 1.0  # the right half: another surface, a metre behind
    image = RangeImage(depth, default_camera((H, W)))
    seg = segment(image, noise=sigma)
    assert seg.stats["subsample"] == 4 and len(seg.parts) == 2
    left, right = seg.labels[:, : W // 2 - 8], seg.labels[:, W // 2 + 8 :]  # beyond two working pixels of the jump
    assert np.all(left == left[0, 0]) and np.all(right == right[0, 0]) and left[0, 0] != right[0, 0] > 0


def test_a_full_size_frame_keeps_the_labels_its_working_image_carried():
    """mOSD learn33 at 640 x 480 (segmented at 160 x 120): a working pixel labelled by propagation or out
    of its model's reach by the free-space test still lends its label to the full-size pixels around it
    that no model explains (they were left unlabelled: a tenth of the table, a third of one object,
    and one object fewer correct than at 160 x 120); and the full-size pixels that no model explains
    but whose working pixel its own model explains are joined along the full-size surface
    (`_fill_footprint`: 3% of the valid pixels here, the Kinect's depth bands striping the table). The
    full-size labels cover at least the surface the working labels cover, and score as they do on the
    working grid."""
    image = sqjax.read_range_image(data_path("mosd", "learn", "learn33.pcd"))
    work = image.subsample(4)
    seg_full, seg_work = segment(image), segment(work)
    assert seg_full.stats["subsample"] == 4 and seg_full.labels.shape == image.shape
    truth = mosd_truth(work.labels)
    on_grid = seg_full.labels[::4, ::4]
    assert hoover(truth, on_grid).correct == hoover(truth, seg_work.labels).correct
    covered = (seg_full.labels > 0)[image.valid].mean()
    assert covered >= (seg_work.labels > 0)[work.valid].mean()


def test_noise_exponent_from_the_depth_at_several_depths():
    """The depth's second differences binned by depth recover sigma ~ z^k (k = 2 and 0) on a sloped,
    curved surface spanning depths 2-6 with the edges of a few steps in it; a surface at one depth has
    no slope to read."""
    from sqjax.domain import depth_noise_exponent

    H, W = 120, 160
    v, u = np.mgrid[0:H, 0:W]
    surface = 2.0 + 4.0 * v / (H - 1) + 0.3 * np.sin(u / 9.0) + 0.5 * (u > 100)  # a slope, waves, a step
    cam = PinholeCamera(W, W, (W - 1) / 2, (H - 1) / 2)
    rng = np.random.default_rng(0)
    for k in (2.0, 0.0):
        depth = surface + 1.4e-3 * surface**k * rng.standard_normal((H, W))
        assert abs(depth_noise_exponent(RangeImage(depth, cam)) - k) <= 0.2 * max(k, 1.0)
    flat = RangeImage(5.0 + 1e-3 * rng.standard_normal((H, W)), cam)
    assert depth_noise_exponent(flat) == 0.0


def test_cloud_noise_is_the_residual_at_the_scale_of_a_part():
    """A plane sampled at 1 cm with white noise 1 mm: the cloud's noise is 1 mm within 10%. With an
    error correlated along the surface added (waves of 3 cm to 1 m, amplitude growing as the square
    root of the wavelength, as registration or stereo leave), the residual grows with the patch, and
    the noise follows it: within 20% of the residual that patches of `PART_WINDOWS` seed windows (what
    a part sees) leave, and over 1.5 times the white noise."""
    from scipy.spatial import cKDTree

    from sqjax.domain import PART_WINDOWS, _patch_residuals, cloud_noise

    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(120), np.arange(120)), -1).reshape(-1, 2) * 0.01
    white = 1e-3 * rng.standard_normal(len(grid))
    field = np.zeros(len(grid))
    for wave in np.geomspace(0.03, 1.0, 60):
        angle, phase = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
        field += np.sqrt(wave) * np.sin(2 * np.pi * grid @ [np.cos(angle), np.sin(angle)] / wave + phase)
    field *= 5e-3 / field.std()
    flat = cloud_noise(np.c_[grid, white], 48)
    assert abs(flat / 1e-3 - 1) < 0.1, flat
    cloud = np.c_[grid, white + field]
    _, nn = cKDTree(cloud).query(cloud[::50], PART_WINDOWS * 48)
    part_scale = np.quantile(_patch_residuals(cloud[nn]), 0.25)
    noise = cloud_noise(cloud, 48)
    assert 0.8 < noise / part_scale < 1.2 and noise > 1.5 * flat, (noise, part_scale, flat)


def test_cloud_noise_is_a_property_of_the_points_not_of_their_rows():
    """The same surface read from another file: its rows shuffled, three rows dropped (NaN rows a
    reader skipped), in millimetres. The noise estimate is the same (dropped rows: within 2%; it
    moved by 29% when the patches were every (P / samples)-th row), and it scales with the unit."""
    from sqjax.domain import cloud_noise

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(80), np.arange(80)), -1).reshape(-1, 2) * 0.01
    cloud = np.c_[grid, 0.2 * (grid[:, 0] - 0.4) ** 2 + 1e-3 * rng.standard_normal(len(grid))]
    base = cloud_noise(cloud, 48)
    assert cloud_noise(cloud[rng.permutation(len(cloud))], 48) == pytest.approx(base, rel=1e-9)
    assert cloud_noise(cloud * 1000.0, 48) == pytest.approx(1000.0 * base, rel=1e-6)
    assert cloud_noise(np.delete(cloud, [5, 10, 20], 0), 48) == pytest.approx(base, rel=0.02)


def test_segmentation_recovers_a_z_squared_noise_model():
    """Six fronto-parallel walls side by side at depths 2 to 8 with Kinect-like noise sigma = 1.4e-3 z^2:
    estimated from the image (noise_exponent=None), k is within 20% of 2."""
    H, W = 90, 120
    band = np.arange(W) * 6 // W
    z = np.geomspace(2.0, 8.0, 6)[band]
    depth = np.repeat(z[None], H, 0)
    depth = depth + 1.4e-3 * depth**2 * np.random.default_rng(0).standard_normal((H, W))
    image = RangeImage(depth, PinholeCamera(W, W, (W - 1) / 2, (H - 1) / 2), np.repeat(band[None] + 1, H, 0))
    seg = segment(image, noise_exponent=None)
    assert abs(seg.stats["noise_exponent"] - 2.0) <= 0.4, seg.stats
    # (The walls themselves over-segment: face-on planes are the thin-slab weakness of the size-weighted
    # fit, issue 14, which the noise model does not touch.)


def test_a_model_in_front_of_the_data_violates_free_space():
    """Two slabs explain a fronto-parallel wall equally well by eq. 10: one behind its surface (the
    solid seen from its front), one in front of it (explaining it with its far face). The camera saw
    through the second one: it fills the free space in front of every wall pixel it covers; the first
    one fills none."""
    from sqjax.segmentation import workspace
    from sqjax.visibility import free_space_violations

    image = RangeImage(np.full((40, 40), 5.0), PinholeCamera(40, 40, 19.5, 19.5))
    ws = workspace(image, sqjax.SegmentOptions.create(noise=0.01, rings=4))
    dom, centre = ws.dom, ws.centre
    half = 0.1

    def slab(z):  # a 2 x 2 x 0.2 box centred at depth z, in the workspace's centred frame
        return np.r_[np.log([1.0, 1.0, half]), 0.1, 0.1, 0.0, 0.0, 0.0, np.array([0.0, 0.0, z]) - centre]

    behind, in_front = slab(5.0 + half), slab(5.0 - half)
    v = free_space_violations(ws, np.stack([behind, in_front]))
    covered = np.sum(np.all(np.abs(dom.points[:, :2]) < 1.0, 1))  # wall pixels in the slab's footprint
    assert v[0] == 0 and v[1] >= 0.9 * covered > 0, (v, covered)
    assert np.array_equal(free_space_violations(ws, np.stack([behind, in_front]), box=True), v)
    # a bar 40 m long and 0.1 m thick across the rays, 0.3 m in front of the wall: the bounding sphere's
    # chord samples it every 2.5 m; the box's chord (`box=True`, what `part_volumes` scores with) across
    # its 0.1 m, so each wall pixel behind it counts. One behind the camera contradicts nothing.
    bar = np.r_[np.log([20.0, 0.1, 0.05]), 0.1, 0.1, 0.0, 0.0, 0.0, np.array([0.0, 0.0, 4.7]) - centre]
    behind_camera = bar.copy()
    behind_camera[10] = -1.0 - centre[2]
    v = free_space_violations(ws, np.stack([bar, behind_camera]), box=True)
    row = np.sum(np.abs(dom.points[:, 1]) < 0.1 * 4.7 / 5.0)  # wall pixels in the bar's shadow
    assert v[0] >= 0.9 * row > 0 and v[1] == 0, (v, row)
    assert free_space_violations(ws, np.stack([bar]))[0] < 0.5 * row  # what the sphere's chord sees


def test_a_model_where_the_camera_saw_nothing_violates_free_space():
    """Pixels with no return are free space along their whole ray: a box beside the observed wall patch,
    where every pixel is empty, is hit by the empty rays its silhouette covers; a box behind the wall,
    inside the patch's silhouette, by none."""
    from sqjax.segmentation import workspace
    from sqjax.visibility import void_violations

    depth = np.full((40, 40), np.nan)
    depth[10:30, 10:30] = 5.0
    image = RangeImage(depth, PinholeCamera(40, 40, 19.5, 19.5))
    ws = workspace(image, sqjax.SegmentOptions.create(noise=0.01, rings=4))

    def box(x, z):  # a 0.6 x 0.6 x 0.2 box centred at (x, 0, z), in the workspace's centred frame
        return np.r_[np.log([0.3, 0.3, 0.1]), 0.1, 0.1, 0.0, 0.0, 0.0, np.array([x, 0.0, z]) - ws.centre]

    # the wall spans x in [-1.25, 1.35] at depth 5.2; the second box covers about 5 x 5 empty pixels
    v = void_violations(ws, np.stack([box(0.0, 5.2), box(2.0, 5.2)]))
    assert v[0] == 0 and v[1] >= 10, v


def test_a_table_is_not_merged_with_its_legs():
    """One box from the table top down to the floor holds the top on its top face and the front legs on
    its side: the union fit explains both pieces, but it fills the space between the legs where the
    camera saw nothing. The merge checks visibility, so top and legs stay separate parts."""
    from sqjax.scenes import multipart_scene

    image, parts = multipart_scene(7, "table")
    seg = segment(image)
    score = hoover(image.labels, seg.labels)
    assert score.under == 0 and score.correct >= 4, score


def test_a_cup_seen_into_is_one_union():
    """A thin-walled cup (a tube with a bottom) on a table, seen from 35 degrees above: the camera sees
    its inner wall and bottom through its opening, that is through the solid cylinder that describes
    the cup, so visibility alone refuses to explain the inside by the cup's model and the cup stays
    two parts, its outside and its inside. The merge judges a union that the camera sees mostly from
    outside as hollow (`postprocess._hollow`): the cup's two pieces are joined. A union of the table
    with either piece (a box whose far faces would explain the table, seen through it) is refused."""
    import trimesh

    import sqjax.postprocess as post
    from sqjax.hypotheses import Models
    from sqjax.raycast import render
    from sqjax.scenes import _rx, default_camera
    from sqjax.segmentation import workspace

    turn = _rx(np.radians(35)) @ np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # z up -> camera

    def placed(mesh, z):
        mesh.apply_translation((0.0, 0.0, z))
        mesh.vertices = np.asarray(mesh.vertices) @ turn.T + (0.0, 0.0, 6.0)
        return mesh

    wall = placed(trimesh.creation.annulus(r_min=0.39, r_max=0.4, height=0.6), 0.3)
    bottom = placed(trimesh.creation.cylinder(radius=0.39, height=0.02), 0.01)
    table = placed(trimesh.creation.box((3.0, 2.0, 0.1)), -0.05)
    image = render([table, wall, bottom], default_camera(), (120, 160), noise=0.003)
    ws = workspace(image, sqjax.SegmentOptions.create(noise=0.003))
    label = image.labels.ravel()[ws.dom.index]
    up = (ws.host_points + ws.centre - (0.0, 0.0, 6.0)) @ turn  # back in the table's frame
    outside = (label == 2) & (np.hypot(up[:, 0], up[:, 1]) > 0.395)
    regions = np.stack([label == 1, outside, (label >= 2) & ~outside])  # the table, the cup's outside, inside
    assert regions.sum(1).min() > 50, regions.sum(1)
    idx = [np.flatnonzero(r) for r in regions]
    theta = ws.fit(idx, None)
    d = [ws.distances(theta[[i]], np.zeros(r.size, np.int64), r)[0] for i, r in enumerate(idx)]
    models = Models(theta, regions, d)
    found = post._union_hypotheses(ws, models, [(0, 1), (0, 2), (1, 2)], keep_fraction=0.9)
    assert set(found) == {(1, 2)}, set(found)
    cup = regions[1] | regions[2]
    assert found[(1, 2)][1][cup].mean() >= 0.9


def test_a_union_is_judged_at_its_bounded_volume(monkeypatch):
    """A wall seen in two pieces, with no return around it: one slab explains both. A union fit is free
    behind the surface and beside it where no point constrains it; a slab 2 m deep and about twice the wall's
    size passes through the empty rays around the wall and fails the merge's visibility test. The merge
    refits such a union with the size bound and judges it by that volume: the pieces are joined."""
    import sqjax.postprocess as post
    from sqjax.hypotheses import Models
    from sqjax.segmentation import workspace
    from sqjax.visibility import void_violations

    depth = np.full((40, 40), np.nan)
    depth[12:28, 6:34] = 5.0
    ws = workspace(RangeImage(depth, PinholeCamera(40, 40, 19.5, 19.5)), sqjax.SegmentOptions.create(noise=0.01))
    P = ws.host_points + ws.centre
    left = P[:, 0] < 0.0

    def slab(x, half_width, half_height, half_depth):  # behind the wall's surface (depth 5), centred frame
        centre = np.array([x, 0.0, 5.0 + half_depth]) - ws.centre
        return np.r_[np.log([half_width, half_height, half_depth]), 0.1, 0.1, 0.0, 0.0, 0.0, centre]

    # the wall: x in [-1.69, 1.69], y in [-0.94, 0.94]
    parts = np.stack([slab(-0.85, 0.86, 0.95, 0.05), slab(0.85, 0.86, 0.95, 0.05)])
    regions = np.stack([left, ~left])
    models = Models(
        parts,
        regions,
        [ws.distances(parts[[i]], np.zeros(r.sum(), np.int64), np.flatnonzero(r))[0] for i, r in enumerate(regions)],
    )
    swollen = slab(0.0, 3.0, 2.0, 1.0)  # explains the wall with its front face, fills the void around it
    everyone = np.arange(ws.P)
    d_swollen = ws.distances(swollen[None], np.zeros(ws.P, np.int64), everyone)[0]
    assert np.mean(d_swollen < ws.tau) > 0.95  # it explains both pieces
    assert void_violations(ws, swollen[None])[0] > 0.1 * ws.P  # and the camera saw through it
    monkeypatch.setattr(
        post, "fit_best", lambda ws, unions, multistart: (swollen[None].copy(), [d_swollen], np.ones(1))
    )
    found = post._union_hypotheses(ws, models, [(0, 1)], keep_fraction=0.9)
    assert (0, 1) in found
    theta, region, _ = found[(0, 1)]
    assert region.mean() > 0.9 and void_violations(ws, theta[None])[0] <= 0.1 * region.sum()


def test_part_volumes_are_the_parts_not_what_growth_extrapolated():
    """A table (top and four legs, one view): growth leaves legs metres long whose far ends lie outside
    the view, and a top thicker and wider than the truth. `part_volumes` refits each final model to its
    part's points and keeps the candidate the observations contradict least, the smallest among equals:
    the labels stay, the matched parts' models come near the truth."""
    from sqjax.scenes import multipart_scene

    image, truth = multipart_scene(0, "table")
    seg, grown = segment(image), segment(image, part_volumes=False)
    assert np.array_equal(seg.labels, grown.labels)
    pairs = hoover(image.labels, seg.labels, tolerance=0.8).correct_pairs
    assert len(pairs) >= 3

    def ious(s):
        return np.array([volume_iou(truth[m - 1], s.parts[n - 1].superquadric, n=20_000) for m, n in pairs])

    iou, before = ious(seg), ious(grown)
    # the top near the truth (its thickness is seen only at its rim: IoU 0.55-0.80 as float rounding
    # differs between CPUs, 0.46-0.54 before); the legs, 2-3 px wide, of about their length (before:
    # up to 900 m long, IoU 0-0.34): none worse by more than 0.05, the mean gain at least 0.1
    assert iou.max() > 0.5 and np.all(iou >= before - 0.05), (iou, before)
    assert np.mean(iou - before) > 0.1, (iou, before)
    extent = max(float(np.max(np.asarray(t.size))) for t in truth)
    assert all(float(np.max(np.asarray(seg.parts[n - 1].superquadric.size))) < 2 * extent for _, n in pairs)
    for i, p in enumerate(seg.parts):  # regions: labelled points it explains
        assert p.num_explained == p.region.size <= p.num_points == np.sum(seg.labels == i + 1)
        assert np.all(seg.labels.ravel()[p.region] == i + 1)


def test_kernel_calls_cover_every_row_once_with_little_padding():
    """Kernel calls (`padding.calls`: the pair kernels', the fit kernel's on CPU) cover rows 0..E-1
    once, in order, each call of a compiled size; at most half of a call is padding unless it is the
    smallest size, and a large E is cut into full calls of the largest."""
    for E in (1, 1000, 1024, 1025, 3000, 5000, 16385, 40000, 100000, 250001):
        made = list(calls(E))
        starts = [s for s, _ in made]
        assert starts == list(np.cumsum([0] + [n for _, n in made[:-1]])), (E, made)
        assert all(n in PAIR_SIZES for _, n in made) and made[-1][0] + made[-1][1] >= E > made[-1][0]
        for s, n in made:
            assert n == PAIR_SIZES[0] or 2 * min(n, E - s) >= n, (E, made)
    assert [n for _, n in calls(5000)] == [4096, 1024]
    assert [n for _, n in calls(100000)][:3] == [PAIR_SIZES[-1]] * 3
    assert [n for _, n in calls(17, (4, 16))] == [16, 4] and [n for _, n in calls(5, (4, 16))] == [4, 4]


def test_each_segmentation_kernel_compiles_once_per_padded_shape():
    """Every jitted kernel that segmentation calls is fed padded shapes (`sqjax.padding`): over three
    scenes, two of one size and one of another, each holds no more compiled variants than its padding
    policy allows (a guard against a kernel that recompiles per growth step, per number of hypotheses
    or per scene)."""
    import jax

    from sqjax import chart, initial, solver, visibility, workspace

    from helpers import compiled_variants

    kernels = {  # kernel: most variants over the three scenes
        "fit": (solver.fit_padded, 6),  # N in {128, max_points} x (warm start: 2 call sizes, multistart: 1)
        "pair distances": (workspace._pair_distances, len(PAIR_SIZES) * 2),  # call sizes x 2 point-row sizes
        "free space": (visibility._free_space, len(PAIR_SIZES) * 2),
        "free space (box)": (visibility._free_space_box, len(PAIR_SIZES) * 2),
        "models to the world": (chart._world, 5),  # powers of two >= 8 up to the hypotheses of a scene
        "volumes": (chart._volumes, 5),
        "starts' rotations": (initial._log_rotations, 6),  # powers of two >= 32 up to the seed count
    }
    jax.clear_caches()
    for seed, shape in ((1, (120, 160)), (2, (120, 160)), (3, (96, 128))):
        image, _ = random_scene(seed, n_parts=(2, 4), shape=shape, noise=0.005)
        segment(image)
    made = {name: compiled_variants(fn) for name, (fn, _) in kernels.items()}
    assert all(made[name] <= most for name, (_, most) in kernels.items()), made
    assert made["fit"] >= 1 and made["pair distances"] >= 1, made  # the counter sees the kernels


def test_a_point_the_camera_saw_through_a_model_is_not_explained_by_it():
    """Visibility (`ExtraOptions.visibility`, issue 11): two slabs explain a fronto-parallel wall
    equally well by eq. 10, one behind its surface and one in front of it (with its back face). The
    camera saw through the second to every wall pixel it covers, so it explains none of them; the
    first explains them all. Rays that only graze a model are not seen through: a cylinder whose
    model is too wide by half the admission distance still explains all of its rim."""
    from sqjax.raycast import render
    from sqjax.segmentation import workspace
    from sqjax.superquadric import Superquadric

    image = RangeImage(np.full((40, 40), 5.0), PinholeCamera(40, 40, 19.5, 19.5))
    half = 0.1

    def slab(ws, z):  # a 2 x 2 x 0.2 box centred at depth z, in the workspace's centred frame
        return np.r_[np.log([1.0, 1.0, half]), 0.1, 0.1, 0.0, 0.0, 0.0, np.array([0.0, 0.0, z]) - ws.centre]

    for visibility in (True, False):
        ws = workspace(image, sqjax.SegmentOptions.create(noise=0.01, rings=4, visibility=visibility))
        covered = np.flatnonzero(np.all(np.abs(ws.dom.points[:, :2]) < 0.95, 1))  # the slabs' footprint
        theta = np.stack([slab(ws, 5.0 + half), slab(ws, 5.0 - half)])
        model = np.repeat([0, 1], covered.size)
        d, _, away = ws.distances(theta, model, np.tile(covered, 2))
        behind, in_front = d[: covered.size], d[covered.size :]
        assert np.all(behind < ws.tau) and not away[: covered.size].any()
        assert away[covered.size :].all()  # the wall lies on the slab's back face
        if visibility:
            assert np.all(np.isinf(in_front))
            # the test only below `within`: the same below it, the plain distance (< tau) above
            near, _, _ = ws.distances(
                theta, model, np.tile(covered, 2), within=np.r_[np.full(covered.size, np.inf), np.zeros(covered.size)]
            )
            assert np.array_equal(near[: covered.size], behind) and np.all(near[covered.size :] < ws.tau)
        else:
            assert np.all(in_front < ws.tau)  # eq. 10 alone: explained from behind
    # a lying cylinder (radius 0.3): its model 0.5 tau too wide contains every observed point, and
    # the rays to the rim pass through its solid, but never deeper than 0.5 tau
    from sqjax.visibility import seen_through

    cylinder = Superquadric.create([0.3, 0.3, 0.8], [0.1, 1.0], euler=[0.0, np.pi / 2, 0.0], translation=[0, 0, 5])
    image = render([cylinder], PinholeCamera(40, 40, 19.5, 19.5), (40, 40))
    ws = workspace(image, sqjax.SegmentOptions.create(noise=0.005, rings=4))
    r = 0.3 + ws.tau / 2
    wide = np.r_[np.log([r, r, 0.8]), 0.1, 1.0, 0.0, np.pi / 2, 0.0, np.array([0.0, 0.0, 5.0]) - ws.centre]
    everywhere = np.zeros(ws.P, np.int64)
    assert not seen_through(ws, wide[None], everywhere, np.arange(ws.P)).any()
    d, _, _ = ws.distances(wide[None], everywhere, np.arange(ws.P))
    assert np.all(d < ws.tau)
    # the same test on the slab in front of the wall sees through it
    assert seen_through(ws, slab(ws, 5.0 - 0.3 - 0.15)[None], everywhere, np.arange(ws.P)).mean() > 0.5


def test_surface_seeds_follow_a_strip_no_window_fits():
    """Seeds grown along the adjacency (issue 11): on a strip three pixels wide, cut from the block
    around it, every seed has min_seed_points points of the strip, starts off the covered points,
    and the seeds cover the strip."""
    from sqjax.domain import OFFSETS
    from sqjax.seeds import surface_seeds

    H, W, min_seed = 12, 40, 22
    strip = np.zeros((H, W), bool)
    strip[5:8, 2:38] = True
    nb = -np.ones((H * W, len(OFFSETS)), np.int64)
    for r in range(H):
        for c in range(W):
            for k, (dr, dc) in enumerate(OFFSETS):
                r2, c2 = r + dr, c + dc
                if 0 <= r2 < H and 0 <= c2 < W and strip[r, c] == strip[r2, c2]:  # the strip's edge is a cut
                    nb[r * W + c, k] = r2 * W + c2
    covered = ~strip.ravel()  # the block around it is covered by windows
    seeds = surface_seeds(nb, covered, min_seed)
    assert len(seeds) >= 3
    for ids in seeds:
        assert ids.size == min_seed and strip.ravel()[ids].all()
    reached = np.zeros(H * W, bool)
    for ids in seeds:
        reached[ids] = True
    assert reached[strip.ravel()].mean() > 0.8


def test_thin_bent_legs_no_window_fits_are_found():
    """Two legs three pixels wide, joined at a knee, in front of a wall: no seed window fits in them
    and the pair is no one superquadric; seeds that follow the surface find both."""
    from sqjax.raycast import render
    from sqjax.scenes import default_camera

    def leg(angle, end, length=0.6, r=0.04):
        d = np.array([np.cos(angle), np.sin(angle), 0.0])
        R = np.stack([np.array([0.0, 0.0, 1.0]), np.cross(d, [0.0, 0.0, 1.0]), d], 1)
        return Superquadric.create(
            size=(r, r, length / 2), epsilon=(0.3, 1.0), rotation=R, translation=end + d * length / 2
        )

    wall = Superquadric.create(size=(3.0, 3.0, 0.1), epsilon=(0.2, 0.2), translation=(0.0, 0.0, 5.2))
    knee = np.array([0.1, 0.0, 4.0])
    image = render(
        [wall, leg(np.deg2rad(200), knee), leg(np.deg2rad(-70), knee)], default_camera(), (120, 160), noise=0.002
    )
    assert [(image.labels == i).sum() for i in (2, 3)] == [75, 75]  # pixels of each leg
    without = hoover(image.labels, segment(image, surface=False).labels)
    found = hoover(image.labels, segment(image).labels)
    assert without.correct == 1 and found.correct == 3, (without.to_dict(), found.to_dict())


def test_a_model_whose_own_points_cannot_determine_it_is_pruned():
    """After the final selection a model must explain, alone, at least min_seed_points points (2 per
    parameter) besides an exclusive share of min_exclusive: a 15-point fragment goes even though all
    its points are its own; a 40-point part and a large one stay."""
    from sqjax.hypotheses import Models
    from sqjax.postprocess import prune_redundant

    P = 1000
    regions = np.zeros((3, P), bool)
    regions[0, :900] = True
    regions[1, 900:940] = True
    regions[2, 940:955] = True
    models = Models(np.zeros((3, 11)), regions, [np.zeros(r.sum(), np.float32) for r in regions])
    assert prune_redundant(models, 0.2) == 0  # every share is exclusive: the share rule keeps all
    assert prune_redundant(models, 0.2, min_points=22) == 1
    assert models.regions.sum(1).tolist() == [900, 40]


def test_an_island_of_a_label_goes_to_the_part_around_it():
    """Where two models nearly coincide, nearest-model labels alternate in blobs. A piece of model 1's
    label enclosed by model 0's label and explained by model 0 over most of it is model 0's surface;
    model 1's largest piece stays, and so does an island that model 0 explains at only half its pixels
    or that touches a third label."""
    from sqjax.labelling import _join_islands
    from sqjax.segmentation import workspace

    image = RangeImage(np.full((24, 24), 5.0), PinholeCamera(24, 24, 11.5, 11.5))
    ws = workspace(image, sqjax.SegmentOptions.create(noise=0.01))
    grid = np.zeros((24, 24), np.int64)
    grid[:, :6] = 1  # model 1's own piece, along the border
    grid[10:13, 14:17] = 1  # an island inside model 0's label
    grid[2:4, 14:16] = 1  # an island that model 0 does not explain at two of its four pixels
    grid[6:8, 18:20] = 1  # an island that model 0 does not explain at one of its four pixels
    grid[18:21, 12:15] = 1  # an island touching model 2's label
    grid[18:21, 15:18] = 2
    best = grid.ravel()[ws.dom.index].copy()
    has = np.ones(ws.P, bool)
    near = np.zeros((3, ws.P))
    near[2] = np.where(best == 2, 0.0, np.inf)
    for r, c in ((2, 14), (3, 15), (6, 18)):  # the pixels' flat index = their point index
        near[0, np.ravel_multi_index((r, c), (24, 24))] = np.inf
    _join_islands(ws, best, has, near)
    out = best.reshape(24, 24)
    assert (out[:, :6] == 1).all()
    assert (out[10:13, 14:17] == 0).all() and (out[6:8, 18:20] == 0).all()
    assert (out[2:4, 14:16] == 1).all() and (out[18:21, 12:15] == 1).all()
    assert np.array_equal(out[grid != 1], grid[grid != 1])


@pytest.mark.parametrize("M", [1, 7, 8, 9, 23])
def test_pack_rows_is_packbits_over_rows(M):
    """Growth's dilation packs regions 8 to a byte with shifted ORs: the same bytes as numpy's packbits."""
    from sqjax.domain import pack_rows

    rows = np.random.default_rng(M).random((M, 301)) < 0.3
    assert np.array_equal(pack_rows(rows), np.packbits(rows, axis=0))
