"""Reading and writing range images and point clouds (host side, numpy).

Range images (`read_range_image` / `write_range_image`): `.npy` / `.npz` depth arrays, 16-bit `.png`
depth, and organised PCL `.pcd` clouds (HEIGHT > 1; `DATA ascii`, `binary`, `binary_compressed`).
Point sets (`read_points` / `write_points`): `.ply`, `.xyz` / `.txt`, `.npy`, `.pcd`, and the vertices
of `.obj` / `.stl` meshes. RGB-D frames (`read_rgbd`): a 16-bit depth PNG, an optional colour image
and intrinsics JSON. Lengths are in the file's units (PCD clouds are usually metres) unless
`depth_scale` is given.

`depth_scale` follows Open3D: stored depth units per metre (1000 for millimetres), and stored values are
*divided* by it (`write_*` multiply). Values below 1 are refused: before sqjax 0.2 the scale multiplied
(0.001 for millimetres); pass 1000 instead. Failing to read a file raises `FileNotFoundError` or a
`ValueError` whose message starts with the file's path.
"""

from __future__ import annotations

import io
import json
import os
import pickle
import struct
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Any, overload

import numpy as np

from .rangeimage import Camera, OrthographicCamera, PinholeCamera, RangeImage

_PCD_TYPES = {
    ("F", 4): "<f4",
    ("F", 8): "<f8",
    ("U", 1): "u1",
    ("U", 2): "<u2",
    ("U", 4): "<u4",
    ("U", 8): "<u8",
    ("I", 1): "i1",
    ("I", 2): "<i2",
    ("I", 4): "<i4",
    ("I", 8): "<i8",
}
_READ_ERRORS = (ValueError, EOFError, struct.error, zipfile.BadZipFile, zlib.error, pickle.UnpicklingError)


