"""PCL's point cloud format (`.pcd`): header, ascii / binary / binary_compressed (LZF) data, organised
clouds as range images (HEIGHT > 1, intrinsics fitted from the points unless given), colours from the
`rgb` / `rgba` field. Host side, numpy; `formats` dispatches to it.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np

from .rangeimage import PinholeCamera, RangeImage

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


_PCD_HEADER_BYTES = 65536
"""A PCD header's last line (DATA) starts within this many bytes."""


def _pcd_header(raw: bytes) -> tuple[dict[str, list[str]], int]:
    """The header of a PCD file (its bytes, or their beginning) -> ({KEY: words}, offset of the data)."""
    header: dict[str, list[str]] = {}
    pos = 0
    while "DATA" not in header:
        end = raw.find(b"\n", pos)
        if end < 0 or pos > _PCD_HEADER_BYTES:
            raise ValueError("not a PCD file (no DATA line in the header)")
        line, pos = raw[pos:end].decode("ascii", "replace").strip(), end + 1
        if line and not line.startswith("#"):
            header[line.split()[0].upper()] = line.split()[1:]
    return header, pos


def pcd_height(path) -> int | None:
    """HEIGHT of a PCD file, read from its header alone (None when the header has none or is damaged):
    above 1 for an organised cloud (a range image), 1 for an unorganised one."""
    with open(path, "rb") as f:
        head = f.read(2 * _PCD_HEADER_BYTES)
    try:
        return int(_pcd_header(head)[0]["HEIGHT"][0])
    except (KeyError, IndexError, ValueError):
        return None


def read_pcd(path: Path):
    """PCD v0.7 -> (xyz (N, 3) float64, labels (N,) int64 or None, WIDTH, HEIGHT)."""
    raw = path.read_bytes()
    header, pos = _pcd_header(raw)
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


def pcd_image(path):
    xyz, labels, width, height, rgb = read_pcd(path)
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


def write_pcd(path, image: RangeImage, data="binary", **_):
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
