"""Reading and writing range images and point clouds (host side, numpy).

Range images (`read_range_image` / `write_range_image`): `.npy` / `.npz` depth arrays (a `.npy` may be a
pickled dict of arrays with `depth` and `rgb`, UOIS's frames: only arrays are unpickled), 16-bit `.png`
depth, and organised PCL `.pcd` clouds (HEIGHT > 1; `DATA ascii`, `binary`, `binary_compressed`).
Point sets (`read_points` / `write_points`): `.ply`, `.xyz` / `.txt`, `.npy`, `.pcd`, and the vertices
of `.obj` / `.stl` meshes. RGB-D frames (`read_rgbd`): a 16-bit depth PNG, an optional colour image
and intrinsics JSON. `read_input` reads either, as the file says (what `sqjax segment` reads). Lengths
are in the file's units (PCD clouds are usually metres) unless `depth_scale` is given.

`depth_scale` follows Open3D: stored depth units per metre (1000 for millimetres), and stored values are
*divided* by it (`write_*` multiply). Values below 1 are refused: before sqjax 0.2 the scale multiplied
(0.001 for millimetres); pass 1000 instead. Failing to read a file raises `FileNotFoundError` or a
`ValueError` whose message starts with the file's path.
"""

from __future__ import annotations

import io
import os
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np

from .numerics import is_real
from .pcd import fit_pinhole, pcd_height, pcd_image, read_pcd, write_pcd
from .rangeimage import Camera, OrthographicCamera, PinholeCamera, RangeImage
from .rgbd import intrinsics_of, open_image, read_intrinsics, with_colors

_READ_ERRORS = (ValueError, EOFError, struct.error, zipfile.BadZipFile, zlib.error, pickle.UnpicklingError)


# -------------------------------------------------------------------------------------- depth arrays
def _load_npy(path):
    """The array of a .npy file; a pickled object only when it is made of arrays (`_arrays_only`)."""
    with open(path, "rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise ValueError("not a NumPy .npy file (bad magic bytes)")
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        if "allow_pickle" in str(e):
            return _arrays_only(path)
        raise
    except Exception as e:  # numpy parses the header with tokenize / ast: damaged ones fail in many ways
        raise ValueError(f"damaged .npy ({type(e).__name__}: {e})") from None


class _ArraysUnpickler(pickle.Unpickler):
    """Unpickles NumPy arrays, dtypes and plain containers (dict, list, tuple, str, numbers) and
    refuses every other global, so that no code named by the file runs."""

    _ALLOWED = {
        (m, n) for m in ("numpy.core.multiarray", "numpy._core.multiarray") for n in ("_reconstruct", "scalar")
    } | {("numpy", "ndarray"), ("numpy", "dtype"), ("_codecs", "encode")}  # encode: Python 2's byte strings

    def find_class(self, module, name):
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name}")


def _arrays_only(path):
    """A .npy whose payload is a pickled object (a dict of arrays, as UOIS's RGB-D frames are), read
    with `_ArraysUnpickler`: the object, or ValueError when it holds anything but arrays."""
    try:
        with open(path, "rb") as f:
            major, _ = np.lib.format.read_magic(f)
            read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            read_header(f)
            obj = _ArraysUnpickler(f, encoding="latin1").load()  # latin1: Python 2 pickles' array bytes
    except pickle.UnpicklingError as e:
        raise ValueError(
            f"holds a pickled Python object that is not only arrays (it names {e}), not loaded for safety; "
            "if you trust the file, use np.load(path, allow_pickle=True) and build the RangeImage yourself"
        ) from None
    except Exception as e:  # truncated or damaged pickles fail in many ways
        raise ValueError(f"damaged .npy ({type(e).__name__}: {e})") from None
    return obj.item() if isinstance(obj, np.ndarray) and obj.dtype == object and obj.shape == () else obj


