"""Figures: the paper's panel sequence (a)-(f) and small helpers for notebooks (host side).

matplotlib is imported inside the functions only, so `import sqjax` never needs it; figures are built
with `matplotlib.figure.Figure` (no pyplot state, any backend). Colours come from
`sqjax.colors.label_colors`, the palette of `labels.png` and the exported meshes.

Model panels of range images are drawn as images: the selected superquadrics are ray cast with the
image's own camera (`sqjax.scenes.render`) and shaded by their surface normals, over the data pixels in
light grey, so a panel lines up pixel for pixel with the range image. Point clouds get 3-D axes.
"""

from __future__ import annotations

import numpy as np

from .colors import colorize_labels, label_colors

_DATA_GREY = 0.86
_EMPTY = 1.0


def _superquadrics(models) -> list:
    return [getattr(m, "superquadric", m) for m in models]


# ----------------------------------------------------------------------------------------------------
# model images (ray cast with the data's camera)


def _shade(points: np.ndarray, orthographic: bool) -> np.ndarray:
    """Lambertian-like shading in [0, 1] from an (H, W, 3) point grid (camera light), NaN-free."""
    # an image one pixel high or wide has no gradient along that axis: flat shading there
    du, dv = (np.gradient(points, axis=a) if points.shape[a] > 1 else np.zeros_like(points) for a in (1, 0))
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
        view = (
            np.broadcast_to([0.0, 0.0, 1.0], points.shape)
            if orthographic
            else points / np.linalg.norm(points, axis=-1, keepdims=True)
        )
        s = np.abs(np.sum(n * view, -1))
    return np.where(np.isfinite(s), s, 0.8)


def _clipped(sqs, resolution, clip):
    """The superquadrics as triangle meshes without the triangles reaching outside the box `clip`
    ((lo, hi) corners (3,), camera frame); None where none is left."""
    import trimesh

    from .mesh import to_trimesh

    out = []
    for sq in sqs:
        m = to_trimesh(sq, resolution)
        v = np.asarray(m.vertices, float)
        keep = ((v[m.faces] >= clip[0]) & (v[m.faces] <= clip[1])).all((1, 2))
        out.append(trimesh.Trimesh(v, np.asarray(m.faces)[keep], process=False) if keep.any() else None)
    return out


def _cast_models(sqs, camera, shape, resolution, clip=None):
    """Ray cast superquadrics: (labels (H, W) int32, shading (H, W) in [0, 1]). `clip`: (lo, hi)
    corners (3,) of a box in the camera frame; the models' triangles reaching outside it are left out
    (a growth model many times the data's size would cover the panel), so a cut model shows its inside."""
    from .rangeimage import OrthographicCamera
    from .raycast import render

    parts, owner = list(sqs), np.arange(len(sqs))
    if clip is not None:
        meshes = _clipped(sqs, resolution, clip)
        owner = np.flatnonzero([m is not None for m in meshes])
        parts = [meshes[i] for i in owner]
    if not parts:
        return np.zeros(shape, np.int32), np.ones(shape)
    r = render(parts, camera, shape, resolution=resolution, refine=False)
    labels = np.r_[0, owner + 1].astype(np.int32)[np.asarray(r.labels)]  # 0 stays 0
    shade = _shade(camera.back_project(r.depth.astype(np.float64)), isinstance(camera, OrthographicCamera))
    return labels, shade


def _paint(labels, shade, colors, valid=None):
    """(H, W, 3) float RGB: shaded model colours with dark outlines, data pixels grey, the rest white."""
    H, W = labels.shape
    rgb = np.full((H, W, 3), _EMPTY)
    if valid is not None:
        rgb[np.asarray(valid, bool)] = _DATA_GREY
    hit = labels > 0
    if not hit.any():
        return rgb
    base = np.asarray(colors, float)[np.maximum(labels - 1, 0)] / 255.0
    lit = base * (0.35 + 0.65 * shade[..., None])
    edge = np.zeros((H, W), bool)  # thin dark outlines where the front model changes
    edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edge[1:, :] |= labels[1:, :] != labels[:-1, :]
    lit = np.where((edge & hit)[..., None], lit * 0.45, lit)
    rgb[hit] = lit[hit]
    return rgb


