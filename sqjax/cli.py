"""The `sqjax` command line: segment range images and point clouds, fit one superquadric, render and score.

Commands (each has `--help`)::

    sqjax demo     [--out DIR]                          a generated scene (Fig. 3 of the paper), no download
    sqjax segment  INPUT [--camera fx,fy,cx,cy | --ortho PIXEL[,cx,cy] | --intrinsics FILE.json]
                   [--color IMAGE] [--depth-scale S] [--subsample STEP] [--noise SIGMA]
                   [-o KEY=VALUE ...] [--out DIR]
    sqjax render   SCENE --out FILE                     SCENE: a paper scene name or random:SEED
    sqjax evaluate RESULT TRUTH [--tolerance 0.8] [--json OUT]
    sqjax fit      POINTS [--json OUT]

`segment` reads range images (`.npz`, `.npy`, 16-bit `.png`, organised `.pcd`) and point clouds
(`.ply`, `.xyz`, `.txt`, unorganised `.pcd`, `(N, 3)` `.npy`, mesh vertices of `.obj` / `.stl`) and
writes into DIR: `models.json` (schema: `sqjax.export`), `labels.npy` (raw int32 labels, 0 = none,
i + 1 = part i), `labels.png` (colour labels) and `labels_id.png` (16-bit label ids; clouds:
`labels.ply`, coloured points), `parts.glb` (glTF, Y-up) and `parts.ply` (camera frame) part meshes
coloured as the labels, and `figure.png` (the paper's panel sequence). RGB-D frames: a 16-bit depth
PNG with `--intrinsics cam.json --depth-scale 1000 [--color rgb.png]`. `--depth-scale` is stored units
per metre and divides (Open3D's convention; values below 1, the old multiplying form, are refused).

Outputs are checked writable before any work, written into a temporary folder and renamed into place
(a failed run leaves no partial file; symlinks in DIR are replaced, never followed). The compiled
kernels are cached on disk (`$XDG_CACHE_HOME/sqjax/jax`, `~/.cache/sqjax/jax` or `$SQJAX_CACHE_DIR`);
`--no-cache` or `SQJAX_NO_CACHE=1` turn that off.

`fit` writes (`--json`) one JSON object, schema version 1::

    {"version": 1, "sqjax_version": str, "input": str,
     "size": [a1, a2, a3],               # half-axes, units of the points
     "epsilon": [e1, e2],                # shape exponents
     "rotation": [[3 x 3]],              # columns = model axes in the points' frame
     "euler_zyz": [phi, theta, psi],     # rad, R = Rz(phi) Ry(theta) Rz(psi)
     "translation": [x, y, z],           # centre
     "taper": [Kx, Ky], "bend": [k, alpha],   # zero unless --deform
     "cost": float,                      # G = sum of squared size-weighted residuals (eq. 9)
     "converged": bool, "num_points": int,
     "rms_distance": float}              # root mean square eq. 10 distance of the points

Bad input (missing or damaged file, unsupported format, bad option) prints one line
`sqjax: error: ...` on stderr and exits with status 2; set SQJAX_DEBUG=1 to see tracebacks.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

EXIT_USAGE = 2
EXIT_FAILURE = 1

_IMAGE_EXTS = (".npz", ".png")
_CLOUD_EXTS = (".ply", ".xyz", ".txt", ".obj", ".stl")
_SUPPORTED = "range images: .npz .npy .png .pcd; point clouds: .ply .xyz .txt .pcd .npy .obj .stl"


class CLIError(ValueError):
    """A user error with a message fit for one line."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports errors in one line: `sqjax: error: ... (see 'sqjax segment --help')`."""

    def error(self, message):
        hint = f" (see '{self.prog} --help')"
        self.exit(EXIT_USAGE, f"sqjax: error: {message}{hint}\n")


# ----------------------------------------------------------------------------------------------------
# argument types


def _floats(text: str, n: tuple[int, ...], what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) not in n or not np.isfinite(vals).all():
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return vals


def _camera_arg(text: str):
    from .rangeimage import PinholeCamera

    fx, fy, cx, cy = _floats(text, (4,), "four numbers fx,fy,cx,cy (pixels)")
    try:
        return PinholeCamera(fx, fy, cx, cy)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _ortho_arg(text: str):
    vals = _floats(text, (1, 3), "PIXEL or PIXEL,cx,cy (pixel size in depth units)")
    if not vals[0] > 0:
        raise argparse.ArgumentTypeError(f"pixel size must be > 0, got {vals[0]}")
    return vals


def _positive(kind):
    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}") from None
        if not (np.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"expected a positive {kind.__name__}, got {text!r}")
        return v

    parse.__name__ = kind.__name__
    return parse


def _noise_arg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (np.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"noise must be a finite number >= 0, got {text!r}")
    return v


