"""Readers of point clouds. Everything leaves here in mm.

Supported: PLY (ASCII or binary, with an intensity-like vertex property),
PCD (ASCII, binary or binary_compressed, via Open3D's tensor reader), CSV/TXT/XYZ
(x, y, z, intensity columns; an optional header row names them), NPY (N x 4).
"""
from __future__ import annotations

import os
import struct
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .limits import check_budget, check_file_ends, max_abs_for

INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance", "scalar_reflectance", "i",
                   "backscatter", "scalar_backscatter", "gray", "grey")


@dataclass(frozen=True)
class PointCloud:
    """Scanner-frame points (n, 3) in mm and their backscatter intensity (n,): float32 as the file holds them
    (lossless), else float64."""

    xyz_mm: np.ndarray
    intensity: np.ndarray


def existing_file(path) -> tuple:
    """Check that ``path`` is a non-empty file; return ``(path as str, lower-case extension)``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise MarkcalError("no such file", path)
    if os.path.getsize(path) == 0:
        raise MarkcalError("file is empty", path)
    return path, os.path.splitext(path)[1].lower()


def read_cloud(path, units_scale: float = 1.0) -> PointCloud:
    """Read a point cloud with intensity; ``units_scale`` converts file units to mm.

    Raises
    ------
    MarkcalError
        Missing, empty, truncated or malformed file, no intensity, NaN coordinates.
    """
    path, ext = existing_file(path)
    readers = {".ply": _read_ply, ".pcd": _read_pcd, ".npy": _read_npy,
               ".csv": _read_text, ".txt": _read_text, ".xyz": _read_text, ".pts": _read_text}
    if ext not in readers:
        raise MarkcalError(f"unknown point cloud extension '{ext}' (use .ply, .pcd, .csv, .txt, .xyz or .npy)", path)
    try:
        if ext in (".ply", ".pcd"):
            _check_declared_sizes(path, ext)
        xyz, inten = readers[ext](path)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    except (ValueError, OSError, EOFError, KeyError, IndexError, RuntimeError, struct.error) as exc:
        raise MarkcalError(f"cannot read {ext[1:].upper()} file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})", path) from None
    xyz, inten = _floats(xyz), _floats(inten).ravel()
    if units_scale != 1.0:
        xyz = xyz.astype(np.float64) * units_scale
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) != len(inten):
        raise MarkcalError("malformed cloud: need x, y, z and intensity per point", path)
    if len(xyz) == 0:
        raise MarkcalError("cloud has no points", path)
    lo, hi = float(xyz.min()), float(xyz.max())          # NaN propagates; one pass each instead of four
    if not np.isfinite(lo + hi):
        bad = ~np.all(np.isfinite(xyz), axis=1)
        raise MarkcalError(f"{int(bad.sum())} points have NaN or infinite coordinates", path)
    if max(-lo, hi) > max_abs_for("xyz_mm"):
        far = np.abs(xyz).max(axis=1) > max_abs_for("xyz_mm")
        raise MarkcalError(f"{int(far.sum())} points lie beyond ±10 m ({max_abs_for('xyz_mm'):g} mm; e.g. "
                           f"{np.abs(xyz[far][0]).max():g} mm): not a scan of a plate (wrong units?)", path)
    if not np.all(np.isfinite(inten)):
        raise MarkcalError("intensity has NaN or infinite values", path)
    return PointCloud(xyz_mm=xyz, intensity=inten)


def _floats(a) -> np.ndarray:
    """``a`` as float32 or float64: float32 values (most scanners' files) stay float32, which holds them
    exactly in half the memory (the stages compute in float64); anything else becomes float64."""
    a = np.asarray(a)
    return a if a.dtype in (np.float32, np.float64) else a.astype(np.float64)


def _pick_intensity(names):
    low = [n.lower() for n in names]
    for cand in INTENSITY_NAMES:
        if cand in low:
            return names[low.index(cand)]
    raise MarkcalError(f"no intensity property (found: {', '.join(names)}); "
                       f"the scan flow needs backscatter intensity")


_PLY_DTYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
               "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
               "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def _read_ply_binary_vertices(path):
    """Fast path: a binary PLY whose first element is ``vertex`` with scalar properties only, read in
    one ``np.fromfile``; None for anything else (plyfile reads it)."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    end = head.find(b"end_header")
    nl = head.find(b"\n", end)
    if end < 0 or nl < 0:
        return None
    lines = head[:end].decode("ascii", "replace").splitlines()
    fmt = next((ln.split() for ln in lines if ln.startswith("format ")), [])
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt[1] if len(fmt) > 1 else "")
    elements = [ln.split() for ln in lines if ln.startswith("element ")]
    if order is None or not elements or elements[0][1:2] != ["vertex"] or len(elements[0]) != 3:
        return None
    fields, seen = [], False
    for ln in lines:
        t = ln.split()
        if t[:1] == ["element"]:
            if seen:
                break
            seen = t[1] == "vertex"
        elif t[:1] == ["property"] and seen:
            if len(t) != 3 or t[1] not in _PLY_DTYPES or t[2] in dict(fields):
                return None
            fields.append((t[2], order + _PLY_DTYPES[t[1]]))
    names = [f for f, _ in fields]
    if not all(c in names for c in "xyz"):
        return None
    n = int(elements[0][2])
    v = np.fromfile(path, dtype=np.dtype(fields), count=n, offset=nl + 1)
    if len(v) != n:
        raise MarkcalError(f"PLY is truncated: {len(v):,} of {n:,} vertices")
    xyz = np.empty((n, 3), np.result_type(*(v.dtype[c] for c in "xyz")))
    for k, c in enumerate("xyz"):
        xyz[:, k] = v[c]
    return xyz, v[_pick_intensity(names)]