def render_models(models, camera, shape, *, colors=None, valid=None, resolution: int = 24, clip=None):
    """Ray cast superquadrics with `camera` into an `(H, W, 3)` float RGB image and `(H, W)` labels.

    **Arguments:**
    - `models`: `Superquadric`s (or `segment.Part`s), camera frame. `shape`: (H, W).
    - `colors`: `(len(models), 3)` uint8, default `label_colors(len(models))`.
    - `valid`: optional `(H, W)` bool data mask, drawn light grey where no model is in front.
    - `clip`: optional `(lo, hi)` corners `(3,)` of a box (camera frame): the models are cut there.

    **Returns:** `(rgb, labels)`; labels as `sqjax.scenes.render` (0 = no model, i + 1 = models[i]).
    """
    sqs = _superquadrics(models)
    labels, shade = _cast_models(sqs, camera, tuple(shape), resolution, clip)
    colors = label_colors(len(sqs)) if colors is None else colors
    return _paint(labels, shade, colors, valid), labels


def _match_colors(model_labels: np.ndarray, final_labels: np.ndarray, n_models: int, n_final: int) -> np.ndarray:
    """Colour indices for intermediate models: a model takes the colour of the final part whose pixels it
    overlaps most (greedy one-to-one), the others colours after the final parts'."""
    both = (model_labels > 0) & (final_labels > 0)
    O = np.zeros((n_models + 1, n_final + 1), np.int64)  # noqa: E741  (overlap counts, as in evaluate.hoover)
    np.add.at(O, (model_labels[both], final_labels[both]), 1)
    O = O[1:, 1:]  # noqa: E741
    out = -np.ones(n_models, np.int64)
    used = np.zeros(n_final, bool)
    for flat in np.argsort(-O, axis=None, kind="stable"):
        i, j = divmod(int(flat), max(n_final, 1))
        if n_final == 0 or O[i, j] == 0:
            break
        if out[i] < 0 and not used[j]:
            out[i], used[j] = j, True
    free = np.flatnonzero(out < 0)
    out[free] = n_final + np.arange(free.size)
    return out


# ----------------------------------------------------------------------------------------------------
# 3-D drawing (point clouds, notebooks)


def _to_plot(p):
    """Camera frame (x right, y down, z forward) -> plot frame (x right, depth into the page, up)."""
    p = np.asarray(p, float)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], -1)


def _equal_3d(ax, pts):
    pts = pts[np.isfinite(pts).all(-1)]
    if len(pts) == 0:
        return
    lo, hi = pts.min(0), pts.max(0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-9)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))


def draw_superquadrics(
    ax, models, colors=None, *, resolution: int = 20, alpha: float = 0.85, frame: str = "camera", clip=None
):
    """Add shaded meshes of superquadrics to a 3-D axes. `frame="camera"` maps camera coordinates to a
    y-up view (as `figure_sequence` does); `"world"` plots x, y, z as they are. `clip`: (lo, hi) corners
    (3,) of a box in the plotted frame; triangles reaching outside it are left out (3-D axes do not
    clip, and a growth model many times the data's size would cover the panel)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from .mesh import to_trimesh

    sqs = _superquadrics(models)
    colors = label_colors(len(sqs)) if colors is None else np.asarray(colors)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    verts_all = []
    for sq, c in zip(sqs, colors):
        m = to_trimesh(sq, resolution)
        v = _to_plot(m.vertices) if frame == "camera" else np.asarray(m.vertices, float)
        tris = v[m.faces]
        if clip is not None:
            tris = tris[((tris >= clip[0]) & (tris <= clip[1])).all((1, 2))]
        n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        s = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
        fc = np.concatenate([(np.asarray(c, float)[None] / 255.0) * s[:, None], np.full((len(s), 1), alpha)], 1)
        ax.add_collection3d(Poly3DCollection(tris, facecolors=fc, edgecolors="none"))
        verts_all.append(tris.reshape(-1, 3))
    return np.concatenate(verts_all) if verts_all else np.zeros((0, 3))


FAR_QUANTILE = 0.005
"""The 3-D point panels span the points between these quantiles of each axis (and as much again around
them, `_bulk`): a few flying pixels metres behind a table top (RealSense, stereo) would shrink the scene
to a dot."""


def _bulk(pts: np.ndarray) -> np.ndarray:
    """(P,) bool: the finite points (P, 3) inside the box of the `FAR_QUANTILE` .. 1 - `FAR_QUANTILE`
    quantiles of each axis, widened by that box's size on each side."""
    pts = np.asarray(pts, float)
    ok = np.asarray(np.isfinite(pts).all(-1))
    if not ok.any():
        return ok
    lo, hi = np.quantile(pts[ok], [FAR_QUANTILE, 1.0 - FAR_QUANTILE], axis=0)
    span = hi - lo
    return ok & np.asarray(((pts >= lo - span) & (pts <= hi + span)).all(-1))