def _depth_scale_arg(text: str) -> float:
    from .formats import check_depth_scale

    try:
        return check_depth_scale(float(text), "--depth-scale")
    except ValueError as e:
        raise argparse.ArgumentTypeError(
            str(e) if "convention" in str(e) else f"expected a positive number (depth units per metre), got {text!r}"
        ) from None


def _shape_arg(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected H,W, got {text!r}") from None
    if h < 8 or w < 8:
        raise argparse.ArgumentTypeError(f"image shape must be at least 8x8, got {h}x{w}")
    return h, w


def _tolerance_arg(text: str) -> float:
    try:
        t = float(text)
    except ValueError:
        t = float("nan")
    if not 0.5 < t <= 1.0:  # Hoover et al.: T in (0.5, 1] keeps the classification one-to-one
        raise argparse.ArgumentTypeError(f"tolerance must be in (0.5, 1], got {text!r}")
    return t


def _segment_options(pairs, noise):
    """`-o KEY=VALUE` pairs -> `SegmentOptions`, values coerced to the type of each field's default."""
    from .segment import SegmentOptions

    fields = {f.name: f for f in dataclasses.fields(SegmentOptions)}
    kw = {}
    for pair in pairs or ():
        key, sep, text = pair.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in fields or key == "weights":
            names = ", ".join(n for n in fields if n != "weights")
            raise CLIError(f"bad segment option {pair!r}: expected KEY=VALUE with KEY one of {names}")
        default, text, annotation = fields[key].default, text.strip(), str(fields[key].type)
        try:
            if text.lower() in ("none", "auto", "") and (default is None or "None" in annotation):
                kw[key] = None
            elif isinstance(default, bool):
                if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(text)
                kw[key] = text.lower() in ("true", "1", "yes")
            elif isinstance(default, int) or "int" in annotation:
                kw[key] = int(text)
            elif isinstance(default, float) or "float" in annotation:
                kw[key] = float(text)
            else:
                kw[key] = text
        except ValueError:
            raise CLIError(f"bad value for segment option {key}: {text!r}") from None
        v = kw[key]
        if isinstance(v, (int, float)) and not isinstance(v, bool) and not (np.isfinite(v) and v >= 0):
            # no SegmentOptions number is negative or infinite (SegmentOptions checks the exact ranges)
            raise CLIError(f"bad value for segment option {key}: {text!r} (must be a finite number >= 0)")
    if noise is not None:
        kw["noise"] = noise
    try:
        return SegmentOptions(**kw)
    except (TypeError, ValueError) as e:  # the options' own checks name the field
        given = ", ".join(f"{k}={v!r}" for k, v in kw.items()) or "defaults"
        raise CLIError(f"bad segment options ({given}): {_one_line(e)}") from None


# ----------------------------------------------------------------------------------------------------
# reading inputs


def _pcd_height(path: Path) -> int | None:
    """HEIGHT from a PCD header (None if absent), without reading the data."""
    with open(path, "rb") as f:
        head = f.read(65536)
    for line in head.split(b"\n"):
        words = line.decode("ascii", "replace").split()
        if words and words[0].upper() == "HEIGHT" and len(words) > 1:
            try:
                return int(words[1])
            except ValueError:
                return None
        if words and words[0].upper() == "DATA":
            break
    return None


def _npy_is_points(path: Path) -> bool:
    try:
        a = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception:  # damaged files: let the reader report them
        return False
    return a.ndim == 2 and a.shape[1] == 3


def load_input(
    path, *, camera=None, ortho=None, depth_scale=None, color=None, intrinsics=None
) -> tuple[Any, str]:  # (RangeImage or (P, 3) array, its kind)
    """Read INPUT as the `segment` command does: `(RangeImage, "range_image")` or `((P, 3), "point_cloud")`.

    `camera`: a `PinholeCamera` (overrides a stored one); `ortho`: [pixel_size] or [pixel_size, cx, cy]
    (an `OrthographicCamera`, centred on the image when cx, cy are not given); `intrinsics`: a JSON file
    of pinhole intrinsics (`formats.read_intrinsics`); `color`: a colour image registered to the depth.
    `depth_scale`: stored units per metre (Open3D), stored values are divided by it.
    """
    from .formats import read_intrinsics, read_points, read_range_image, with_colors
    from .rangeimage import OrthographicCamera, RangeImage

    if intrinsics is not None:
        if camera is not None or ortho is not None:
            raise CLIError("--intrinsics, --camera and --ortho are exclusive: give one camera")
        camera = read_intrinsics(intrinsics)
    path = Path(path)
    ext = path.suffix.lower()
    known = _IMAGE_EXTS + _CLOUD_EXTS + (".npy", ".pcd")
    if ext not in known:
        raise CLIError(f"{path}: unsupported file extension {ext!r} ({_SUPPORTED})")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise CLIError(f"{path}: is a directory, expected a file ({_SUPPORTED})")
    has_camera = camera is not None or ortho is not None
    if (
        ext in _CLOUD_EXTS
        or (ext == ".pcd" and (_pcd_height(path) or 0) <= 1 and not has_camera)
        or (ext == ".npy" and not has_camera and _npy_is_points(path))
    ):
        if has_camera:
            raise CLIError(f"{path}: --camera / --ortho apply to range images, and this is a point cloud")
        if color is not None:
            raise CLIError(f"{path}: --color applies to range images, and this is a point cloud")
        pts = read_points(path)
        return (pts / depth_scale if depth_scale is not None else pts), "point_cloud"
    if ext in (".npy", ".png") and not has_camera:
        raise CLIError(
            f"{path}: a {ext} depth image stores no camera; pass --intrinsics FILE.json, "
            "--camera fx,fy,cx,cy or --ortho PIXEL"
        )
    cam = camera
    if ortho is not None:
        cam = OrthographicCamera(ortho[0], *(ortho[1:] if len(ortho) == 3 else (0.0, 0.0)))
    image = read_range_image(path, camera=cam, depth_scale=depth_scale)
    if ortho is not None and len(ortho) == 1:
        H, W = image.shape
        image = RangeImage(
            image.depth,
            OrthographicCamera(ortho[0], (W - 1) / 2, (H - 1) / 2),
            image.labels,
            image.points_override,
            image.colors,
        )
    if color is not None:
        image = with_colors(image, color)
    return image, "range_image"


# ----------------------------------------------------------------------------------------------------
# progress


class _Progress:
    """A progress bar on stderr (only when it is a terminal), with a total and an ETA (tqdm).

    Units are growth steps plus one unit per final stage (rejoining split parts and the final selection)
    of each round: `max_steps` growth steps and that stage per round, `1 + reseed` rounds. The total is an
    upper bound that shrinks to the truth as rounds end early, so the ETA errs long.

    `segment()` calls `progress(step, n_active, n_models)` after each growth step; this class also takes
    the keywords `stage` ("grow", "merge", "select", "reseed", "finish"), `round` (0-based) and `total`
    (the true number of units) should `segment()` pass them, and then uses them as given.
    """

    def __init__(self, max_steps: int, stream=None, enabled: bool | None = None, *, rounds: int = 1):
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled if enabled is not None else bool(getattr(self.stream, "isatty", lambda: False)())
        self.budget, self.rounds = max(int(max_steps), 1), max(int(rounds), 1)
        self.round, self.round_start, self.step, self.in_final = 0, 0, 0, False
        self.n_models, self.bar = 1 << 62, None

    @property
    def total(self) -> int:
        """Units still possible: steps done + the rest of this round's budget + later rounds + final stages."""
        done_rounds_steps = self.round_start
        this_round = self.step - self.round_start if self.in_final else self.budget
        return done_rounds_steps + this_round + (self.rounds - self.round - 1) * self.budget + self.rounds

    def _open(self, what: str):
        if self.bar is None and self.enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=self.total,
                desc=f"sqjax: {what}",
                file=self.stream,
                unit="step",
                dynamic_ncols=True,
                leave=False,
                bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}] {postfix}",
            )

    def start(self, what: str):
        self._open(what)
        self._post("seeding (the first run compiles the kernels)")

    def _post(self, text: str):
        if self.bar is not None:
            self.bar.set_postfix_str(text, refresh=True)

    def _sync(self, total=None):
        if self.bar is not None:
            self.bar.total = int(total) if total is not None else self.total
            done = min(self.step + self.round, self.bar.total)  # a final stage per finished round
            if done > self.bar.n:
                self.bar.update(done - self.bar.n)  # update(): tqdm's smoothed rate, so the ETA forgets compiling
            else:
                self.bar.refresh()

    def __call__(
        self,
        step: int,
        n_active: int,
        n_models: int,
        *,
        stage: str | None = None,
        round: int | None = None,
        total: int | None = None,
    ):  # noqa: A002
        if round is not None and round != self.round:
            self.round, self.round_start, self.in_final = int(round), self.step, False
        elif stage in (None, "grow") and step > self.step and (self.in_final or n_models > self.n_models):
            # growth again after a final stage, or more models than selection left (reseeded ones
            # joined): a reseed round
            self.round, self.round_start, self.in_final = min(self.round + 1, self.rounds - 1), self.step, False
        self.step, self.n_models = int(step), int(n_models)
        stage = stage or ("grow" if n_active and self.step - self.round_start < self.budget else "merge")
        if stage != "grow":
            self.in_final = True
        self._sync(total)
        where = f"round {self.round + 1}/{self.rounds}, " if self.rounds > 1 else ""
        tail = (
            f"{n_active} of {n_models} models growing"
            if stage == "grow"
            else "merging split parts, final selection"
            if stage in ("merge", "select")
            else stage
        )
        self._post(f"{where}growth step {self.step - self.round_start}/{self.budget}, {tail}")

    def phase(self, what: str):
        self._post(what)

    def close(self):
        if self.bar is not None:
            self.bar.n = self.bar.total
            self.bar.close()
            self.bar = None