def _read_ply(path):
    fast = _read_ply_binary_vertices(path)
    if fast is not None:
        return fast
    from plyfile import PlyData, PlyParseError
    try:
        ply = PlyData.read(path)
    except PlyParseError as exc:
        raise MarkcalError(f"malformed PLY: {exc}") from None
    if "vertex" not in ply:
        raise MarkcalError("PLY has no vertex element")
    v = ply["vertex"].data
    names = list(v.dtype.names)
    for c in "xyz":
        if c not in names:
            raise MarkcalError(f"PLY vertex has no '{c}' property")
    inten = v[_pick_intensity(names)]
    return np.column_stack([v["x"], v["y"], v["z"]]), inten


def _read_pcd(path):
    with open(path, "rb") as fh:
        head = fh.read(4096).decode("ascii", "replace")
    fields = []
    for line in head.splitlines():
        if line.upper().startswith("FIELDS"):
            fields = line.split()[1:]
            break
    if not fields:
        raise MarkcalError("not a PCD file (no FIELDS header)")
    name = _pick_intensity(fields)
    import open3d as o3d
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)   # no coloured warnings on stderr
    pc = o3d.t.io.read_point_cloud(path)
    if "positions" not in pc.point:
        raise MarkcalError("PCD has no points")
    xyz = pc.point.positions.numpy()
    key = name if name in pc.point else name.lower()
    if key not in pc.point:
        raise MarkcalError(f"PCD field '{name}' could not be read")
    inten = pc.point[key].numpy().ravel()
    if len(inten) != len(xyz):
        raise MarkcalError("PCD is truncated")
    return xyz, inten


#: bytes one vertex of a cloud costs while reading and processing it (a few float64 copies of x, y, z, i)
BYTES_PER_POINT = 160
#: bytes a row of a PLY list property costs in plyfile (an object array of a small array per row)
BYTES_PER_LIST_ROW = 120
_PLY_SIZES = {name: np.dtype(code).itemsize for name, code in _PLY_DTYPES.items()}


def _header_lines(path, end: bytes, what: str) -> tuple:
    """The header lines up to ``end`` (at most 64 kB) and the byte count left after it."""
    with open(path, "rb") as fh:
        head = fh.read(65536)
    size = os.path.getsize(path)
    i = head.find(end)
    if i < 0:
        raise MarkcalError(f"{what} header has no '{end.decode().strip()}' line in its first 64 kB (truncated or "
                           "not a " + what + " file)")
    j = head.find(b"\n", i)
    body = size - (j + 1 if j >= 0 else len(head))
    return head[:i].decode("ascii", "replace").splitlines(), body


