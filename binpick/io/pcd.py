"""PCD point clouds (PCL, Zivid Studio), organized or not: ascii, binary and binary_compressed.

Coordinates are returned in the file's unit. An organized cloud has HEIGHT > 1 and WIDTH x HEIGHT
points in row-major order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from binpick.errors import InputError
from binpick.io.ply import PointCloudData

_TYPES = {
    ("F", 4): "f4",
    ("F", 8): "f8",
    ("U", 1): "u1",
    ("U", 2): "u2",
    ("U", 4): "u4",
    ("I", 1): "i1",
    ("I", 2): "i2",
    ("I", 4): "i4",
}


def _header(raw: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise InputError(path, "PCD header has no DATA line")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, pos


def _lzf_decompress(data: bytes, size: int) -> bytes:
    """LZF decompression (the codec of PCL's binary_compressed)."""
    out = bytearray(size)
    i = o = 0
    n = len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            ln = ctrl + 1
            out[o : o + ln] = data[i : i + ln]
            i += ln
            o += ln
        else:
            ln = ctrl >> 5
            ref = o - ((ctrl & 0x1F) << 8) - 1
            if ln == 7:
                ln += data[i]
                i += 1
            ref -= data[i]
            i += 1
            ln += 2
            for _ in range(ln):  # overlapping copies are allowed, so byte by byte
                out[o] = out[ref]
                o += 1
                ref += 1
    if o != size:
        raise ValueError("LZF stream ended early")
    return bytes(out)


def load_pcd(path: str | Path) -> PointCloudData:
    path = Path(path)
    raw = path.read_bytes()
    try:
        header, start = _header(raw, path)
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        width, height = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        n = int(header.get("POINTS", [str(width * height)])[0])
        kind = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as exc:
        raise InputError(path, f"malformed PCD header ({exc})") from None
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise InputError(
            path,
            f"malformed PCD header: {len(fields)} FIELDS, {len(sizes)} SIZE, {len(types)} TYPE, {len(counts)} COUNT",
        )
    for f, s, t in zip(fields, sizes, types, strict=True):
        if (t, s) not in _TYPES:
            raise InputError(
                path, f"field {f!r} has TYPE {t} with SIZE {s}, which PCD does not define (F: 4 or 8; U, I: 1, 2 or 4)"
            )
    dtype = np.dtype(
        [
            (f"{f}{j}" if c > 1 else f, "<" + _TYPES[(t, s)])
            for f, s, t, c in zip(fields, sizes, types, counts, strict=False)
            for j in range(c)
        ]
    )
    body = raw[start:]
    try:
        if kind == "ascii":
            table = np.loadtxt(body.decode("ascii").splitlines(), dtype=np.float64, ndmin=2)
            if len(table) != n:
                raise ValueError(f"{len(table)} rows for {n} points")
            data = np.empty(n, dtype)
            for k, name in enumerate(dtype.names or ()):
                data[name] = table[:, k]
        elif kind == "binary":
            if len(body) < n * dtype.itemsize:
                raise ValueError(f"{len(body)} bytes for {n} points of {dtype.itemsize} bytes")
            data = np.frombuffer(body, dtype, count=n)
        elif kind == "binary_compressed":
            comp, size = np.frombuffer(body[:8], "<u4")
            columns = np.frombuffer(_lzf_decompress(body[8 : 8 + int(comp)], int(size)), np.uint8)
            # Compressed PCDs store each field as a contiguous column.
            data = np.empty(n, dtype)
            off = 0
            for name in dtype.names or ():
                col = np.dtype(dtype[name])
                data[name] = columns[off : off + n * col.itemsize].view(col)
                off += n * col.itemsize
        else:
            raise ValueError(f"unknown DATA kind {kind!r}")
    except (ValueError, KeyError, IndexError) as exc:
        raise InputError(path, f"PCD data unreadable or truncated ({exc})") from None
    names = set(dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise InputError(path, "PCD has no x, y, z fields")
    xyz = np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float32)
    rgb = None
    if "rgb" in names or "rgba" in names:
        packed = np.ascontiguousarray(data["rgb" if "rgb" in names else "rgba"]).view(np.uint32)
        rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1).astype(np.uint8)
    normals = None
    if {"normal_x", "normal_y", "normal_z"} <= names:
        normals = np.stack([data["normal_x"], data["normal_y"], data["normal_z"]], axis=1).astype(np.float32)
    shape = (height, width) if height > 1 and width * height == n else None
    return PointCloudData(xyz=xyz, rgb=rgb, normals=normals, shape=shape)


def save_pcd(path: str | Path, cloud: PointCloudData) -> None:
    """Write a binary PCD (organized when cloud.shape is set)."""
    from binpick.io.atomic import atomic_path

    xyz = np.asarray(cloud.xyz, np.float32).reshape(-1, 3)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if cloud.rgb is not None:
        fields.append(("rgb", "u4"))
    data = np.empty(len(xyz), fields)
    data["x"], data["y"], data["z"] = xyz.T
    if cloud.rgb is not None:
        c = np.asarray(cloud.rgb, np.uint32).reshape(-1, 3)
        data["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    H, W = cloud.shape if cloud.shape is not None else (1, len(xyz))
    names = " ".join(f for f, _ in fields)
    header = (
        f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {names}\n"
        f"SIZE {' '.join('4' for _ in fields)}\nTYPE {' '.join('U' if t == 'u4' else 'F' for _, t in fields)}\n"
        f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {W}\nHEIGHT {H}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS "
        f"{len(xyz)}\nDATA binary\n"
    )
    with atomic_path(path) as tmp:
        tmp.write_bytes(header.encode("ascii") + data.tobytes())