# ----------------------------------------------------------------------------------------------------
# commands


def _fmt(v, w=7, p=3):
    return f"{v:{w}.{p}f}"


def _parts_table(seg) -> str:
    head = (
        f"{'part':>4} {'points':>7} {'a1':>7} {'a2':>7} {'a3':>7} {'e1':>5} {'e2':>5} "
        f"{'x':>8} {'y':>8} {'z':>8} {'rms':>9}"
    )
    rows = [head]
    for i, p in enumerate(seg.parts):
        sq = p.superquadric
        a, e, t = (np.asarray(v, float) for v in (sq.size, sq.epsilon, sq.translation))
        rms = np.sqrt(p.error / p.num_explained) if p.num_explained else float("nan")
        rows.append(
            f"{i + 1:>4} {p.num_points:>7} {_fmt(a[0])} {_fmt(a[1])} {_fmt(a[2])} {_fmt(e[0], 5, 2)} "
            f"{_fmt(e[1], 5, 2)} {_fmt(t[0], 8)} {_fmt(t[1], 8)} {_fmt(t[2], 8)} {rms:9.2e}"
        )
    return "\n".join(rows)


def _segment_and_write(data, kind, out, *, input_path, input_shape, settings, options, figure, quiet):
    from .export import write_segmentation
    from .segment import segment

    progress = _Progress(options.max_steps, rounds=1 + max(int(options.reseed), 0))
    progress.start(Path(input_path).name if input_path else "segment")
    try:
        try:
            seg = segment(data, options=options, progress=progress)
        except ValueError as e:  # e.g. too few valid points: say which input
            raise CLIError(f"{input_path}: {_one_line(e)}" if input_path else _one_line(e)) from None
        progress.phase("writing models, labels, meshes" + (" and the figure" if figure else ""))
        written = write_segmentation(
            seg, data, out, input_path=input_path, input_shape=input_shape, settings=settings, figure=figure
        )
    finally:
        progress.close()
    n = int(data.valid.sum()) if kind == "range_image" else len(data)
    t = seg.timings
    if not quiet:
        print(
            f"sqjax: {len(seg.parts)} part{'s' if len(seg.parts) != 1 else ''} from {n} "
            f"{'pixels' if kind == 'range_image' else 'points'} in {t['total']:.1f} s "
            f"(compile {t['compile']:.1f} s); noise {seg.noise:.3g}, threshold {seg.threshold:.3g}"
        )
        if seg.parts:
            print(_parts_table(seg))
        print(f"wrote {out}{os.sep}: {' '.join(written)}")
    return seg, written


