"""Correction tables that controllers load: byte-level codecs, pure functions.

Each format has ``encode_*`` (a table -> bytes or text) and ``decode_*`` (back);
``*_file_order`` give a binary table's entries as the file stores them, for the
structural check (:func:`markcal.stages.ctable.table_structure`).
Tables are :class:`~markcal.stages.deviation.GridCorrection` objects: node
positions and command offsets in mm (galvo formats) or mm / µm (stage format),
indexed ``[iy, ix]``. What the public sources leave open is an option, with the
defaults documented in the README ("Correction tables").

Formats
-------
cor
    EZCAD2 / BJJCZ lens correction "JCZ_COR_2_1" (33,840 bytes): 22-byte label,
    6 header bytes, float64 scale (galvo units per mm) at byte 28, 65 x 65
    little-endian int32 (dx, dy) pairs from byte 36, 4-byte trailer. EZCAD's own
    files run the inner index of the 65 x 65 loop along x (the axis of the
    first value of each pair): the default here (``outer="y"``).
ctb
    SCANLAB RTC4 table (16,900 bytes): the X table then the Y table, each
    65 x 65 little-endian uint16 (offset binary), inner index along x.
correxion
    SCANLAB correXion input text: ``[CALIBRATION]`` (bits/mm), ``[GRIDNUMBERS]``
    (half counts), ``[GRIDVALUES_X/Y]`` and one line per grid point with its
    indices and measured position (mm).
a3200
    Aerotech A3200 2D calibration file (stage), corrections in µm.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

from markcal.stages.ctable import centred_nodes, check_range
from markcal.stages.deviation import GridCorrection
from markcal.stages.errors import MarkcalError

__all__ = ["FORMATS", "CorOptions", "CtbOptions", "encode_cor", "decode_cor", "cor_file_order", "encode_ctb",
           "decode_ctb", "ctb_file_order", "encode_correxion", "decode_correxion", "encode_a3200", "decode_a3200",
           "sniff_format", "COR_NODES"]

#: name -> (typical extension, one-line description)
FORMATS = {
    "cor": (".cor", "EZCAD2 / BJJCZ galvo lens correction, JCZ_COR_2_1 (65 x 65, int32 galvo units); from a scan result"),
    "ctb": (".ctb", "SCANLAB RTC4 correction table (65 x 65 x 2, uint16); from a scan result"),
    "correxion": (".dat", "SCANLAB correXion input (nominal grid + measured positions, mm) that correXion "
                          "turns into a .ct5; from a scan result"),
    "a3200": (".cal", "Aerotech A3200 2D stage calibration file (µm); from a selfcal result"),
}

COR_LABEL = b"JCZ_COR_2_1"
COR_SIZE = 33840
COR_NODES = 65
CTB_SIZE = 16900


# ----------------------------------------------------------------------------- EZCAD .cor

#: the widest spacing of the 65 nodes of a .cor/.ctb table (the 16-bit field is 65536 units wide)
MAX_NODE_SPACING = 65536.0


@dataclass(frozen=True)
class CorOptions:
    """What the public sources leave open about JCZ_COR_2_1 (see the README).

    Attributes
    ----------
    node_spacing_units : float
        Galvo units between table nodes; 1024 puts 65 nodes over the 16-bit field
        with node 32 at its centre (0x8000).
    outer : {"y", "x"}
        Which axis the outer loop of the 65 x 65 entries runs along. ``y`` (the
        default) is the layout of EZCAD's own files: the inner index runs along
        x, the axis of the first value of each pair (README, "Correction
        tables", for the evidence); ``x`` is the transposed layout.
    sign : {"subtract", "add"}
        ``subtract``: the controller drives ``nominal - entry`` (so an entry is the
        negated command offset, as meerk40t's cor tools plot it); ``add``: ``nominal + entry``.
    """

    node_spacing_units: float = 1024.0
    outer: str = "y"
    sign: str = "subtract"

    def __post_init__(self):
        if not 0 < self.node_spacing_units <= MAX_NODE_SPACING:
            raise MarkcalError(f"--node-spacing must be positive and at most {MAX_NODE_SPACING} galvo units "
                               f"(got {self.node_spacing_units})")
        if self.outer not in ("x", "y") or self.sign not in ("subtract", "add"):
            raise MarkcalError("cor options: outer must be x or y, sign subtract or add")


def _entries_to_xy(a: np.ndarray, outer: str) -> np.ndarray:
    """(65, 65) in file order [outer, inner] -> indexed [iy, ix] (and back: the map is its own inverse)."""
    return a.T if outer == "x" else a


def _check_cor(data: bytes, path=None) -> float:
    if len(data) != COR_SIZE or not data.startswith(COR_LABEL):
        raise MarkcalError(f"not a JCZ_COR_2_1 correction file ({len(data)} bytes; expected {COR_SIZE} "
                           "starting with 'JCZ_COR_2_1')", path)
    scale = struct.unpack_from("<d", data, 28)[0]
    if not np.isfinite(scale) or scale <= 0:
        raise MarkcalError(f"bad scale {scale!r} galvo units/mm at byte 28", path)
    return float(scale)


def cor_file_order(data: bytes, path=None) -> np.ndarray:
    """The (65, 65, 2) int32 entries of a JCZ_COR_2_1 file as stored: ``[outer, inner, (first, second)]``."""
    _check_cor(data, path)
    return np.frombuffer(data, "<i4", count=2 * COR_NODES * COR_NODES, offset=36).reshape(COR_NODES, COR_NODES, 2)


def encode_cor(table: GridCorrection, units_per_mm: float, opts: CorOptions = CorOptions()) -> bytes:
    """A JCZ_COR_2_1 file from a 65 x 65 table of command offsets (mm)."""
    if table.dx_mm.shape != (COR_NODES, COR_NODES):
        raise MarkcalError(f"a .cor table has 65 x 65 nodes, not {table.dx_mm.shape}")
    s = -1.0 if opts.sign == "subtract" else 1.0
    dx = np.rint(s * table.dx_mm * units_per_mm)
    dy = np.rint(s * table.dy_mm * units_per_mm)
    check_range(np.r_[dx.ravel(), dy.ravel()], -0x7FFF, 0x7FFF, ".cor entry", "galvo units")
    dx, dy = _entries_to_xy(dx, opts.outer), _entries_to_xy(dy, opts.outer)
    pairs = np.empty((COR_NODES * COR_NODES, 2), "<i4")
    pairs[:, 0], pairs[:, 1] = dx.ravel(), dy.ravel()
    head = COR_LABEL.ljust(22, b"\0") + b"\0" * 6 + struct.pack("<d", float(units_per_mm))
    return head + pairs.tobytes() + b"\0" * 4


def decode_cor(data: bytes, opts: CorOptions = CorOptions(), path=None) -> tuple:
    """Read a JCZ_COR_2_1 file; return ``(table, units_per_mm)``; node positions mm."""
    scale = _check_cor(data, path)
    pairs = cor_file_order(data, path)
    s = -1.0 if opts.sign == "subtract" else 1.0
    dx = _entries_to_xy(pairs[..., 0], opts.outer) * s / scale
    dy = _entries_to_xy(pairs[..., 1], opts.outer) * s / scale
    nodes = centred_nodes(COR_NODES, opts.node_spacing_units, scale)
    return GridCorrection(nodes, nodes.copy(), dx.astype(float), dy.astype(float)), float(scale)


# ----------------------------------------------------------------------------- SCANLAB .ctb

@dataclass(frozen=True)
class CtbOptions:
    """What the public sources leave open about the RTC4 table (see the README).

    Attributes
    ----------
    node_spacing_bits : float
        Bits between nodes; 65535/64 puts the 65 nodes on 0..65535 so that the
        1:1 table fits the 16-bit range exactly.
    content : {"absolute", "offset"}
        ``absolute``: each entry is the corrected output position (offset binary,
        32768 = centre); ``offset``: the command offset plus 32768.
    outer : {"y", "x"}
        Axis of the outer index of each 65 x 65 table; ``y`` (default): the X
        table ramps along the inner index, as in SCANLAB's 2D tables.
    """

    node_spacing_bits: float = 65535.0 / 64.0
    content: str = "absolute"
    outer: str = "y"

    def __post_init__(self):
        if not 0 < self.node_spacing_bits <= MAX_NODE_SPACING:
            raise MarkcalError(f"--node-spacing must be positive and at most {MAX_NODE_SPACING} bits "
                               f"(got {self.node_spacing_bits})")
        if self.content not in ("absolute", "offset") or self.outer not in ("x", "y"):
            raise MarkcalError("ctb options: content must be absolute or offset, outer x or y")


def encode_ctb(table: GridCorrection, bits_per_mm: float, opts: CtbOptions = CtbOptions()) -> bytes:
    """An RTC4 .ctb (X table then Y table, 65 x 65 uint16, inner index along x by default) from command offsets (mm)."""
    if table.dx_mm.shape != (COR_NODES, COR_NODES):
        raise MarkcalError(f"a .ctb table has 65 x 65 nodes, not {table.dx_mm.shape}")
    gx, gy = np.meshgrid(table.x_mm, table.y_mm)
    base_x = gx * bits_per_mm if opts.content == "absolute" else 0.0
    base_y = gy * bits_per_mm if opts.content == "absolute" else 0.0
    vx = np.rint(32767.5 + base_x + table.dx_mm * bits_per_mm)
    vy = np.rint(32767.5 + base_y + table.dy_mm * bits_per_mm)
    try:
        check_range(np.r_[vx.ravel(), vy.ravel()], 0, 65535, ".ctb entry", "bits")
    except MarkcalError as exc:
        if opts.content != "absolute":
            raise
        raise MarkcalError(exc.message + ": with absolute content the nominal field already spans the whole 16-bit "
                           "range, so a correction at the edge overflows; write the offsets instead "
                           "(--ctb-content offset) or give a larger --lens-mm") from None
    vx, vy = _entries_to_xy(vx, opts.outer), _entries_to_xy(vy, opts.outer)
    return vx.astype("<u2").tobytes() + vy.astype("<u2").tobytes()


def ctb_file_order(data: bytes, path=None) -> np.ndarray:
    """The two 65 x 65 tables of an RTC4 .ctb as stored, minus the offset-binary centre: ``[X|Y, outer, inner]``."""
    if len(data) != CTB_SIZE:
        raise MarkcalError(f"not an RTC4 .ctb table ({len(data)} bytes; expected {CTB_SIZE})", path)
    return np.frombuffer(data, "<u2").astype(float).reshape(2, COR_NODES, COR_NODES) - 32767.5


def decode_ctb(data: bytes, bits_per_mm: float, opts: CtbOptions = CtbOptions(), path=None) -> GridCorrection:
    """Read an RTC4 .ctb; node positions and offsets in mm (``bits_per_mm`` is not in the file)."""
    raw = ctb_file_order(data, path)
    v = np.stack([_entries_to_xy(raw[0], opts.outer), _entries_to_xy(raw[1], opts.outer)])
    nodes = centred_nodes(COR_NODES, opts.node_spacing_bits, bits_per_mm)
    gx, gy = np.meshgrid(nodes, nodes)
    if opts.content == "absolute":
        v = v - np.stack([gx, gy]) * bits_per_mm
    return GridCorrection(nodes, nodes.copy(), v[0] / bits_per_mm, v[1] / bits_per_mm)


# ----------------------------------------------------------------------------- SCANLAB correXion input

def encode_correxion(nominal_x_mm: np.ndarray, nominal_y_mm: np.ndarray, measured_xy_mm: np.ndarray,
                     bits_per_mm: float, rtc4: bool = False, name: str = "markcal") -> str:
    """correXion input: the nominal grid and where each point was measured.

    Parameters
    ----------
    nominal_x_mm, nominal_y_mm : ndarray
        Grid lines (odd counts, symmetric about 0), mm.
    measured_xy_mm : ndarray
        (ny, nx, 2) measured position of the point commanded at each node,
        indexed ``[iy, ix]`` with y ascending.
    bits_per_mm : float
        The RTC calibration factor K.
    """
    ny, nx = len(nominal_y_mm), len(nominal_x_mm)
    limit_mm = (2 ** 16 if rtc4 else 2 ** 20) / bits_per_mm
    check_range(np.r_[np.ravel(nominal_x_mm), np.ravel(nominal_y_mm), np.ravel(measured_xy_mm)],
                -limit_mm, limit_mm, "correXion position", "mm")
    if nx % 2 == 0 or ny % 2 == 0:
        raise MarkcalError(f"correXion needs odd grid counts symmetric about 0 (got {nx} x {ny})")
    limit_bits = 2 ** 16 if rtc4 else 2 ** 20
    lines = [f"[INPUT]={name} ; input table filename", f"[OUTPUT]={name}_corrected ; output table filename",
             f"[CALIBRATION]={bits_per_mm:.8f} ; bits per mm", f"[RTC4]={int(rtc4)}",
             "[FITORDER]=0", "[SMOOTHING]=-1", "[AUTO_FIT]=0", "[TOLERANCE]=0.1", "[APPLY_OFFSET]= 0", "",
             f"[Limit(Bits)]={limit_bits // 2}", f"[Limit(mm)]={limit_bits / bits_per_mm:.3f}",
             "[OffsetX]=0", "[OffsetY]=0", "[Deviation]=0", "",
             f"[GRIDNUMBERS]={ny // 2} {nx // 2}"]
    lines += [f"[GRIDVALUES_X]={v:.6f}" for v in nominal_x_mm] + [""]
    lines += [f"[GRIDVALUES_Y]={v:.6f}" for v in nominal_y_mm] + ["", "\tXn\tYn\tX mm\tY mm", ""]
    for iy in range(ny - 1, -1, -1):             # top row first, left to right
        for ix in range(nx):
            mx, my = measured_xy_mm[iy, ix]
            lines.append(f"\t{ix - nx // 2}\t{iy - ny // 2}\t{mx:.6f}\t{my:.6f}")
    return "\n".join(lines) + "\n"


_KEY = re.compile(r"^\s*\[([^\]]+)\]\s*=\s*([^;]*)")


def decode_correxion(text: str, path=None) -> dict:
    """Read correXion input; return ``bits_per_mm``, ``rtc4``, ``x_mm``, ``y_mm`` and ``measured_xy_mm`` [iy, ix]."""
    keys, gx, gy, points = {}, [], [], []
    for i, line in enumerate(text.splitlines()):
        m = _KEY.match(line)
        if m:
            k, v = m.group(1).strip().upper(), m.group(2).strip()
            if k == "GRIDVALUES_X":
                gx.append(float(v))
            elif k == "GRIDVALUES_Y":
                gy.append(float(v))
            else:
                keys[k] = v
            continue
        f = line.split()
        if len(f) == 4 and re.fullmatch(r"-?\d+", f[0]) and re.fullmatch(r"-?\d+", f[1]):
            try:
                points.append((int(f[0]), int(f[1]), float(f[2]), float(f[3])))
            except ValueError:
                raise MarkcalError(f"line {i + 1}: bad grid point {line.strip()!r}", path) from None
    try:
        k = float(keys["CALIBRATION"])
        hy, hx = (int(v) for v in keys["GRIDNUMBERS"].split())
    except (KeyError, ValueError):
        raise MarkcalError("not a correXion input file ([CALIBRATION] and [GRIDNUMBERS] needed)", path) from None
    nx, ny = 2 * hx + 1, 2 * hy + 1
    if len(gx) != nx or len(gy) != ny:
        raise MarkcalError(f"[GRIDNUMBERS] says {nx} x {ny} but there are {len(gx)} x {len(gy)} grid values", path)
    meas = np.full((ny, nx, 2), np.nan)
    for xn, yn, mx, my in points:
        if abs(xn) > hx or abs(yn) > hy:
            raise MarkcalError(f"grid point ({xn}, {yn}) is outside the {nx} x {ny} grid", path)
        meas[yn + hy, xn + hx] = (mx, my)
    if np.isnan(meas).any():
        raise MarkcalError(f"{int(np.isnan(meas[..., 0]).sum())} grid points have no measured position", path)
    return {"bits_per_mm": k, "rtc4": keys.get("RTC4", "0").strip() == "1", "x_mm": np.array(gx),
            "y_mm": np.array(gy), "measured_xy_mm": meas}


# ----------------------------------------------------------------------------- Aerotech A3200

#: the largest A3200 correction written (µm): a stage error beyond 10 mm is a broken map
A3200_MAX_UM = 10_000.0


def encode_a3200(x_mm: np.ndarray, y_mm: np.ndarray, error_x_um: np.ndarray, error_y_um: np.ndarray,
                 ax1: int = 1, ax2: int = 2, sign: float = 1.0) -> str:
    """An A3200 2D calibration table from a measured stage error map.

    Parameters
    ----------
    x_mm, y_mm : ndarray
        Evenly spaced axis-1 (x) and axis-2 (y) positions, ascending.
    error_x_um, error_y_um : ndarray
        Measured error at each node, indexed ``[iy, ix]`` (µm).
    ax1, ax2 : int
        Controller axis numbers of x and y.
    sign : float
        +1 or -1; the table holds ``-sign x error`` (µm).
    """
    dx, dy = np.diff(x_mm), np.diff(y_mm)
    if len(x_mm) < 2 or len(y_mm) < 2 or not (np.allclose(dx, dx[0]) and np.allclose(dy, dy[0])) or dx[0] <= 0 or dy[0] <= 0:
        raise MarkcalError("an A3200 table needs evenly spaced ascending positions along both axes")
    cx, cy = -sign * np.asarray(error_x_um), -sign * np.asarray(error_y_um)
    check_range(np.r_[cx.ravel(), cy.ravel()], -A3200_MAX_UM, A3200_MAX_UM, "A3200 entry", "µm")
    check_range(np.r_[x_mm, y_mm], -1e4, 1e4, "A3200 position", "mm")
    lines = [f":START2D {ax2} {ax1} {ax1} {ax2} {dy[0]:.6f} {dx[0]:.6f} {len(x_mm)}",
             f":START2D POSUNIT=METRIC CORUNIT=METRIC/1000 OFFSETROW={y_mm[0]:.6f} OFFSETCOL={x_mm[0]:.6f}"]
    for iy in range(len(y_mm)):
        lines.append("\t".join(f"{cx[iy, ix]:.6f}\t{cy[iy, ix]:.6f}" for ix in range(len(x_mm))))
    lines.append(":END")
    return "\n".join(lines) + "\n"


def decode_a3200(text: str, sign: float = 1.0, path=None) -> dict:
    """Read an A3200 2D table; return ``x_mm``, ``y_mm``, ``error_x_um``, ``error_y_um`` ([iy, ix]) and axes."""
    lines = [l.strip() for l in text.splitlines() if l.strip() and not l.strip().startswith(";")]
    if len(lines) < 4 or not lines[0].upper().startswith(":START2D") or not lines[1].upper().startswith(":START2D"):
        raise MarkcalError("not an A3200 2D calibration file (expected two :START2D lines)", path)
    try:
        f = lines[0].split()[1:]
        ax2, ax1 = int(f[0]), int(f[1])
        step_y, step_x, nx = float(f[4]), float(f[5]), int(f[6])
    except (IndexError, ValueError):
        raise MarkcalError(f"bad :START2D line {lines[0]!r}", path) from None
    opts = dict(kv.split("=", 1) for kv in lines[1].split()[1:] if "=" in kv)
    if opts.get("CORUNIT", "METRIC/1000").upper() != "METRIC/1000" or opts.get("POSUNIT", "METRIC").upper() != "METRIC":
        raise MarkcalError("only POSUNIT=METRIC CORUNIT=METRIC/1000 tables are read", path)
    try:
        end = next(i for i, l in enumerate(lines) if l.upper() == ":END")
    except StopIteration:
        raise MarkcalError("no :END line", path) from None
    try:
        rows = np.array([[float(v) for v in l.split()] for l in lines[2:end]])
    except ValueError:
        raise MarkcalError("non-numeric correction values", path) from None
    if rows.ndim != 2 or rows.shape[1] != 2 * nx:
        raise MarkcalError(f"each row must hold {nx} pairs of corrections", path)
    y0, x0 = float(opts.get("OFFSETROW", 0.0)), float(opts.get("OFFSETCOL", 0.0))
    return {"x_mm": x0 + step_x * np.arange(nx), "y_mm": y0 + step_y * np.arange(len(rows)),
            "error_x_um": -rows[:, 0::2] / sign, "error_y_um": -rows[:, 1::2] / sign, "ax1": ax1, "ax2": ax2}


def sniff_format(data: bytes) -> str:
    """Guess a table's format from its bytes."""
    if data.startswith(COR_LABEL):
        return "cor"
    if len(data) == CTB_SIZE:
        return "ctb"
    head = data[:4096].decode("latin-1", "replace").upper()
    if ":START2D" in head:
        return "a3200"
    if "[GRIDNUMBERS]" in head or "[CALIBRATION]" in head:
        return "correxion"
    raise MarkcalError("not a correction table markcal knows (cor, ctb, correXion input, A3200)")