def lzf_decompress(data: bytes | memoryview, size: int) -> bytes:
    """Decompress a raw LZF stream (liblzf, as in PCD `binary_compressed`) to exactly `size` bytes."""
    src, out, ip, op, n = memoryview(data), bytearray(size), 0, 0, len(data)
    try:
        while ip < n:
            ctrl = src[ip]
            ip += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                if ip + ctrl + 1 > n or op + ctrl + 1 > size:
                    raise ValueError("LZF stream corrupt (literal run past the end)")
                out[op : op + ctrl + 1] = src[ip : ip + ctrl + 1]
                ip, op = ip + ctrl + 1, op + ctrl + 1
                continue
            length, ref = ctrl >> 5, op - ((ctrl & 0x1F) << 8) - 1  # back reference
            if length == 7:
                length, ip = length + src[ip], ip + 1
            ref, ip, length = ref - src[ip], ip + 1, length + 2
            if ref < 0 or op + length > size:
                raise ValueError("LZF stream corrupt (back reference out of range)")
            if ref + length <= op:
                out[op : op + length] = out[ref : ref + length]
            else:  # overlapping copy: the last (op - ref) bytes repeat
                out[op : op + length] = (out[ref:op] * (length // (op - ref) + 1))[:length]
            op += length
    except IndexError:
        raise ValueError("LZF stream corrupt (ends inside a back reference)") from None
    if op != size:
        raise ValueError(f"LZF stream corrupt (decompressed to {op} bytes, expected {size})")
    return bytes(out)


def fit_pinhole(points: np.ndarray) -> PinholeCamera:
    """Least-squares pinhole intrinsics (pixels) of an organised cloud `(H, W, 3)`.

    Fits `u = fx x / z + cx` and `v = fy y / z + cy` (u = column, v = row) over the points with finite
    xyz and z > 0. Raises ValueError when the valid points do not span at least two rows and columns.
    """
    pts = np.asarray(points, np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"fit_pinhole: points must be (H, W, 3), got shape {pts.shape}")
    v, u = np.mgrid[0 : pts.shape[0], 0 : pts.shape[1]].astype(np.float64)
    ok = np.isfinite(pts).all(-1) & (pts[..., 2] > 0)
    params = []
    for pix, coord in ((u, pts[..., 0]), (v, pts[..., 1])):
        a, b = coord[ok] / pts[..., 2][ok], pix[ok]
        var = np.var(a) if a.size >= 3 else 0.0
        if not var > 0:
            raise ValueError(f"cannot fit pinhole intrinsics to {int(ok.sum())} valid points; pass camera=")
        f = np.mean((a - a.mean()) * (b - b.mean())) / var
        params.append((float(f), float(b.mean() - f * a.mean())))
    (fx, cx), (fy, cy) = params
    return PinholeCamera(fx, fy, cx, cy)


# ---------------------------------------------------------------------------------------------- PCD
def _read_pcd(path: Path):
    """PCD v0.7 -> (xyz (N, 3) float64, labels (N,) int64 or None, WIDTH, HEIGHT)."""
    raw, header, pos = path.read_bytes(), {}, 0
    while "DATA" not in header:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > 65536:
            raise ValueError("not a PCD file (no DATA line in the header)")
        line, pos = raw[pos:end].decode("ascii", "replace").strip(), end + 1
        if line and not line.startswith("#"):
            header[line.split()[0].upper()] = line.split()[1:]
    try:
        names, sizes, types = header["FIELDS"], [int(s) for s in header["SIZE"]], header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        npts, kind = int(header.get("POINTS", [width * height])[0]), header["DATA"][0].lower()
        if not len(names) == len(sizes) == len(types) == len(counts) >= 1:
            lens = [len(names), len(sizes), len(types), len(counts)]
            raise ValueError(f"FIELDS/SIZE/TYPE/COUNT lengths differ: {lens}")
        if (bad := [f"{t}{s}" for t, s in zip(types, sizes) if (t.upper(), s) not in _PCD_TYPES]) or min(counts) < 1:
            raise ValueError(f"unsupported TYPE/SIZE {bad} or COUNT {counts}")
        if width < 0 or height < 0 or npts != width * height:
            raise ValueError(f"POINTS {npts} != WIDTH {width} x HEIGHT {height}")
    except (KeyError, IndexError, ValueError) as e:
        raise ValueError(f"bad PCD header ({f'missing {e}' if isinstance(e, KeyError) else e})") from None
    dts = [np.dtype(_PCD_TYPES[t.upper(), s]) for t, s in zip(types, sizes)]
    body, fields = memoryview(raw)[pos:], {}
    need = npts * sum(d.itemsize * c for d, c in zip(dts, counts))
    if kind == "ascii":
        try:
            text = bytes(body).decode("ascii")
            table = np.loadtxt(io.StringIO(text), np.float64, ndmin=2) if npts else np.zeros((0, sum(counts)))
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"bad PCD ascii data ({e})") from None
        if table.shape != (npts, sum(counts)):
            raise ValueError(f"PCD ascii data has shape {table.shape}, header says ({npts}, {sum(counts)})")
        cols = np.cumsum([0] + counts)
        fields = {n: table[:, cols[i] : cols[i + 1]].astype(dts[i]) for i, n in enumerate(names)}
    elif kind == "binary":
        if len(body) < need:
            raise ValueError(f"PCD binary data truncated ({len(body)} bytes, header says {need})")
        dt = np.dtype({"names": [f"f{i}" for i in range(len(names))], "formats": list(zip(dts, counts))})
        rec = np.frombuffer(body, dt, count=npts)
        fields = {n: rec[f"f{i}"].reshape(npts, -1) for i, n in enumerate(names)}
    elif kind == "binary_compressed":  # uint32 compressed size, uint32 size, LZF of the fields column-wise
        if len(body) < 8:
            raise ValueError("PCD binary_compressed data truncated (no size words)")
        csize, usize = struct.unpack("<II", body[:8])
        if len(body) - 8 < csize or usize != need:
            raise ValueError(
                f"PCD binary_compressed data truncated or inconsistent ({len(body)} bytes, "
                f"compressed size {csize}, uncompressed {usize}, header needs {need})"
            )
        buf, off = lzf_decompress(body[8 : 8 + csize], usize), 0
        for n, d, c in zip(names, dts, counts):
            fields[n] = np.frombuffer(buf, d, npts * c, off).reshape(npts, c)
            off += npts * c * d.itemsize
    else:
        raise ValueError(f"bad PCD header (unknown DATA {kind!r})")
    if not {"x", "y", "z"} <= fields.keys():
        raise ValueError(f"PCD has no x y z fields (FIELDS {' '.join(names)})")
    xyz = np.concatenate([fields[n][:, :1].astype(np.float64) for n in "xyz"], 1)
    labels = fields["label"][:, 0].astype(np.int64) if "label" in fields else None
    return xyz, labels, width, height, _pcd_colors(fields)


def _pcd_colors(fields) -> np.ndarray | None:
    """(N, 3) uint8 RGB from a PCD `rgb` / `rgba` field (4 bytes packed 0xAARRGGBB, stored as F or U)."""
    name = "rgb" if "rgb" in fields else "rgba" if "rgba" in fields else None
    if name is None or fields[name].dtype.itemsize != 4:
        return None
    packed = np.ascontiguousarray(fields[name][:, 0]).view(np.uint32)
    return np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], 1).astype(np.uint8)