def _check_out_dir(out: Path) -> bool:
    """Fail now, not after the segmentation, when `out` cannot take the results; True if it was created."""
    from .export import check_writable_dir

    existed = os.path.lexists(out)
    check_writable_dir(out)
    return not existed


def cmd_segment(args) -> int:
    from .dataset import cli_segment_many, wants_many

    if wants_many(args):  # several inputs, a folder, a glob or a cluster: sqjax.dataset
        return cli_segment_many(args)
    path = Path(args.input[0])
    options = _segment_options(args.option, args.noise)  # bad options: before any work
    out = Path(args.out) if args.out else Path(f"sqjax-{path.stem}")
    created = _check_out_dir(out)  # unusable --out: before any work
    try:
        return _segment_file(args, path, options, out)
    except BaseException:
        if created:  # leave no empty folder behind a failed run
            with contextlib.suppress(OSError):
                out.rmdir()
        raise


def _segment_file(args, path, options, out) -> int:
    data, kind = load_input(
        path,
        camera=args.camera,
        ortho=args.ortho,
        depth_scale=args.depth_scale,
        color=args.color,
        intrinsics=args.intrinsics,
    )
    input_shape = data.shape if kind == "range_image" else (len(data),)
    if kind == "range_image":  # segmented at a working resolution, labelled at the input's
        options = dataclasses.replace(options, subsample=args.subsample)
    elif args.subsample is not None and args.subsample > 1:
        data = data[:: args.subsample]
    camera_source = (
        "--intrinsics"
        if args.intrinsics is not None
        else "--camera"
        if args.camera is not None
        else "--ortho"
        if args.ortho is not None
        else ("file" if kind == "range_image" else None)
    )
    settings = {
        "subsample": 1 if kind == "range_image" else (args.subsample or 1),
        "depth_scale": args.depth_scale,
        "depth_scale_convention": "stored units per metre (divides)",
        "noise": args.noise,
        "camera_source": camera_source,
        "color": None if args.color is None else str(args.color),
        "options": dataclasses.asdict(options),
    }
    _segment_and_write(
        data,
        kind,
        out,
        input_path=path,
        input_shape=input_shape,
        settings=settings,
        options=options,
        figure=not args.no_figure,
        quiet=args.quiet,
    )
    return 0


