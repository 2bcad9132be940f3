"""Readers of point clouds. Everything leaves here in mm.

Supported: PLY (ASCII or binary, with an intensity-like vertex property),
PCD (ASCII, binary or binary_compressed, via Open3D's tensor reader), CSV/TXT/XYZ
(x, y, z, intensity columns; an optional header row names them), NPY (N x 4).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError

INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance", "scalar_reflectance", "i",
                   "backscatter", "scalar_backscatter", "gray", "grey")


@dataclass(frozen=True)
class PointCloud:
    """Scanner-frame points (n, 3) in mm and their backscatter intensity (n,)."""

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
        xyz, inten = readers[ext](path)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    except (ValueError, OSError, EOFError, KeyError, IndexError, RuntimeError) as exc:
        raise MarkcalError(f"cannot read {ext[1:].upper()} file ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})", path) from None
    xyz = np.asarray(xyz, np.float64) * units_scale
    inten = np.asarray(inten, np.float64).ravel()
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) != len(inten):
        raise MarkcalError("malformed cloud: need x, y, z and intensity per point", path)
    if len(xyz) == 0:
        raise MarkcalError("cloud has no points", path)
    bad = ~np.all(np.isfinite(xyz), axis=1)
    if bad.any():
        raise MarkcalError(f"{int(bad.sum())} points have NaN or infinite coordinates", path)
    if not np.all(np.isfinite(inten)):
        raise MarkcalError("intensity has NaN or infinite values", path)
    return PointCloud(xyz_mm=xyz, intensity=inten)


def _pick_intensity(names):
    low = [n.lower() for n in names]
    for cand in INTENSITY_NAMES:
        if cand in low:
            return names[low.index(cand)]
    raise MarkcalError(f"no intensity property (found: {', '.join(names)}); "
                       f"the scan flow needs backscatter intensity")


def _read_ply(path):
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


def _read_npy(path):
    a = np.load(path, allow_pickle=False)
    if a.ndim != 2 or a.shape[1] < 4:
        raise MarkcalError(f"NPY array has shape {a.shape}; need N x 4 (x, y, z, intensity)")
    return a[:, :3], a[:, 3]


def _read_text(path):
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