def _pcd_image(path):
    xyz, labels, width, height, rgb = _read_pcd(path)
    if height <= 1:
        raise ValueError(f"unorganised PCD (HEIGHT {height}, WIDTH {width}) is not a range image; use read_points")
    xyz = xyz.reshape(height, width, 3)
    return (
        xyz[..., 2],
        None if labels is None else labels.reshape(height, width),
        xyz,
        None,
        None if rgb is None else rgb.reshape(height, width, 3),
    )


def _write_pcd(path, image: RangeImage, data="binary", **_):
    if data not in ("ascii", "binary"):
        raise ValueError(f"PCD data must be 'ascii' or 'binary', got {data!r}")
    cols = {n: image.points[..., i].reshape(-1).astype("<f4") for i, n in enumerate("xyz")}
    if image.labels is not None:
        cols["label"] = image.labels.reshape(-1).astype("<i4" if (image.labels < 0).any() else "<u4")
    (h, w), types = image.shape, " ".join(c.dtype.kind.upper() for c in cols.values())  # F, U or I
    with open(path, "wb") as f:
        f.write(
            (
                f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {' '.join(cols)}\n"
                f"SIZE {' '.join('4' * len(cols))}\nTYPE {types}\nCOUNT {' '.join('1' * len(cols))}\n"
                f"WIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {h * w}\nDATA {data}\n"
            ).encode()
        )
        if data == "binary":
            rec = np.empty(h * w, [(n, c.dtype) for n, c in cols.items()])
            for n, c in cols.items():
                rec[n] = c
            f.write(rec.tobytes())
        else:  # 9 significant digits round-trip float32 exactly
            table = np.stack(list(cols.values()), 1, dtype=np.float64)
            np.savetxt(f, table, fmt=["%.9g"] * 3 + ["%d"] * (len(cols) - 3))


# -------------------------------------------------------------------------------------- depth arrays
def _load_npy(path):
    with open(path, "rb") as f:
        if f.read(6) != b"\x93NUMPY":
            raise ValueError("not a NumPy .npy file (bad magic bytes)")
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        if "allow_pickle" in str(e):
            raise ValueError(
                "holds a pickled Python object, not loaded for safety; if you trust the file, use "
                "np.load(path, allow_pickle=True) and build the RangeImage yourself"
            ) from None
        raise
    except Exception as e:  # numpy parses the header with tokenize / ast: damaged ones fail in many ways
        raise ValueError(f"damaged .npy ({type(e).__name__}: {e})") from None


def _npy_image(path):
    return _load_npy(path), None, None, None, None


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