def cmd_demo(args) -> int:
    from .formats import write_range_image
    from .scenes import paper_scene

    out = Path(args.out)
    options = _segment_options(None, None)
    _check_out_dir(out)
    image, truth = paper_scene("occluded_block", shape=args.shape, noise=args.noise, seed=0)
    scene = out / "scene.npz"
    write_range_image(scene, image)
    print(
        f"sqjax demo: the paper's Fig. 3 scene (a block behind a cylinder, and a sphere), "
        f"{image.shape[0]}x{image.shape[1]} pixels, {len(truth)} true parts -> {scene}"
    )
    data, _ = load_input(scene)
    settings = {
        "subsample": 1,
        "depth_scale": None,
        "noise": None,
        "camera_source": "file",
        "options": dataclasses.asdict(options),
        "scene": "occluded_block",
    }
    seg, written = _segment_and_write(
        data,
        "range_image",
        out,
        input_path=scene,
        input_shape=data.shape,
        settings=settings,
        options=options,
        figure=not args.no_figure,
        quiet=False,
    )
    from .evaluate import hoover

    score = hoover(data.labels, seg.labels)
    print(
        f"Hoover scores against the truth (T = 0.8): {score.correct} of {score.n_truth} parts correct, "
        f"{score.over} over-, {score.under} under-segmented, {score.missed} missed, {score.noise} noise"
    )
    fig = written.get("figure.png")
    look = f"open {fig}, or run " if fig is not None and Path(fig).is_file() else "run "
    print(f"next: {look} sqjax evaluate {out} {scene}")
    return 0


def _scene(name: str, shape, noise, seed):
    from .scenes import PAPER_SCENES, paper_scene, random_scene

    if name.startswith("random:") or name == "random":
        try:
            s = int(name.partition(":")[2] or seed)
        except ValueError:
            raise CLIError(f"bad scene {name!r}: expected random:SEED with an integer SEED") from None
        kw = {} if noise is None else {"noise": noise}
        return random_scene(s, shape=shape, **kw)
    if name not in PAPER_SCENES:
        raise CLIError(f"unknown scene {name!r}: expected one of {', '.join(PAPER_SCENES)} or random:SEED")
    return paper_scene(name, shape=shape, noise=0.0 if noise is None else noise, seed=seed)


def cmd_render(args) -> int:
    from .export import atomic_paths, check_writable_file, dumps, superquadric_dict
    from .formats import write_range_image

    out = Path(args.out)
    if out.suffix.lower() not in (".npz", ".pcd", ".png"):
        raise CLIError(f"{out}: --out must end in .npz (depth, labels, camera), .pcd or .png")
    json_path = Path(args.json) if args.json else None
    if out.parent != Path(""):
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OSError(e.errno, f"{out}: cannot create folder {out.parent} ({e.strerror})") from None
    for target in (out, json_path):  # both writable, or neither is written (before the ray casting)
        if target is not None:
            check_writable_file(target)
    image, truth = _scene(args.scene, args.shape, args.noise, args.seed)
    doc = None
    if json_path is not None:
        doc = {
            "version": 1,
            "scene": args.scene,
            "image_size": list(image.shape),
            "camera": image.camera.to_dict(),
            "parts": [{"label": i + 1, **superquadric_dict(sq)} for i, sq in enumerate(truth)],
        }
    with atomic_paths(*(p for p in (json_path,) if p is not None)) as tmps:
        if tmps:
            tmps[0].write_text(dumps(doc) + "\n")
        write_range_image(out, image, depth_scale=args.depth_scale)  # atomic itself; the JSON follows it
    msg = f"wrote {out}: {image.shape[0]}x{image.shape[1]} range image of {args.scene!r}, {len(truth)} parts"
    if out.suffix.lower() == ".png":
        msg += (
            f" (16-bit depth x {args.depth_scale:g}; no labels or camera: read with --camera "
            f"{image.camera.fx:g},{image.camera.fy:g},{image.camera.cx:g},{image.camera.cy:g} "  # pyright: ignore[reportAttributeAccessIssue]  (scenes: pinhole)
            f"--depth-scale {args.depth_scale:g})"
        )
    print(msg)
    if json_path is not None:
        print(f"wrote {json_path}: true parameters")
    return 0