def _box(pts: np.ndarray) -> np.ndarray:
    """(2, 3): the box of the points (P, 3) with a fifth of its size around (where the model panels cut
    the models)."""
    lo, hi = pts.min(0), pts.max(0)
    return np.stack([lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo)])


def _far_note(far: int) -> str:
    """A panel title's note of the points `_bulk` leaves out."""
    return f"\n{far} far point{'s' if far != 1 else ''} not drawn" if far else ""


def _scatter(ax, pts, c, *, cmap=None, max_points=6000, size=1.0, keep=None):
    """Scatter at most `max_points` of the finite points (P, 3) (of those in `keep` (P,) bool, if given),
    evenly strided; returns them in the plot frame."""
    pts = np.asarray(pts, float)
    keep = np.isfinite(pts).all(-1) if keep is None else keep & np.isfinite(pts).all(-1)
    idx = np.flatnonzero(keep)
    if idx.size > max_points:
        idx = idx[np.linspace(0, idx.size - 1, max_points).astype(np.int64)]
    c = np.asarray(c)[idx] if np.ndim(c) and len(c) == len(pts) else c
    ax.scatter(*_to_plot(pts[idx]).T, c=c, cmap=cmap, s=size, linewidths=0, depthshade=False)
    return _to_plot(pts[idx])


def _style_3d(ax):
    ax.view_init(elev=18, azim=-72)
    ax.set_xticklabels([])
    ax.set_yticklabels([])
    ax.set_zticklabels([])
    ax.set_xlabel("x")
    ax.set_ylabel("z (depth)")
    ax.set_zlabel("-y")


def plot_fit(points, fitted, truth=None, *, ax=None, resolution: int = 20):
    """3-D view of a point set with its fitted superquadric (and the true one as a wireframe).

    Coordinates are plotted as they are (x, y, z). Returns the axes (a new `Figure` when `ax` is None).
    """
    from matplotlib.figure import Figure

    from .mesh import surface_grid

    if ax is None:
        ax = Figure(figsize=(5, 5)).add_subplot(projection="3d")
    pts = np.asarray(points, float)
    ax.scatter(*pts.T, s=2, c="k", linewidths=0, depthshade=False)
    allv = [pts, draw_superquadrics(ax, [fitted], label_colors(1), resolution=resolution, alpha=0.45, frame="world")]
    if truth is not None:
        g = surface_grid(truth, resolution)
        ax.plot_wireframe(g[..., 0], g[..., 1], g[..., 2], color="tab:red", linewidth=0.5, rstride=2, cstride=2)
        allv.append(g.reshape(-1, 3))
    _equal_3d(ax, np.concatenate(allv))
    return ax


# ----------------------------------------------------------------------------------------------------
# the paper's sequence


def _history_panels(segmentation):
    """(title, models) of the three model panels: after the first selection, midway, final."""
    hist = list(segmentation.history)
    final = [p.superquadric for p in segmentation.parts]
    plural = lambda n, w: f"{n} {w}{'s' if n != 1 else ''}"
    if not hist:
        return [
            ("after the first selection: none", []),
            ("midway: none", []),
            (f"final: {plural(len(final), 'part')}", final),
        ]
    mid = len(hist) // 2
    return [
        (f"after the first selection: {plural(len(hist[0]), 'model')}", hist[0]),
        (f"midway (selection {mid + 1} of {len(hist)}): {plural(len(hist[mid]), 'model')}", hist[mid]),
        (f"final: {plural(len(final), 'part')}", final),
    ]