def _open_image(path, what: str = "image"):
    """PIL's `Image.open(path)` fully loaded, with PIL's failures (broken files, decompression bombs:
    more pixels than `PIL.Image.MAX_IMAGE_PIXELS`) as ValueErrors without the path (the caller adds it)."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            im = Image.open(path)
            im.load()
            return im
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise ValueError(
            f"{what} refused as a possible decompression bomb ({e}); raise "
            "PIL.Image.MAX_IMAGE_PIXELS if you trust the file"
        ) from None
    except (OSError, SyntaxError) as e:  # PIL reports broken images as either
        raise ValueError(f"could not read {what} ({type(e).__name__}: {e})") from None


def _png_image(path):
    with _open_image(path, "PNG") as im:
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
    if np.ndim(depth) != 2 or not np.issubdtype(depth.dtype, np.number):
        raise ValueError(f"depth must be a numeric (H, W) array, got {depth.dtype} of shape {depth.shape}")
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
def _mesh_points(path):
    import trimesh

    try:
        if path.suffix.lower() == ".obj":  # text: UTF-8, else Latin-1 (trimesh would need charset_normalizer)
            raw = path.read_bytes()
            try:
                raw.decode("utf-8")
            except UnicodeDecodeError:
                raw = raw.decode("latin-1").encode("utf-8")
            obj = trimesh.load(io.BytesIO(raw), file_type="obj", process=False)
        else:
            obj = trimesh.load(path, process=False)
    except Exception as e:  # trimesh raises many kinds of errors on bad input
        raise ValueError(f"could not read with trimesh ({type(e).__name__}: {e})") from None
    verts = []
    for g in obj.dump() if isinstance(obj, trimesh.Scene) else [obj]:
        v = np.asarray(getattr(g, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
        if isinstance(g, trimesh.Trimesh):  # distinct positions, in file order (STL repeats every corner)
            v = v[np.sort(np.unique(v, axis=0, return_index=True)[1])]
        verts.append(v)
    return np.concatenate(verts) if verts else np.zeros((0, 3)), None


def _text_points(path):
    lines = [s for s in path.read_text(errors="replace").splitlines() if s.strip() and s.strip()[0] != "#"]
    if not lines:
        return np.zeros((0, 3)), None
    try:
        sep = "," if "," in lines[0] else None
        return np.loadtxt(lines, np.float64, delimiter=sep, usecols=(0, 1, 2), ndmin=2).reshape(-1, 3), None
    except ValueError as e:
        raise ValueError(f"every line needs >= 3 numeric columns ({e})") from None


def _npy_points(path):
    pts = _load_npy(path)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
        raise ValueError(f"points must be a numeric (N, 3) array, got {pts.dtype} of shape {pts.shape}")
    return pts.astype(np.float64), None


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


def _write_txt(path, pts):
    np.savetxt(path, pts, fmt="%.17g")  # 17 significant digits round-trip float64 exactly


_CLOUD = "is an unorganised point cloud, not a range image; use read_points"
_MESH = "is a mesh, not a range image; use read_points for its vertices (or render it)"
_IMAGE = "is a range image; use read_range_image"
_TO_IMAGE, _TO_POINTS = "use .npz, .pcd or .png", "use .npy, .ply or .xyz"
# extension -> (read_range_image, read_points, write_range_image, write_points); a str explains a refusal.
_FORMATS: dict[str, tuple[Any, Any, Any, Any]] = {  # per extension: a handler or why there is none
    ".npy": (_npy_image, _npy_points, "use .npz to keep the camera", _write_npy),
    ".npz": (_npz_image, _IMAGE, _write_npz, _TO_POINTS),
    ".png": (_png_image, _IMAGE, _write_png, _TO_POINTS),
    ".pcd": (_pcd_image, lambda p: _read_pcd(p)[:2], _write_pcd, _TO_POINTS),
    ".ply": (_CLOUD, _mesh_points, _TO_IMAGE, _write_ply),
    ".xyz": (_CLOUD, _text_points, _TO_IMAGE, _write_txt),
    ".txt": (_CLOUD, _text_points, _TO_IMAGE, _write_txt),
    ".obj": (_MESH, _mesh_points, _TO_IMAGE, _TO_POINTS),
    ".stl": (_MESH, _mesh_points, _TO_IMAGE, _TO_POINTS),
}


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


def read_intrinsics(path_or_dict) -> PinholeCamera:
    """Pinhole intrinsics from a JSON file (or its dict) in any of the common forms:

    - `{"fx", "fy", "cx", "cy"}` (pixels); `x_offset` / `y_offset` (or `ppx` / `ppy`) for cx / cy;
    - Open3D's `PinholeCameraIntrinsic` JSON: `{"width", "height", "intrinsic_matrix": [9 numbers,
      column-major]}`;
    - a 3 x 3 matrix under `K`, `camera_matrix` or `intrinsic_matrix` (nested lists, row-major).

    Optional `width` / `height` (or `img_width` / `img_height`) are checked against the depth image by
    `read_rgbd`. Raises FileNotFoundError / ValueError naming the file.
    """
    return _intrinsics(path_or_dict)[0]


def _intrinsics(path_or_dict):
    """(PinholeCamera, (H, W) or None) of `read_intrinsics`."""
    where = "intrinsics"
    d = path_or_dict
    if not isinstance(d, dict):
        p = Path(os.fspath(d))
        where = str(p)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
        try:
            d = json.loads(p.read_text(encoding="utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ValueError(f"{p}: not valid JSON ({e})") from None
        except OSError as e:
            raise ValueError(f"{p}: cannot read ({e.strerror or e})") from None
    if isinstance(d, dict) and isinstance(d.get("intrinsic"), dict):  # nested, as some tools write
        d = d["intrinsic"]
    if not isinstance(d, dict):
        raise ValueError(f"{where}: intrinsics must be a JSON object, got {type(d).__name__}")
    pick = lambda *keys: next((d[k] for k in keys if k in d), None)
    fx, fy, cx, cy = pick("fx"), pick("fy"), pick("cx", "x_offset", "ppx"), pick("cy", "y_offset", "ppy")
    matrix = pick("intrinsic_matrix", "K", "camera_matrix")
    try:
        if None in (fx, fy, cx, cy) and matrix is not None:
            m = np.asarray(matrix, np.float64)
            if m.shape == (9,):  # Open3D: flat, column-major
                m = m.reshape(3, 3).T
            if m.shape != (3, 3):
                raise ValueError(f"intrinsic matrix must have 9 numbers, got shape {m.shape}")
            fx, fy, cx, cy = m[0, 0], m[1, 1], m[0, 2], m[1, 2]
        if None in (fx, fy, cx, cy):
            raise ValueError(f"needs fx, fy, cx, cy (or an intrinsic_matrix); has {', '.join(sorted(d)) or 'nothing'}")
        cam = PinholeCamera(float(fx), float(fy), float(cx), float(cy))  # pyright: ignore[reportArgumentType]  (no None: checked)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: bad intrinsics ({e})") from None
    size = (pick("height", "img_height"), pick("width", "img_width"))
    return cam, (tuple(int(v) for v in size) if None not in size else None)  # pyright: ignore[reportArgumentType]


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
    cam, size = _intrinsics(intrinsics) if camera is None else (camera, None)
    image = read_range_image(depth, camera=cam, depth_scale=depth_scale)
    if size is not None and size != image.shape:
        raise ValueError(
            f"{depth}: depth image is {image.shape[1]}x{image.shape[0]} (WxH) but the intrinsics "
            f"{intrinsics if not isinstance(intrinsics, dict) else ''} are for {size[1]}x{size[0]}"
        )
    if color is None:
        return image
    return with_colors(image, color)


def with_colors(image: RangeImage, color) -> RangeImage:
    """`image` with `colors` read from the image file `color` (same size as the depth)."""
    color = Path(os.fspath(color))
    if not color.is_file():
        raise FileNotFoundError(f"{color}: no such file")
    try:
        with _open_image(color, "colour image") as im:
            rgb = np.asarray(im.convert("RGB"))
    except ValueError as e:
        raise ValueError(f"{color}: {e}") from None
    except OSError as e:
        raise ValueError(f"{color}: {type(e).__name__}: {e}") from None
    if rgb.shape[:2] != image.shape:
        raise ValueError(
            f"{color}: colour image is {rgb.shape[1]}x{rgb.shape[0]} (WxH), the depth is "
            f"{image.shape[1]}x{image.shape[0]}"
        )
    return RangeImage(image.depth, image.camera, image.labels, image.points_override, rgb)


def read_points(path, *, with_labels: bool = False):
    """Read a point set: `(N, 3)` float64 xyz in the file's units; rows with NaN / inf are dropped.

    `.ply` / `.obj` / `.stl` (via trimesh; meshes give their distinct vertex positions), `.xyz` / `.txt`
    (whitespace or comma separated, first 3 columns used, `#` comments), `.npy` `(N, 3)`, `.pcd` (any
    organisation). With `with_labels=True` returns `(points, labels)`: `(N,)` int64 from a PCD `label`
    field, else None. Raises FileNotFoundError / ValueError naming the file.
    """
    path, fn = _handler(path, 1, "read_points")
    pts, labels = _read(path, fn)
    keep = np.isfinite(pts).all(1)
    pts = np.ascontiguousarray(pts[keep], np.float64)
    return (pts, None if labels is None else labels[keep]) if with_labels else pts


def write_range_image(path, image: RangeImage, *, data: str = "binary", depth_scale: float = 1.0) -> None:
    """Write a RangeImage as `.npz` (depth, labels, camera, points_override, colors), organised `.pcd`
    (x y z float32 + `label` uint32 if labelled; `data="binary"` or `"ascii"`), or 16-bit `.png` storing
    round(depth * depth_scale), 0 = missing (the camera, labels and colours are not stored); e.g.
    `depth_scale=1000` for metres -> millimetres. Written atomically (a temporary file renamed)."""
    if not isinstance(image, RangeImage):
        raise TypeError(f"image must be a RangeImage, got {type(image).__name__}")
    from .export import atomic_paths

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
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
        raise ValueError(f"{path}: points must be a numeric (N, 3) array, got {pts.dtype} of shape {pts.shape}")
    from .export import atomic_paths

    with atomic_paths(path) as (tmp,):
        fn(tmp, pts.astype(np.float64))