def _read_truth_labels(path: Path):
    from .formats import read_points, read_range_image

    ext = path.suffix.lower()
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if ext == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                if "labels" not in z:
                    raise CLIError(f"{path}: has no 'labels' array (keys: {', '.join(sorted(z.keys()))})")
                return np.asarray(z["labels"])
        except CLIError:
            raise
        except Exception as e:  # damaged archives fail in many ways
            raise CLIError(f"{path}: damaged .npz ({type(e).__name__}: {e})") from None
    if ext == ".pcd":
        if (_pcd_height(path) or 0) > 1:
            labels = read_range_image(path).labels
        else:
            labels = read_points(path, with_labels=True)[1]
        if labels is None:
            raise CLIError(f"{path}: the PCD has no 'label' field")
        return labels
    if ext == ".npy":
        try:
            labels = np.load(path, allow_pickle=False)
        except Exception as e:
            raise CLIError(f"{path}: could not read .npy ({type(e).__name__}: {e})") from None
        if not np.issubdtype(labels.dtype, np.integer):
            raise CLIError(f"{path}: labels must be integers, got {labels.dtype}")
        return labels
    raise CLIError(f"{path}: unsupported truth file {ext!r} (use .npz or .pcd with labels, or a .npy label array)")


def cmd_evaluate(args) -> int:
    from .evaluate import hoover
    from .export import read_models_json, write_json

    result = Path(args.result)
    meta = {}
    if args.json:
        from .export import check_writable_file

        check_writable_file(args.json)
    if result.is_dir():
        labels_path = result / "labels.npy"
        if (result / "models.json").exists():
            meta = read_models_json(result / "models.json")
    else:
        labels_path = result
        if result.suffix.lower() != ".npy":
            raise CLIError(f"{result}: RESULT must be a directory written by 'sqjax segment' or a labels .npy file")
        if (result.parent / "models.json").exists() and result.name == "labels.npy":
            meta = read_models_json(result.parent / "models.json")
    if not labels_path.exists():
        raise FileNotFoundError(f"{labels_path}: no such file")
    try:
        found = np.load(labels_path, allow_pickle=False)
    except Exception as e:
        raise CLIError(f"{labels_path}: could not read .npy ({type(e).__name__}: {e})") from None
    if not np.issubdtype(found.dtype, np.integer):
        raise CLIError(f"{labels_path}: labels must be integers, got {found.dtype}")
    truth_path = Path(args.truth)
    truth = _read_truth_labels(truth_path)
    step = (meta.get("settings") or {}).get("subsample") or 1
    if isinstance(step, bool) or not isinstance(step, int) or step < 1:
        raise CLIError(
            f"{labels_path.parent / 'models.json'}: settings.subsample must be an integer >= 1, got {step!r}"
        )
    if truth.shape != found.shape and step > 1:
        truth = truth[::step, ::step] if truth.ndim == 2 else truth[::step]
    if truth.shape != found.shape:
        raise CLIError(
            f"label shapes differ: result {found.shape} ({labels_path}) vs truth {truth.shape} ({truth_path})"
        )
    score = hoover(truth, found, tolerance=args.tolerance)
    pct = lambda r: "  -" if not np.isfinite(r) else f"{100 * r:5.1f} %"
    print(
        f"Hoover et al. (1996) at tolerance {score.tolerance:g}: {score.n_truth} truth regions, "
        f"{score.n_found} found regions"
    )
    print(f"  correct  {score.correct:4d}  {pct(score.correct_rate)} of truth")
    print(f"  over     {score.over:4d}  {pct(score.over_rate)} of truth")
    print(f"  under    {score.under:4d}  {pct(score.under_rate)} of found")
    print(f"  missed   {score.missed:4d}  {pct(score.missed_rate)} of truth")
    print(f"  noise    {score.noise:4d}  {pct(score.noise_rate)} of found")
    if args.json:
        doc = {"version": 1, "result": str(labels_path), "truth": str(truth_path), "subsample": step, **score.to_dict()}
        print(f"wrote {write_json(doc, args.json)}")
    return 0


def cmd_fit(args) -> int:
    from .export import fit_dict, write_json
    from .fitting import fit
    from .formats import read_points

    path = Path(args.points)
    if args.json:
        from .export import check_writable_file

        check_writable_file(args.json)
    pts = read_points(path)
    if args.depth_scale is not None:
        pts = pts / args.depth_scale
    try:
        result = fit(pts, max_steps=args.max_steps, deform=args.deform)
    except ValueError as e:  # e.g. too few valid points: say which input
        raise CLIError(f"{path}: {_one_line(e)}") from None
    doc = fit_dict(result, input_path=path)
    deg = np.degrees(doc["euler_zyz"])
    status = "converged" if doc["converged"] else "NOT converged (raise --max-steps?)"
    print(f"sqjax: fitted one superquadric to {doc['num_points']} points of {path} ({status})")
    print(f"  size a1 a2 a3       {' '.join(f'{v:.4g}' for v in doc['size'])}")
    print(f"  exponents e1 e2     {' '.join(f'{v:.3f}' for v in doc['epsilon'])}")
    print(f"  translation x y z   {' '.join(f'{v:.4g}' for v in doc['translation'])}")
    print(f"  Euler ZYZ (deg)     {' '.join(f'{v:.2f}' for v in deg)}")
    rows = [" ".join(f"{v:+.4f}" for v in r) for r in doc["rotation"]]
    print(f"  rotation            {rows[0]}\n                      {rows[1]}\n                      {rows[2]}")
    if args.deform:
        print(f"  taper Kx Ky         {' '.join(f'{v:.3f}' for v in doc['taper'])}")
        print(f"  bend k alpha        {' '.join(f'{v:.3f}' for v in doc['bend'])}")
    print(f"  cost G              {doc['cost']:.4g}   rms distance {doc['rms_distance']:.4g}")
    if args.json:
        print(f"wrote {write_json(doc, args.json)}")
    return 0