def _npy_image(path):
    """A depth array, or a pickled dict of arrays with `depth` (H, W) and optionally `rgb` / `colors`
    (H, W, 3) (UOIS's RealSense frames)."""
    a = _load_npy(path)
    if isinstance(a, np.ndarray) and a.dtype == object:
        raise ValueError(f"holds a pickled object array of shape {a.shape}, not a depth image or a dict with 'depth'")
    if not isinstance(a, dict):
        return a, None, None, None, None
    if "depth" not in a:
        raise ValueError(f"holds a dict without a 'depth' array (keys: {sorted(map(str, a))})")
    colors = next((a[k] for k in ("rgb", "colors", "color") if k in a), None)
    return np.asarray(a["depth"]), None, None, None, None if colors is None else np.asarray(colors)


def _npz_image(path):
    try:
        with np.load(path, allow_pickle=False) as z:
            if "depth" not in z:
                raise ValueError(f"npz has no 'depth' array (keys: {sorted(z.keys())})")
            get = {k: z[k] for k in ("depth", "labels", "points", "fx", "fy", "cx", "cy", "pixel_size") if k in z}
            colors = z["colors"] if "colors" in z else None
    except ValueError:
        raise
    except Exception as e:  # zipfile / numpy report damaged archives in many ways
        raise ValueError(f"damaged .npz ({type(e).__name__}: {e})") from None
    depth, labels, points = get.pop("depth"), get.pop("labels", None), get.pop("points", None)
    cam = {k: float(np.asarray(v).item()) for k, v in get.items()}  # .item(): ValueError unless one value
    if cam and "pixel_size" not in cam and len(cam) < 4:
        raise ValueError(f"incomplete camera in npz: has {sorted(cam)}, needs fx, fy, cx, cy or pixel_size")
    stored = (OrthographicCamera(**cam) if "pixel_size" in cam else PinholeCamera(**cam)) if cam else None
    return depth, labels, points, stored, colors


def _png_image(path):
    with open_image(path, "PNG") as im:
        if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
            raise ValueError(f"PNG mode {im.mode!r} is not a 16-bit depth image")
        return np.asarray(im), None, None, None, None