def figure_sequence(
    image,
    segmentation,
    path=None,
    *,
    title: str | None = None,
    resolution: int = 24,
    max_points: int = 6000,
    dpi: int = 110,
):
    """The paper's figure sequence for one segmentation, as a `matplotlib.figure.Figure`.

    Range images (a `RangeImage`): (a) the range image, (b) the back-projected points (x, y, z) coloured
    by depth (by `image.colors` when the image has colours: RGB-D frames, coloured PCDs), (c) the models
    after the first selection, (d) midway, (e) the final models, all three ray cast with the image's camera
    over the data (grey), and (f) the label image (as `labels.png`).
    Point clouds (an `(P, 3)` array): the same in 3-D axes, (a) the points coloured by depth and (f) the
    points coloured by label. Final parts use `label_colors`; earlier models take the colour of the
    final part they overlap most. Saved to `path` when given.
    """
    from matplotlib.figure import Figure

    from .rangeimage import RangeImage

    fig = Figure(figsize=(13.5, 8.2), dpi=dpi)
    # fixed margins: matplotlib's constrained layout measured 0.15-0.2 s of the demo's save, with no
    # visible difference for these six panels
    spec = fig.add_gridspec(
        2, 3, left=0.02, right=0.98, bottom=0.02, top=0.91 if title else 0.95, wspace=0.12, hspace=0.18
    )
    panels = _history_panels(segmentation)
    n_final = len(segmentation.parts)

    if isinstance(image, RangeImage):
        H, W = image.shape
        cmap = _depth_cmap()
        ax = fig.add_subplot(spec[0, 0])
        im = ax.imshow(image.depth, cmap=cmap, interpolation="nearest")
        fig.colorbar(im, ax=ax, shrink=0.8, label="depth")
        ax.set_title("(a) range image")
        ax.set_axis_off()
        ax = fig.add_subplot(spec[0, 1], projection="3d")
        pts = image.points.reshape(-1, 3)
        bulk = _bulk(pts)
        if image.colors is not None:  # an RGB-D frame or a coloured PCD: the points in their own colours
            shown = _scatter(ax, pts, image.colors.reshape(-1, 3) / 255.0, max_points=max_points, keep=bulk)
        else:
            shown = _scatter(ax, pts, pts[:, 2], cmap=cmap, max_points=max_points, keep=bulk)
        _equal_3d(ax, shown)
        _style_3d(ax)
        far = int(image.valid.sum() - bulk.sum())
        ax.set_title("(b) points (x, y, z)" + (", in colour" if image.colors is not None else "") + _far_note(far))
        final_labels = np.asarray(segmentation.labels)
        # the models are ray cast no finer than a panel's pixels (a third of the figure's width)
        step = max(1, int(np.ceil(max(H, W) / (fig.get_figwidth() * dpi / 3))))
        small = image.subsample(step)
        box = _box(pts[bulk])
        for k, (name, models) in enumerate(panels):
            ax = fig.add_subplot(spec[(2 + k) // 3, (2 + k) % 3])
            sqs = _superquadrics(models)
            # growth models are cut at the data's box, as in the cloud panels; the final parts are whole
            lab, shade = _cast_models(sqs, small.camera, small.shape, resolution, None if k == 2 else box)
            if k == 2:  # the final parts: the colours of labels.png
                colors = label_colors(n_final)
            else:  # earlier models: the colour of the final part they overlap most
                idx = _match_colors(lab, final_labels[::step, ::step], len(sqs), n_final)  # pyright: ignore[reportArgumentType]
                colors = label_colors(int(idx.max()) + 1)[idx] if idx.size else np.zeros((0, 3))
            rgb = _paint(lab, shade, colors, small.valid)
            ax.imshow(rgb, interpolation="nearest")
            ax.set_title(f"({'cde'[k]}) {name}")
            ax.set_axis_off()
        ax = fig.add_subplot(spec[1, 2])
        rgb = colorize_labels(final_labels, image.valid)
        rgb[~image.valid & (final_labels == 0)] = 255  # white where there is no data, as in the other panels
        ax.imshow(rgb, interpolation="nearest")
        ax.set_title(f"(f) labels: {n_final} part{'s' if n_final != 1 else ''}")
        ax.set_axis_off()
    else:
        pts = np.asarray(image, float)
        cmap = _depth_cmap()
        ax = fig.add_subplot(spec[0, 0], projection="3d")
        bulk = _bulk(pts)
        shown = _scatter(ax, pts, pts[:, 2], cmap=cmap, max_points=max_points, keep=bulk)
        _equal_3d(ax, shown)
        _style_3d(ax)
        far = int(np.isfinite(pts).all(-1).sum() - bulk.sum())
        ax.set_title("(a) points, coloured by depth" + _far_note(far))
        final_labels = np.asarray(segmentation.labels)
        for k, (name, models) in enumerate(panels):
            ax = fig.add_subplot(spec[(1 + k) // 3, (1 + k) % 3], projection="3d")
            colors = (
                label_colors(n_final)
                if k == 2
                else label_colors(len(models) + n_final)[_match_cloud(models, pts, final_labels, n_final)]
            )
            _scatter(ax, pts, [(_DATA_GREY,) * 3], max_points=max_points, size=0.5, keep=bulk)
            box = _box(shown)  # a swollen growth model is cut there
            draw_superquadrics(ax, models, colors, resolution=max(resolution // 2, 8), clip=box)
            _equal_3d(ax, box)
            _style_3d(ax)
            ax.set_title(f"({'bcd'[k]}) {name}")
        ax = fig.add_subplot(spec[1, 1], projection="3d")
        lut = np.concatenate([np.array([[96, 96, 96]], np.uint8), label_colors(n_final)]) / 255.0
        _scatter(ax, pts, lut[final_labels], max_points=max_points, keep=bulk)
        _equal_3d(ax, shown)
        _style_3d(ax)
        ax.set_title(f"(e) labelled points: {n_final} part{'s' if n_final != 1 else ''}")
    if title:
        fig.suptitle(title)
    if path is not None:
        fig.savefig(path)
    return fig


MATCH_POINTS = 20_000
"""`_match_cloud` counts the overlaps of a panel's models with the final parts on at most this many of
a cloud's points (evenly strided). On every point, the figure of a 1.2M-point cloud took 19 s, 15 of
them in this matching (hundreds of models each tested on every point), against 40 s of segmentation."""


def _match_cloud(models, pts, final_labels, n_final):
    """Colour indices of cloud models: the final part whose points they contain most (as `_match_colors`),
    counted on at most `MATCH_POINTS` of the points."""
    import jax.numpy as jnp

    from .superquadric import contains

    sqs = _superquadrics(models)
    if not sqs:
        return np.zeros(0, np.int64)
    stride = max(1, -(-len(pts) // MATCH_POINTS))
    pts, final_labels = pts[::stride], np.asarray(final_labels)[::stride]
    on_device = jnp.asarray(pts, sqs[0].size.dtype)  # once for every model

    lab = np.zeros(len(pts), np.int32)
    best = np.full(len(pts), np.inf)
    # one call per model: one vmapped call over all of them (padded to a power of two) took 0.6 s
    # instead of 0.3 s for 305 models on 20,000 points, the same colours (2026-12-06)
    for i, sq in enumerate(sqs):  # points inside a 10 % enlarged model count as its pixels
        big = type(sq)(sq.size * 1.1, sq.epsilon, sq.rotation, sq.translation, sq.taper, sq.bend)
        inside = np.asarray(contains(big, on_device))
        vol = float(np.prod(np.asarray(sq.size)))
        take = inside & (vol < best)
        lab[take], best[take] = i + 1, vol
    return _match_colors(lab[:, None], np.asarray(final_labels)[:, None], len(sqs), n_final)


def _depth_cmap():
    import matplotlib

    return matplotlib.colormaps["viridis_r"].with_extremes(bad="white")