# ----------------------------------------------------------------------------------------------------
# the parser


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    p = _Parser(
        prog="sqjax",
        description="Direct part-level segmentation of range images with superquadrics "
        "(recover-and-select; Leonardis, Jaklic, Solina).",
        epilog="Start with 'sqjax demo'. Each command has --help.",
    )
    p.add_argument("--version", action="version", version=f"sqjax {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    common = _Parser(add_help=False)  # a parent of the sub-parsers, so of their class
    common.add_argument(
        "--no-cache",
        action="store_true",
        help="do not use the on-disk compilation cache (also: SQJAX_NO_CACHE=1); "
        "default folder $XDG_CACHE_HOME/sqjax/jax or ~/.cache/sqjax/jax ($SQJAX_CACHE_DIR)",
    )

    s = sub.add_parser(
        "segment",
        parents=[common],
        help="segment a range image or point cloud into superquadric parts",
        description="Segment INPUT into superquadric parts (recover-and-select) and write "
        "models.json, labels.npy, labels.png, labels_id.png (clouds: labels.ply), parts.glb (Y-up), "
        "parts.ply and figure.png into DIR. Inputs: " + _SUPPORTED + ".",
    )
    s.add_argument(
        "input",
        metavar="INPUT",
        nargs="+",
        help="range image or point cloud file; several files, a "
        "folder or a glob: one output folder each under DIR, summary.csv / summary.json (sqjax.dataset)",
    )
    s.add_argument("--workers", type=_positive(int), metavar="N", help="several inputs: a local Dask cluster of N")
    s.add_argument("--scheduler", metavar="ADDRESS", help="several inputs: run on this Dask scheduler")
    cam = s.add_mutually_exclusive_group()
    cam.add_argument(
        "--camera",
        type=_camera_arg,
        metavar="fx,fy,cx,cy",
        help="pinhole intrinsics in pixels (needed for .npy/.png depth; overrides a stored camera)",
    )
    cam.add_argument(
        "--ortho",
        type=_ortho_arg,
        metavar="PIXEL[,cx,cy]",
        help="orthographic camera: pixel size in depth units (principal point: the image centre)",
    )
    cam.add_argument(
        "--intrinsics",
        metavar="FILE.json",
        help="pinhole intrinsics JSON: fx, fy, cx, cy (or x_offset, y_offset) or Open3D's intrinsic_matrix",
    )
    s.add_argument("--color", metavar="IMAGE", help="colour image registered to the depth (RGB-D); used in figure.png")
    s.add_argument(
        "--depth-scale",
        type=_depth_scale_arg,
        metavar="S",
        help="stored depth units per metre, divides (Open3D's convention): 1000 for millimetres; "
        "default: use the stored values",
    )
    s.add_argument(
        "--subsample",
        type=_positive(int),
        default=None,
        metavar="STEP",
        help="range images: segment at every STEP-th row and column and label every input pixel "
        "with the final models (default: the step that brings the image near 160 x 120; 1 = the "
        "slow exact path); clouds: use every STEP-th point (default 1)",
    )
    s.add_argument(
        "--noise",
        type=_positive(float),
        metavar="SIGMA",
        help="sensor noise std in depth units (default: estimated from the data)",
    )
    s.add_argument(
        "-o",
        "--option",
        action="append",
        metavar="KEY=VALUE",
        help="any SegmentOptions field, e.g. -o window=8 -o max_steps=40 (repeatable)",
    )
    s.add_argument("--out", metavar="DIR", help="output folder (default: ./sqjax-<input name>)")
    s.add_argument("--no-figure", action="store_true", help="do not draw figure.png (faster)")
    s.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    s.set_defaults(func=cmd_segment)

    d = sub.add_parser(
        "demo",
        parents=[common],
        help="segment a generated scene of the paper (no download)",
        description="Render the paper's Fig. 3 scene (a block seen in two pieces behind a "
        "cylinder, and a sphere), segment it and write the results and the figure to DIR.",
    )
    d.add_argument("--out", default="sqjax-demo", metavar="DIR", help="output folder (default: ./sqjax-demo)")
    d.add_argument("--shape", type=_shape_arg, default=(120, 160), metavar="H,W", help="image size (default 120,160)")
    d.add_argument("--noise", type=_noise_arg, default=0.002, metavar="SIGMA", help="depth noise std (default 0.002)")
    d.add_argument("--no-figure", action="store_true", help="do not draw figure.png")
    d.set_defaults(func=cmd_demo)

    r = sub.add_parser(
        "render",
        parents=[common],
        help="write a labelled synthetic range image",
        description="Ray cast a synthetic scene: SCENE is one of the paper's scenes "
        "(sphere_cylinder, two_cylinders, occluded_block) or random:SEED. Writes depth, labels "
        "and camera (.npz, .pcd) or 16-bit depth only (.png).",
    )
    r.add_argument("scene", metavar="SCENE", help="sphere_cylinder | two_cylinders | occluded_block | random:SEED")
    r.add_argument("--out", required=True, metavar="FILE", help="output .npz, .pcd or .png")
    r.add_argument("--shape", type=_shape_arg, default=(120, 160), metavar="H,W", help="image size (default 120,160)")
    r.add_argument(
        "--noise",
        type=_noise_arg,
        default=None,
        metavar="SIGMA",
        help="depth noise std (default: 0 for paper scenes, 0.005 for random ones)",
    )
    r.add_argument("--seed", type=int, default=0, help="noise seed of paper scenes (default 0)")
    r.add_argument(
        "--depth-scale",
        type=_depth_scale_arg,
        default=1000.0,
        metavar="S",
        help=".png only: stored value = depth x S, S = stored units per metre (default 1000: mm)",
    )
    r.add_argument("--json", metavar="OUT", help="also write the true superquadrics as JSON")
    r.set_defaults(func=cmd_render)

    e = sub.add_parser(
        "evaluate",
        parents=[common],
        help="Hoover scores of a segmentation against ground-truth labels",
        description="Compare found labels (a 'sqjax segment' output folder or its labels.npy) "
        "with ground truth (.npz or .pcd with labels, or a .npy label array) by the region "
        "classification of Hoover et al. (1996). A --subsample recorded in models.json is "
        "applied to the truth.",
    )
    e.add_argument("result", metavar="RESULT", help="output folder of 'sqjax segment', or a labels .npy")
    e.add_argument("truth", metavar="TRUTH", help=".npz / .pcd with labels, or a .npy label array")
    e.add_argument("--tolerance", type=_tolerance_arg, default=0.8, metavar="T", help="overlap tolerance (default 0.8)")
    e.add_argument("--json", metavar="OUT", help="write the scores as JSON")
    e.set_defaults(func=cmd_evaluate)

    f = sub.add_parser(
        "fit",
        parents=[common],
        help="fit one superquadric to a point set",
        description="Recover one superquadric from POINTS (.ply, .npy, .xyz, .txt, .pcd, .obj, "
        ".stl) and print its parameters; --json writes them (schema: 'python -m pydoc sqjax.cli').",
    )
    f.add_argument("points", metavar="POINTS", help="point set file")
    f.add_argument("--json", metavar="OUT", help="write the parameters as JSON")
    f.add_argument("--deform", action="store_true", help="also fit tapering and bending")
    f.add_argument("--max-steps", type=_positive(int), default=20, metavar="N", help="LM steps (default 20)")
    f.add_argument(
        "--depth-scale",
        type=_depth_scale_arg,
        metavar="S",
        help="stored units per metre: coordinates are divided by S (1000 for millimetres)",
    )
    f.set_defaults(func=cmd_fit)
    return p


def _one_line(e: BaseException) -> str:
    msg = str(e) or type(e).__name__
    if isinstance(e, OSError) and e.strerror and e.errno is not None:
        msg = e.strerror  # without the "[Errno N]" prefix; our own messages carry the path in strerror
    if isinstance(e, OSError) and e.filename and str(e.filename) not in msg:
        msg = f"{e.filename}: {msg}"
    return " ".join(msg.split())


def main(argv=None) -> int:
    """Run the command line with `argv` (default `sys.argv[1:]`); returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version and usage errors (already reported)
        return e.code if isinstance(e.code, int) else EXIT_USAGE
    try:
        if not getattr(args, "no_cache", False):
            from .cache import cache_disabled_by_env, enable_compilation_cache

            if not cache_disabled_by_env():
                enable_compilation_cache()
        return args.func(args)
    except BrokenPipeError:  # `sqjax ... | head`: stop quietly (Python docs, "Note on SIGPIPE")
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return EXIT_FAILURE
    except (ValueError, FileNotFoundError, OSError) as e:
        if os.environ.get("SQJAX_DEBUG"):
            raise
        print(f"sqjax: error: {_one_line(e)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("sqjax: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # a bug: still one line, the traceback on request
        if os.environ.get("SQJAX_DEBUG"):
            raise
        print(
            f"sqjax: internal error: {type(e).__name__}: {_one_line(e)} (set SQJAX_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