@overload
def check_depth_scale(depth_scale: None, what: str = ...) -> None: ...
@overload
def check_depth_scale(depth_scale: float | str, what: str = ...) -> float: ...
def check_depth_scale(depth_scale, what: str = "depth_scale"):
    """Refuse a `depth_scale` that is not finite and >= 1 (Open3D's convention: stored units per metre)."""
    if depth_scale is None:
        return None
    try:
        v = float(depth_scale)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {depth_scale!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be finite and > 0, got {depth_scale}")
    if v < 1:
        raise ValueError(
            f"{what} is stored depth units per metre and divides (Open3D's convention), so it is "
            f">= 1; got {depth_scale:g}, the old multiplying convention: pass {1 / v:g} instead"
        )
    return v


def _range_image(parts, camera, scale):
    depth, labels, points, stored, colors = parts
    if np.ndim(depth) != 2 or not is_real(depth.dtype):
        raise ValueError(f"depth must be a real numeric (H, W) array, got {depth.dtype} of shape {depth.shape}")
    if scale is not None:
        depth, points = depth / scale, None if points is None else points / scale
    camera = stored if camera is None else camera
    if camera is None and points is None:
        raise ValueError("no camera stored in the file; pass camera=PinholeCamera(...) or OrthographicCamera(...)")
    return RangeImage(
        depth,
        fit_pinhole(points) if camera is None else camera,  # pyright: ignore[reportArgumentType]  (points: checked above)
        labels,
        points,
        colors,
    )


def _write_npz(path, image: RangeImage, **_):
    extra = {k: v for k, v in image.camera.to_dict().items() if k != "model"}
    extra.update(
        {
            k: v
            for k, v in (("labels", image.labels), ("points", image.points_override), ("colors", image.colors))
            if v is not None
        }
    )
    with open(path, "wb") as f:
        np.savez_compressed(f, depth=image.depth, **extra)


def _write_png(path, image: RangeImage, depth_scale=1.0, **_):
    from PIL import Image

    depth_scale = check_depth_scale(depth_scale)
    q = np.where(image.valid, np.round(np.nan_to_num(image.depth) * depth_scale), 0.0)
    bad = image.valid & ((q < 1) | (q > 65535))
    if bad.any():
        raise ValueError(
            f"{int(bad.sum())} depths do not fit 1..65535 at depth_scale={depth_scale} "
            f"(depths {np.nanmin(image.depth)}..{np.nanmax(image.depth)})"
        )
    Image.fromarray(q.astype(np.uint16)).save(path, format="PNG")


# ---------------------------------------------------------------------------------------- point sets
def load_mesh(path, **kw):
    """`trimesh.load(path, **kw)` of a mesh file, an `.obj` decoded as UTF-8, else Latin-1 (trimesh
    would need charset_normalizer); a ValueError that names the cause for a file trimesh cannot read."""
    import trimesh

    path = Path(os.fspath(path))
    try:
        if path.suffix.lower() == ".obj":
            raw = path.read_bytes()
            try:
                raw.decode("utf-8")
            except UnicodeDecodeError:
                raw = raw.decode("latin-1").encode("utf-8")
            return trimesh.load(io.BytesIO(raw), file_type="obj", **kw)
        return trimesh.load(path, **kw)
    except Exception as e:  # trimesh raises many kinds of errors on bad input
        raise ValueError(f"could not read with trimesh ({type(e).__name__}: {e})") from None


def _mesh_points(path):
    import trimesh

    obj = load_mesh(path, process=False)
    verts = []
    for g in obj.dump() if isinstance(obj, trimesh.Scene) else [obj]:
        v = np.asarray(getattr(g, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
        if isinstance(g, trimesh.Trimesh):  # distinct positions, in file order (STL repeats every corner)
            v = v[np.sort(np.unique(v, axis=0, return_index=True)[1])]
        verts.append(v)
    return np.concatenate(verts) if verts else np.zeros((0, 3)), None


def _text_points(path):
    lines = [s for s in path.read_text(errors="replace").splitlines() if s.strip() and s.strip()[0] != "#"]
    if lines and not _numeric(lines[0].replace(",", " ").split()[:3]):
        lines = lines[1:]  # a header row: "x,y,z" or "x y z"
    if not lines:
        return np.zeros((0, 3)), None
    try:
        sep = "," if "," in lines[0] else None
        return np.loadtxt(lines, np.float64, delimiter=sep, usecols=(0, 1, 2), ndmin=2).reshape(-1, 3), None
    except ValueError as e:
        raise ValueError(f"every line needs >= 3 numeric columns ({e})") from None


def _npy_points(path):
    pts = _load_npy(path)
    if isinstance(pts, dict):  # a pickled frame (UOIS): a range image, not a cloud
        what = "an RGB-D frame (a dict with 'depth'): a range image" if "depth" in pts else "a pickled dict"
        raise ValueError(f"holds {what}, not an (N, 3) point array (keys: {sorted(map(str, pts))})")
    if not (_cloud_shape(pts.shape) and is_real(pts.dtype)):
        raise ValueError(
            f"points must be a real numeric (N, 3) array (x y z, up to {_MAX_COLUMNS - 3} more columns), got "
            f"{pts.dtype} of shape {pts.shape}"
        )
    return pts[:, :3].astype(np.float64), None


_MAX_COLUMNS = 7
"""A 2-D .npy with 3 to this many columns is a point set (x y z, then intensity, colour or normals, as
the text formats' first three columns are used): no depth image is 7 pixels wide."""


def _cloud_shape(shape) -> bool:
    return len(shape) == 2 and 3 <= shape[1] <= _MAX_COLUMNS


def _write_ply(path, pts):
    with open(path, "wb") as f:
        f.write(
            f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty double x\n"
            "property double y\nproperty double z\nend_header\n".encode()
        )
        f.write(np.ascontiguousarray(pts, "<f8").tobytes())


def _write_npy(path, pts):
    with open(path, "wb") as f:  # a file object: np.save would append .npy to other names
        np.save(f, pts)


def _numeric(fields) -> bool:
    """Whether every field of a text row reads as a number."""
    try:
        [float(f) for f in fields]
    except ValueError:
        return False
    return True


def _write_txt(path, pts):
    sep = "," if path.suffix.lower() == ".csv" else " "
    np.savetxt(path, pts, fmt="%.17g", delimiter=sep)  # 17 significant digits round-trip float64 exactly


_CLOUD = "is an unorganised point cloud, not a range image; use read_points"
_MESH = "is a mesh, not a range image; use read_points for its vertices (or render it)"
_IMAGE = "is a range image; use read_range_image"
_TO_IMAGE, _TO_POINTS = "use .npz, .pcd or .png", "use .npy, .ply or .xyz"
# extension -> (read_range_image, read_points, write_range_image, write_points); a str explains a refusal.
_FORMATS: dict[str, tuple[Any, Any, Any, Any]] = {  # per extension: a handler or why there is none
    ".npy": (_npy_image, _npy_points, "use .npz to keep the camera", _write_npy),
    ".npz": (_npz_image, _IMAGE, _write_npz, _TO_POINTS),
    ".png": (_png_image, _IMAGE, _write_png, _TO_POINTS),
    ".pcd": (pcd_image, lambda p: read_pcd(p)[:2], write_pcd, _TO_POINTS),
    ".ply": (_CLOUD, _mesh_points, _TO_IMAGE, _write_ply),
    ".xyz": (_CLOUD, _text_points, _TO_IMAGE, _write_txt),
    ".txt": (_CLOUD, _text_points, _TO_IMAGE, _write_txt),
    ".csv": (_CLOUD, _text_points, _TO_IMAGE, _write_txt),
    ".obj": (_MESH, _mesh_points, _TO_IMAGE, _TO_POINTS),
    ".stl": (_MESH, _mesh_points, _TO_IMAGE, _TO_POINTS),
}


def _npy_shape(path) -> tuple | None:
    """The shape of a plain .npy array (None for a pickled or damaged file: the reader reports those)."""
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False).shape
    except Exception:
        return None


# extensions `_FORMATS` reads both ways but `.npy` (its shape decides) -> does this file hold a point set?
_HOLDS_POINTS = {".pcd": lambda p: (pcd_height(p) or 0) <= 1}
_NO_CAMERA = (".npy", ".png")  # range images that store no camera
SUPPORTED_INPUTS = (
    f"range images: {' '.join(e for e, h in _FORMATS.items() if callable(h[0]))}; "
    f"point clouds: {' '.join(e for e, h in _FORMATS.items() if callable(h[1]))}"
)
"""What `read_input` reads, in words."""
INPUT_EXTENSIONS = tuple(_FORMATS)
"""The extensions `read_input` reads."""
MESH_EXTENSIONS = tuple(e for e, h in _FORMATS.items() if h[0] is _MESH)
"""The extensions that are always meshes, read as their distinct vertices (`read_points`)."""


def has_faces(path) -> bool:
    """Whether a point-set file is a mesh (`read_points` reads its distinct vertices): `.obj` / `.stl`
    always, a `.ply` whose header declares faces."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in MESH_EXTENSIONS:
        return True
    if suffix != ".ply":
        return False
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return False
    for line in head.split(b"end_header")[0].splitlines():
        words = line.split()
        if words[:2] == [b"element", b"face"] and len(words) > 2 and words[2].isdigit() and int(words[2]) > 0:
            return True
    return False


def _handler(path, slot: int, what: str) -> tuple[Path, Any]:
    path, reading = Path(os.fspath(path)), slot < 2
    ext = path.suffix.lower()
    if ext not in _FORMATS:
        ok = ", ".join(e for e, h in _FORMATS.items() if callable(h[slot]))
        raise ValueError(f"{path}: unsupported file extension {ext!r} for {what} (supported: {ok})")
    fn = _FORMATS[ext][slot]
    if not callable(fn):
        raise ValueError(f"{path}: a {ext} file {fn}" if reading else f"{path}: {what} cannot write {ext}; {fn}")
    if reading and not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    return path, fn


def _read(path, fn):
    try:
        return fn(path)
    except FileNotFoundError:
        raise
    except (*_READ_ERRORS, OSError) as e:  # OSError: unreadable file, PIL's UnidentifiedImageError
        raise ValueError(f"{path}: {e if isinstance(e, ValueError) else f'{type(e).__name__}: {e}'}") from None


def read_range_image(path, *, camera: Camera | None = None, depth_scale: float | None = None) -> RangeImage:
    """Read a range image: `(H, W)` depth (NaN / 0 / inf = missing), its camera, optional `(H, W)` labels.

    - `.npy`: `(H, W)` depth; `camera` is required.
    - `.npz`: key `depth` `(H, W)`, optional `labels` `(H, W)` int, optional `points` `(H, W, 3)`
      (`points_override`), and the camera as scalar keys `fx, fy, cx, cy` (pinhole, pixels) or
      `pixel_size[, cx, cy]` (orthographic).
    - `.png`: 16-bit depth divided by `depth_scale` (default: stored units; stored 0 = missing); `camera`
      is required. For a colour image and intrinsics JSON beside it use `read_rgbd`.
    - `.pcd`: an organised PCL cloud (HEIGHT > 1): depth = z, labels from a `label` field, and
      `points_override` = the `(H, W, 3)` xyz grid. Without `camera`, pinhole intrinsics are fitted
      (`fit_pinhole`). VIEWPOINT is ignored: points are used as stored.

    `camera` overrides a stored one. `depth_scale` (Open3D's convention): stored units per metre, the
    stored depths (and PCD / npz points) are divided by it, e.g. 1000 for millimetres -> metres; values
    below 1 are refused (the old multiplying convention). Colours: a PCD `rgb` / `rgba` field or an npz
    `colors` array become `RangeImage.colors`. Raises FileNotFoundError / ValueError naming the file.
    """
    if camera is not None and not isinstance(camera, (PinholeCamera, OrthographicCamera)):
        raise TypeError(f"camera must be a PinholeCamera or OrthographicCamera, got {type(camera).__name__}")
    depth_scale = check_depth_scale(depth_scale)
    path, fn = _handler(path, 0, "read_range_image")
    return _read(path, lambda p: _range_image(fn(p), camera, depth_scale))


def read_rgbd(
    depth, color=None, *, intrinsics=None, camera: Camera | None = None, depth_scale: float = 1000.0
) -> RangeImage:
    """An RGB-D frame -> `RangeImage` with `colors`: a 16-bit depth PNG, an optional colour image and the
    pinhole intrinsics (a JSON file / dict for `read_intrinsics`, or `camera`).

    `depth_scale` (Open3D's convention): stored depth units per metre, default 1000 (millimetres), depths
    come out in metres; stored 0 = missing. `color`: any image PIL reads (RGB, RGBA, grey), the same size
    as the depth. Raises FileNotFoundError / ValueError naming the file.
    """
    depth = Path(os.fspath(depth))
    if depth.suffix.lower() != ".png":
        raise ValueError(f"{depth}: an RGB-D depth image must be a 16-bit .png")
    if (intrinsics is None) == (camera is None):
        raise ValueError(f"{depth}: pass exactly one of intrinsics= (a JSON file or dict) and camera=")
    cam, size = intrinsics_of(intrinsics) if camera is None else (camera, None)
    image = read_range_image(depth, camera=cam, depth_scale=depth_scale)
    if size is not None and size != image.shape:
        raise ValueError(
            f"{depth}: depth image is {image.shape[1]}x{image.shape[0]} (WxH) but the intrinsics "
            f"{intrinsics if not isinstance(intrinsics, dict) else ''} are for {size[1]}x{size[0]}"
        )
    if color is None:
        return image
    return with_colors(image, color)


@overload
def read_points(path, *, with_labels: Literal[False] = ...) -> np.ndarray: ...
@overload
def read_points(path, *, with_labels: Literal[True]) -> tuple[np.ndarray, np.ndarray | None]: ...
@overload
def read_points(path, *, with_labels: bool) -> np.ndarray | tuple[np.ndarray, np.ndarray | None]: ...
def read_points(path, *, with_labels: bool = False):
    """Read a point set: `(N, 3)` float64 xyz in the file's units; rows with NaN / inf are dropped
    (a file whose every row has one is an error).

    `.ply` / `.obj` / `.stl` (via trimesh; meshes give their distinct vertex positions), `.xyz` / `.txt`
    / `.csv` (whitespace or comma separated, first 3 columns used, `#` comments; the file may start with
    one header row such as `x,y,z` or `x y z`), `.npy` `(N, 3)` (to `(N, 7)`, first 3 columns used), `.pcd` (any
    organisation). With `with_labels=True` returns `(points, labels)`: `(N,)` int64 from a PCD `label`
    field, else None. Raises FileNotFoundError / ValueError naming the file. `read_input` (what `sqjax
    segment` reads) keeps the NaN rows instead.
    """
    pts, labels = read_point_rows(path)
    keep = np.isfinite(pts).all(1)
    pts = np.ascontiguousarray(pts[keep], np.float64)
    return (pts, None if labels is None else labels[keep]) if with_labels else pts


def read_point_rows(path) -> tuple[np.ndarray, np.ndarray | None]:
    """Every row of a point file, NaN / inf ones included ((N, 3) float64, labels or None); a file whose
    every row has one is an error."""
    path, fn = _handler(path, 1, "read_points")
    pts, labels = _read(path, fn)
    if len(pts) and not np.isfinite(pts).all(1).any():
        raise ValueError(f"{path}: no finite point ({len(pts)} rows, each with NaN or inf)")
    return np.asarray(pts, np.float64), labels


def write_range_image(path, image: RangeImage, *, data: str = "binary", depth_scale: float = 1.0) -> None:
    """Write a RangeImage as `.npz` (depth, labels, camera, points_override, colors), organised `.pcd`
    (x y z float32 + `label` uint32 if labelled; `data="binary"` or `"ascii"`), or 16-bit `.png` storing
    round(depth * depth_scale), 0 = missing (the camera, labels and colours are not stored); e.g.
    `depth_scale=1000` for metres -> millimetres. Written atomically (a temporary file renamed)."""
    if not isinstance(image, RangeImage):
        raise TypeError(f"image must be a RangeImage, got {type(image).__name__}")
    from .files import atomic_paths

    path, fn = _handler(path, 2, "write_range_image")
    try:
        with atomic_paths(path) as (tmp,):
            fn(tmp, image, data=data, depth_scale=depth_scale)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def write_points(path, points) -> None:
    """Write `(N, 3)` points as `.ply` (binary float64 vertices), `.npy` (float64) or `.xyz` / `.txt`."""
    path, fn = _handler(path, 3, "write_points")
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or not is_real(pts.dtype):
        raise ValueError(f"{path}: points must be a real numeric (N, 3) array, got {pts.dtype} of shape {pts.shape}")
    from .files import atomic_paths

    with atomic_paths(path) as (tmp,):
        fn(tmp, pts.astype(np.float64))


def _intrinsics_beside(path: Path) -> str | None:
    """The one JSON beside `path` whose name says camera or intrinsics (UOIS's `camera_params.json`,
    a dataset's `intrinsics.json`), to name in the missing-camera error; None if none or several."""
    try:
        found = [
            f.name for f in path.parent.glob("*.json") if any(w in f.name.lower() for w in ("camera", "intrinsic"))
        ]
    except OSError:
        return None
    return found[0] if len(found) == 1 else None


def read_input(
    path,
    *,
    camera: PinholeCamera | None = None,
    ortho=None,
    depth_scale: float | None = None,
    color=None,
    intrinsics=None,
) -> tuple[RangeImage | np.ndarray, str]:
    """Read a file as `sqjax segment` does: `(RangeImage, "range_image")` or `((P, 3) points, "point_cloud")`.

    The extension decides (`SUPPORTED_INPUTS`); a `.pcd` is a range image when organised (HEIGHT > 1)
    and a `.npy` a point set when `(N, 3)` (to `(N, 7)`: x y z first; a camera given with one is an
    error, and so is a `(3, N)` array without a camera: a transposed cloud). A point set keeps every
    row of the file (NaN ones too, which `segment` leaves unlabelled), so that labels[i] belongs to
    row i.
    `camera`: a `PinholeCamera` (overrides a stored one); `ortho`: `[pixel_size]` or `[pixel_size, cx,
    cy]` (an `OrthographicCamera`, centred on the image when cx, cy are not given); `intrinsics`: a JSON
    file of pinhole intrinsics (`read_intrinsics`); `color`: a colour image registered to the depth
    (`with_colors`). `depth_scale`: stored units per metre (Open3D), stored values are divided by it.
    Raises FileNotFoundError / ValueError naming the file; messages name the options as `sqjax segment`
    spells them.
    """
    if intrinsics is not None:
        if camera is not None or ortho is not None:
            raise ValueError("--intrinsics, --camera and --ortho are exclusive: give one camera")
        camera = read_intrinsics(intrinsics)
    path = Path(os.fspath(path))
    ext = path.suffix.lower()
    if ext not in _FORMATS:
        raise ValueError(f"{path}: unsupported file extension {ext!r} ({SUPPORTED_INPUTS})")
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise ValueError(f"{path}: is a directory, expected a file ({SUPPORTED_INPUTS})")
    has_camera = camera is not None or ortho is not None
    shape = _npy_shape(path) if ext == ".npy" else None  # None: pickled (a frame), damaged or empty
    if shape is not None and len(shape) == 2 and not has_camera and 3 <= shape[0] <= _MAX_COLUMNS < shape[1]:
        raise ValueError(
            f"{path}: holds an array of shape {shape}: points are rows (N, 3), so this looks like a "
            f"transposed cloud (save it as array.T), and a depth image {shape[0]} pixels tall needs a camera"
        )
    holds = _HOLDS_POINTS.get(ext)
    holds_points = _cloud_shape(shape) if shape is not None else holds is not None and holds(path)
    if not callable(_FORMATS[ext][0]) or holds_points:
        if has_camera:
            raise ValueError(f"{path}: --camera / --ortho apply to range images, and this is a point cloud")
        if color is not None:
            raise ValueError(f"{path}: --color applies to range images, and this is a point cloud")
        pts = read_point_rows(path)[0]  # every row: labels[i] belongs to the file's row i (NaN rows get 0)
        return (pts / depth_scale if depth_scale is not None else pts), "point_cloud"
    if shape is not None and len(shape) != 2:
        raise ValueError(f"{path}: holds an array of shape {shape}: neither a depth image (H, W) nor points (N, 3)")
    if ext in _NO_CAMERA and not has_camera:
        if ext == ".npy" and shape is None:
            try:  # a damaged or empty file is said to be one, not a depth image without its camera
                _load_npy(path)
            except ValueError as e:
                raise ValueError(f"{path}: {e}") from None
        beside = _intrinsics_beside(path)
        raise ValueError(
            f"{path}: a {ext} depth image stores no camera; pass --intrinsics FILE.json, "
            "--camera fx,fy,cx,cy or --ortho PIXEL" + (f" ({beside} is beside it)" if beside else "")
        )
    cam = camera
    if ortho is not None:
        cam = OrthographicCamera(ortho[0], *(ortho[1:] if len(ortho) == 3 else (0.0, 0.0)))
    image = read_range_image(path, camera=cam, depth_scale=depth_scale)
    if ortho is not None and len(ortho) == 1:
        H, W = image.shape
        cam = OrthographicCamera(ortho[0], (W - 1) / 2, (H - 1) / 2)
        image = RangeImage(image.depth, cam, image.labels, image.points_override, image.colors)
    if color is not None:
        image = with_colors(image, color)
    return image, "range_image"