def _int_field(text: str, what: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise MarkcalError(f"{what} = {text!r} is not a whole number") from None
    if v < 0:
        raise MarkcalError(f"{what} = {v} is negative")
    return v


def _check_declared_sizes(path, ext: str) -> None:
    """Refuse a PLY/PCD whose header declares more data than the file holds or the memory budget allows."""
    if ext == ".ply":
        lines, body = _header_lines(path, b"end_header", "PLY")
        fmt = next((ln.split()[1] for ln in lines if ln.startswith("format ") and len(ln.split()) > 1), "ascii")
        elements = []                                   # [name, count, fixed bytes per row, list properties]
        for ln in lines:
            t = ln.split()
            if t[:1] == ["element"] and len(t) == 3:
                elements.append([t[1], _int_field(t[2], f"element {t[1]} count"), 0, 0])
            elif t[:1] == ["property"] and elements:
                if len(t) >= 5 and t[1] == "list":
                    elements[-1][2] += _PLY_SIZES.get(t[2], 4)        # at least the count of each row
                    elements[-1][3] += 1
                elif len(t) >= 3:
                    elements[-1][2] += _PLY_SIZES.get(t[1], 8)
        least = sum(n * (b if fmt != "ascii" else 2 * max(1, b // 4)) for _, n, b, _ in elements)
        if least > body:
            name, n = max(((e[0], e[1]) for e in elements), key=lambda e: e[1], default=("", 0))
            raise MarkcalError(f"header declares {n:,} {name} rows needing at least {least:,} bytes, but the file "
                               f"holds {body:,}: truncated or a hostile header")
        for name, n, b, lists in elements:
            check_budget(n * (BYTES_PER_POINT if name == "vertex" else b) + n * lists * BYTES_PER_LIST_ROW,
                         f"element {name} ({n:,} rows{', a list property' if lists else ''})")
        return
    lines, body = _header_lines(path, b"DATA", "PCD")
    fields = {}
    for ln in lines:
        t = ln.split()
        if t:
            fields[t[0].upper()] = t[1:]
    n = _int_field((fields.get("POINTS") or ["0"])[0], "POINTS")
    width = _int_field((fields.get("WIDTH") or [str(n)])[0], "WIDTH")
    height = _int_field((fields.get("HEIGHT") or ["1"])[0], "HEIGHT")
    if width * height != n:
        raise MarkcalError(f"WIDTH x HEIGHT = {width * height:,} but POINTS = {n:,}")
    sizes = [_int_field(v, "SIZE") for v in fields.get("SIZE", [])]
    counts = [_int_field(v, "COUNT") for v in fields.get("COUNT", ["1"] * len(sizes))]
    row = sum(s * c for s, c in zip(sizes, counts)) or 4
    with open(path, "rb") as fh:
        data_kind = next((ln.split()[1].lower() for ln in fh.read(65536).decode("ascii", "replace").splitlines()
                          if ln.startswith("DATA") and len(ln.split()) > 1), "ascii")
    least = {"binary": n * row, "ascii": n * 2 * max(1, len(sizes))}.get(data_kind, 0)
    if least > body:
        raise MarkcalError(f"header declares {n:,} points needing at least {least:,} bytes, but the file holds "
                           f"{body:,}: truncated or a hostile header")
    check_budget(n * (BYTES_PER_POINT + row), f"{n:,} points")


def _read_npy(path):
    with open(path, "rb") as fh:
        try:
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read_header(fh)
        except (ValueError, EOFError) as exc:
            raise MarkcalError(f"not an NPY array ({exc})") from None
    if dtype.kind not in "iuf" or dtype.names:
        raise MarkcalError(f"NPY array holds {dtype} values; need real numbers (x, y, z, intensity)")
    if len(shape) != 2 or shape[1] != 4:
        raise MarkcalError(f"NPY array has shape {shape}; need N x 4 (x, y, z, intensity)")
    check_budget(shape[0] * BYTES_PER_POINT, f"{shape[0]:,} points")
    a = np.load(path, allow_pickle=False)
    return a[:, :3], a[:, 3]


def _read_text(path):
    check_file_ends(path)
    with open(path, encoding="utf-8", errors="replace") as fh:
        first = fh.readline()
    delim = "," if "," in first else None
    tokens = [t.strip().lower() for t in (first.split(",") if delim else first.split())]
    header = any(t and not _is_number(t) for t in tokens)
    cols = [0, 1, 2, 3]
    if header:
        try:
            cols = [tokens.index(c) for c in ("x", "y", "z")] + [tokens.index(_pick_intensity(tokens))]
        except ValueError:
            cols = [0, 1, 2, 3]
    a = np.loadtxt(path, delimiter=delim, skiprows=1 if header else 0, ndmin=2, usecols=None)
    if a.shape[1] < 4:
        raise MarkcalError(f"text cloud has {a.shape[1]} columns; need x, y, z, intensity")
    return a[:, cols[:3]], a[:, cols[3]]


def _is_number(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False
