"""Readers of vendor SPM files: Bruker NanoScope, Nanosurf NID, JPK, WSxM.

Called by :func:`markcal.stages.image_io.read_image`, the one entry point;
this module also holds the unit tables and the channel choice that every AFM
reader shares.

The format is recognised by content (:func:`sniff_format`), never by the
extension: Bruker files are named ``.spm``, ``.000``-``.00x`` or anything else.
Each reader lists the file's channels, picks one (:func:`pick_channel`:
the height/topography channel in the trace direction unless one is named) and
converts it to nm from the unit and scales the file states; a channel whose
unit is not a length is refused. The lateral pixel size comes from the file's
scan size in its own unit. Every reader returns rows with row 0 at the top of
the image (the files that store the first scan line at the bottom are flipped,
as Gwyddion and AFMReader show them).

Formats, as documented by their vendors and read by Gwyddion:

- Bruker NanoScope (v4-v9, ``\\*File list`` text header, int16/int32 images):
  height = raw x hard scale (V/LSB, per 16-bit LSB) x sensitivity (nm/V).
- Nanosurf ``.nid`` (INI text header, ``#!``, then the channels' integers):
  value = Dim2Min + (raw - int min) / 2^bits x Dim2Range, in Dim2Unit.
- JPK ``.jpk`` (TIFF; JPK tags 0x8000+): value = raw x multiplier + offset of
  the page's default calibration slot, in that slot's unit; lateral sizes (m)
  from the grid tags of the first page.
- WSxM ``.stp`` (doubles in the Z Amplitude unit) and ``.top`` (int16 whose
  full range spans the Z Amplitude).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .errors import MarkcalError

__all__ = ["sniff_format", "is_jpk", "read_spm_file", "pick_channel", "other_direction", "Channel", "length_um",
           "height_nm_per_unit", "LEN_UM", "Z_NM", "OTHER_DIRECTION"]

#: length unit name -> µm (None: no physical unit)
LEN_UM = {"m": 1e6, "mm": 1e3, "cm": 1e4, "um": 1.0, "µm": 1.0, "μm": 1.0, "~m": 1.0, "micron": 1.0,
          "microns": 1.0, "micrometer": 1.0, "micrometre": 1.0, "nm": 1e-3, "pm": 1e-6, "a": 1e-4, "å": 1e-4,
          "inch": 25400.0, "\\u00b5m": 1.0, "pixel": None, "": None}
#: height unit name -> nm
Z_NM = {k: v * 1e3 for k, v in LEN_UM.items() if v is not None and k != "inch"}

_FORMATS = {"bruker": "Bruker NanoScope", "nid": "Nanosurf NID", "jpk": "JPK", "wsxm": "WSxM"}


def _unit_key(unit) -> str:
    return str(unit).strip().lower().replace("\\u00b5", "µ").replace("\u00c2", "")


def length_um(unit) -> float | None:
    """µm per one ``unit`` of length, or None when ``unit`` is no length unit."""
    return None if unit is None else LEN_UM.get(_unit_key(unit))


def height_nm_per_unit(unit) -> float | None:
    """nm per one ``unit`` of height, or None when ``unit`` is no length unit."""
    return None if unit is None else Z_NM.get(_unit_key(unit))


# ----------------------------------------------------------------------------- format and channels

def sniff_format(head: bytes) -> str | None:
    """The SPM format of a file from its first bytes, or None.

    Returns one of ``"bruker"``, ``"nid"``, ``"wsxm"`` (a JPK file is a TIFF:
    see :func:`is_jpk`).
    """
    if head.startswith(b"\\*File list") or head.startswith(b"?*File list"):
        return "bruker"
    if head.lstrip(b"\xef\xbb\xbf").startswith(b"[DataSet]"):
        return "nid"
    if head.startswith(b"WSxM file copyright"):
        return "wsxm"
    return None


def is_jpk(tiff_file) -> bool:
    """True when an open ``tifffile.TiffFile`` is a JPK image (JPK format tag 0x8000 on page 0)."""
    return 0x8000 in tiff_file.pages[0].tags


@dataclass(frozen=True)
class Channel:
    """One image channel of a file: its name, scan direction and a loader.

    ``load()`` returns ``(values, unit)``: the (rows, cols) array in ``unit``
    (row 0 at the top) and the unit name as the file states it (None: unknown).
    """

    name: str
    direction: str | None            # "trace", "retrace" or None
    load: Callable[[], tuple]

    @property
    def label(self) -> str:
        return f"{self.name} {self.direction}" if self.direction else self.name


#: default height channels, best first (names compared without case, spaces or punctuation)
HEIGHT_NAMES = ("height", "topography", "zaxis", "z", "heightsensor", "zsensor", "measuredheight")


def _norm(name) -> str:
    return re.sub(r"[^0-9a-z]", "", str(name).lower())


def pick_channel(channels: list[Channel], requested: str | None) -> Channel:
    """Choose a channel: the one named, else the height channel in the trace direction.

    ``requested`` matches a channel's label (``"Height retrace"``) or its name
    (``"height"``, then the trace is preferred), ignoring case, spaces and
    punctuation.

    Raises
    ------
    MarkcalError
        No such channel, or no height channel; the message lists the channels.
    """
    labels = ", ".join(c.label for c in channels) or "none"
    order = {"trace": 0, None: 1, "retrace": 2}

    def best(cands):
        return min(cands, key=lambda c: order.get(c.direction, 3)) if cands else None

    if requested is not None:
        key = _norm(requested)
        hit = next((c for c in channels if _norm(c.label) == key), None) or \
            best([c for c in channels if _norm(c.name) == key])
        if hit is None:
            raise MarkcalError(f"no channel '{requested}' in the file (channels: {labels})")
        return hit
    for name in HEIGHT_NAMES:
        hit = best([c for c in channels if _norm(c.name) == name])
        if hit is not None:
            return hit
    raise MarkcalError(f"no height channel in the file (channels: {labels}); name one with --channel")


def _to_nm(values, unit, label):
    scale = height_nm_per_unit(unit)
    if scale is None:
        what = f"in '{unit}'" if unit else "without a unit"
        raise MarkcalError(f"channel '{label}' is {what}, not a height in a length unit")
    return np.asarray(values, np.float64) * scale


#: ``meta`` key under which a reader hands :func:`.image_io.read_image` the picked channel scanned the other way
OTHER_DIRECTION = "_other_direction"


def other_direction(channels: list[Channel], picked: Channel) -> Channel | None:
    """The channel of ``picked``'s name scanned the other way (its retrace for a trace, and back), or None."""
    want = {"trace": "retrace", "retrace": "trace"}.get(picked.direction)
    if want is None:
        return None
    return next((c for c in channels if c.direction == want and _norm(c.name) == _norm(picked.name)), None)


def read_spm_file(path, fmt: str, channel: str | None = None):
    """Read one channel of a vendor SPM file.

    Parameters
    ----------
    path : path
    fmt : str
        From :func:`sniff_format`.
    channel : str, optional
        Channel name; default the height channel, trace direction.

    Returns
    -------
    data_nm : ndarray (rows, cols)
        Heights (nm), row 0 at the top.
    pixel_um : float or None
        Lateral pixel size (µm).
    meta : dict
        ``format``, ``channel``, ``channels``, ``z_unit_in_file``, ``pixel_source``.
    """
    with open(path, "rb") as fh:
        buf = fh.read()
    reader = {"bruker": _bruker, "nid": _nid, "jpk": _jpk, "wsxm": _wsxm}[fmt]
    channels, px_um, extra = reader(buf, path)
    ch = pick_channel(channels, channel)
    values, unit = ch.load()
    data = _to_nm(values, unit, ch.label)
    meta = {"format": fmt, "channel": ch.label, "channels": [c.label for c in channels],
            "z_unit_in_file": unit, "pixel_source": _FORMATS[fmt] if px_um else None, **extra}
    if (other := other_direction(channels, ch)) is not None:
        o_values, o_unit = other.load()
        if np.shape(o_values) == np.shape(data):
            meta[OTHER_DIRECTION] = _to_nm(o_values, o_unit, other.label)
    return data, px_um, meta


def pixel_um_xy(x_um, y_um, cols, rows):
    """Pixel size (µm) from the field and the sample counts: one number where the pixels are square (within
    0.1 %), else (along x, along y); :func:`.image_io.read_image` resamples such a map to square pixels."""
    px, py = x_um / cols, y_um / rows
    return px if abs(px - py) <= 1e-3 * max(px, py) else (px, py)


def _need(buf, offset, nbytes, what):
    if offset < 0 or offset + nbytes > len(buf):
        raise MarkcalError(f"file truncated: {what} needs bytes {offset}-{offset + nbytes}, file has {len(buf)}")


# ----------------------------------------------------------------------------- Bruker NanoScope

def _bruker_sections(text: str):
    """Split the header into (section name, {key: value}) in file order.

    Keys keep their ``@`` / ``@2:`` prefixes (``"@2:Z scale"``, ``"@Sens. Zscan"``).
    """
    out = []
    for line in text.replace("\r", "").split("\n"):
        line = line.strip()
        if line.startswith("\\*"):
            out.append((line[2:].strip(), {}))
        elif line.startswith("\\") and out:
            body = line[1:]
            m = re.match(r"@(\d:)?", body)
            prefix = m.group(0) if m else ""
            body = body[len(prefix):]
            if ":" in body:
                k, v = body.split(":", 1)
                out[-1][1].setdefault(prefix + k.strip(), v.strip())
    return out


def _bruker_number_unit(text):
    m = re.match(r"\s*([-+0-9.eE]+)\s*(\S*)", text or "")
    if not m:
        raise MarkcalError(f"cannot read the number in '{text}'")
    return float(m.group(1)), m.group(2)


def _bruker(buf, path):
    end = buf.find(b"\\*File list end")
    if end < 0:
        raise MarkcalError("Bruker header has no '\\*File list end'")
    sections = _bruker_sections(buf[:end].decode("latin-1"))
    sens = {}
    for name, kv in sections:
        for k, v in kv.items():
            if k.startswith("@Sens. "):                     # "@Sens. Zscan": "V 12.95302 nm/V"
                sens[k[len("@Sens. "):]] = v
    images = [kv for name, kv in sections if name.lower() in ("ciao image list", "afm image list", "stm image list")]
    if not images:
        raise MarkcalError("Bruker file holds no image (no '\\*Ciao image list' section)")
    channels = []
    px_um = None
    for kv in images:
        name_m = re.search(r'"([^"]+)"', kv.get("@2:Image Data", "")) or re.search(r"\[([^\]]+)\]",
                                                                                    kv.get("@2:Image Data", ""))
        name = name_m.group(1) if name_m else kv.get("Image data", "image")
        cols, rows = int(kv["Samps/line"]), int(kv["Number of lines"])
        off, bpp = int(kv["Data offset"]), int(kv.get("Bytes/pixel", 2))
        if bpp not in (2, 4):
            raise MarkcalError(f"Bruker image '{name}' has {bpp} bytes per pixel (need 2 or 4)")
        _need(buf, off, rows * cols * bpp, f"image '{name}'")
        direction = {"trace": "trace", "retrace": "retrace"}.get(kv.get("Line direction", "").lower())
        zscale = kv.get("@2:Z scale", "")
        channels.append(Channel(name, direction, _bruker_loader(buf, off, rows, cols, bpp, zscale, sens, name)))
        if px_um is None:
            px_um = _bruker_pixel(kv.get("Scan size", ""), cols, rows)
    return channels, px_um, {"version": next((kv.get("Version") for n, kv in sections if "Version" in kv), None)}


def _bruker_pixel(scan_size, cols, rows):
    """Pixel size (µm) from an image's 'Scan size: 2 2 ~m' (x, y, unit) entry."""
    parts = scan_size.split()
    if len(parts) == 3:
        x, y, unit = float(parts[0]), float(parts[1]), parts[2]
    elif len(parts) == 2:
        x = y = float(parts[0])
        unit = parts[1]
    else:
        return None
    scale = length_um(unit)
    if scale is None:
        raise MarkcalError(f"Bruker scan size '{scan_size}' has no length unit: give --pixel-size-um")
    return pixel_um_xy(x * scale, y * scale, cols, rows)


def _bruker_loader(buf, off, rows, cols, bpp, zscale, sens, name):
    def load():
        raw = np.frombuffer(buf, "<i2" if bpp == 2 else "<i4", count=rows * cols, offset=off).reshape(rows, cols)
        # "V [Sens. Zscan] (0.006693481 V/LSB) 438.6572 V": hard scale per 16-bit LSB
        m = re.match(r"\s*V\s*(?:\[(?P<sens>[^\]]+)\])?\s*\((?P<hard>[-+0-9.eE]+)\s*(?P<hu>[^)/]*)/LSB\)", zscale)
        if not m:
            return raw[::-1].astype(np.float64), None
        per_lsb = float(m.group("hard")) * 65536.0 / 2.0 ** (8 * bpp)
        unit = m.group("hu").strip() or "V"
        if m.group("sens"):
            key = m.group("sens").replace("Sens. ", "").strip()
            if key not in sens:
                raise MarkcalError(f"Bruker image '{name}' refers to sensitivity '{key}', not in the header")
            s = sens[key].split()                                   # ["V", "12.95302", "nm/V"]
            value, sunit = _bruker_number_unit(" ".join(s[1:]) if s and s[0] == "V" else sens[key])
            if not sunit.endswith("/V"):
                return raw[::-1] * per_lsb * value, None            # no unit: unknown physical quantity
            per_lsb *= value
            unit = sunit[:-2]
        # the first line in the file is the bottom of the image
        return raw[::-1] * per_lsb, unit
    return load


# ----------------------------------------------------------------------------- Nanosurf NID

def _ini(text):
    out, cur = {}, None
    for line in text.replace("\r", "").split("\n"):
        line = line.strip()
        if line.startswith("[") and line.endswith("]"):
            cur = out.setdefault(line[1:-1], {})
        elif "=" in line and cur is not None:
            k, v = line.split("=", 1)
            cur[k.strip()] = v.strip()
    return out


def _nid(buf, path):
    start = buf.find(b"#!")
    if start < 0:
        raise MarkcalError("NID file has no data marker '#!' after its header")
    ini = _ini(buf[:start].decode("utf-8", "replace"))
    ds = ini.get("DataSet", {})
    order = []
    for g in range(int(ds.get("GroupCount", 0))):
        frame = ds.get(f"Gr{g}-Name", "")
        direction = "retrace" if "backward" in frame.lower() else "trace"
        for c in range(int(ds.get(f"Gr{g}-Count", 0))):
            key = ds.get(f"Gr{g}-Ch{c}")
            if key:
                order.append((key, direction))
    if not order:
        raise MarkcalError("NID header lists no channel ([DataSet] Gr0-Ch0 ...)")
    scan = ini.get("DataSet\\DataSetInfos\\Scan", ini.get("DataSet-Info", {}))
    up = scan.get("Scan direction", "Down").strip().lower() == "up"
    channels, px_um, off = [], None, start + 2
    for key, direction in order:
        sec = ini.get(key)
        if sec is None:
            raise MarkcalError(f"NID header names channel [{key}] but has no such section")
        cols, rows, bits = int(sec["Points"]), int(sec["Lines"]), int(sec.get("SaveBits", 32))
        if bits not in (16, 32):
            raise MarkcalError(f"NID channel [{key}] has {bits}-bit data (need 16 or 32)")
        nbytes = rows * cols * bits // 8
        _need(buf, off, nbytes, f"channel [{key}]")
        channels.append(Channel(sec.get("Dim2Name", key), direction, _nid_loader(buf, off, rows, cols, bits, sec, up)))
        if px_um is None:
            sx, sy = length_um(sec.get("Dim0Unit")), length_um(sec.get("Dim1Unit"))
            if sx is None or sy is None:
                raise MarkcalError(f"NID lateral unit '{sec.get('Dim0Unit')}' is no length: give --pixel-size-um")
            px_um = pixel_um_xy(float(sec["Dim0Range"]) * sx, float(sec["Dim1Range"]) * sy, cols, rows)
        off += nbytes
    px_x = px_um[0] if isinstance(px_um, tuple) else px_um
    return channels, px_um, {"scan_size_um": px_x * int(ini[order[0][0]]["Points"])}


def _nid_loader(buf, off, rows, cols, bits, sec, up):
    def load():
        signed = sec.get("SaveSign", "Signed").lower() == "signed"
        dtype = {16: "<i2", 32: "<i4"}[bits] if signed else {16: "<u2", 32: "<u4"}[bits]
        raw = np.frombuffer(buf, dtype, count=rows * cols, offset=off).reshape(rows, cols).astype(np.float64)
        lo = -(2.0 ** (bits - 1)) if signed else 0.0
        vals = float(sec["Dim2Min"]) + (raw - lo) / 2.0 ** bits * float(sec["Dim2Range"])
        return (vals[::-1] if up else vals), sec.get("Dim2Unit")
    return load


# ----------------------------------------------------------------------------- JPK

_JPK_SLOT0, _JPK_SLOT_SIZE = 0x8090, 0x30


def _jpk(buf, path):
    import tifffile
    tf = tifffile.TiffFile(path)
    try:
        first = tf.pages[0].tags
        if 0x8000 not in first:
            raise MarkcalError("TIFF file is not a JPK image (no JPK format tag 0x8000)")
        try:
            xlen_m, ylen_m = float(first[0x8042].value), float(first[0x8043].value)
            cols, rows = int(first[0x8046].value), int(first[0x8047].value)
        except KeyError:
            raise MarkcalError("JPK file has no grid size tags (0x8042/0x8043/0x8046/0x8047)") from None
        # lengths in m, as the JPK image spec defines them
        px_um = pixel_um_xy(xlen_m * 1e6, ylen_m * 1e6, cols, rows)
        channels = []
        for k, page in enumerate(tf.pages[1:], 1):
            tags = page.tags
            if 0x8050 not in tags:
                continue
            direction = "retrace" if int(tags[0x8051].value) else "trace"
            channels.append(Channel(str(tags[0x8050].value), direction, _jpk_loader(path, k)))
    finally:
        tf.close()
    return channels, px_um, {"scan_size_um": xlen_m * 1e6}


def _jpk_loader(path, k):
    def load():
        import tifffile
        with tifffile.TiffFile(path) as tf:
            page = tf.pages[k]
            tags = {t.code: t.value for t in page.tags}
            raw = page.asarray().astype(np.float64)
        default = tags.get(0x8081)
        for s in range(int(tags.get(0x8080, 0))):
            base = _JPK_SLOT0 + s * _JPK_SLOT_SIZE
            if tags.get(base) == default:
                kind = tags.get(base + 0x13)
                if kind == "LinearScaling":
                    vals = raw * float(tags[base + 0x14]) + float(tags[base + 0x15])
                elif kind == "NullScaling":
                    vals = raw
                else:
                    raise MarkcalError(f"JPK slot '{default}' has scaling '{kind}' (need LinearScaling)")
                # the first line stored is the bottom of the scan
                return vals[::-1], (tags.get(base + 0x12) if kind == "LinearScaling" else None)
        raise MarkcalError(f"JPK channel has no calibration slot named '{default}'")
    return load


# ----------------------------------------------------------------------------- WSxM

def _wsxm(buf, path):
    m = re.search(rb"Image header size:\s*(\d+)", buf[:200])
    if not m:
        raise MarkcalError("WSxM file has no 'Image header size'")
    size = int(m.group(1))
    head = buf[:size].decode("latin-1")

    def key(name):
        km = re.search(rf"^\s*{re.escape(name)}:\s*(.*?)\s*$", head, re.M)
        return km.group(1) if km else None
    try:
        cols, rows = int(key("Number of columns")), int(key("Number of rows"))
    except TypeError:
        raise MarkcalError("WSxM header has no 'Number of columns/rows'") from None
    kind = (key("Image Data Type") or "short").lower()
    dtype = {"short": "<i2", "integer": "<i2", "int": "<i4", "float": "<f4", "double": "<f8"}.get(kind)
    if dtype is None:
        raise MarkcalError(f"WSxM data type '{kind}' is not supported")
    _need(buf, size, rows * cols * np.dtype(dtype).itemsize, "image data")
    px_um = None
    xa, ya = key("X Amplitude"), key("Y Amplitude")
    if xa and ya:
        (x, xu), (y, yu) = _bruker_number_unit(xa), _bruker_number_unit(ya)
        sx, sy = length_um(xu), length_um(yu)
        if sx is None or sy is None:
            raise MarkcalError(f"WSxM X Amplitude '{xa}' has no length unit: give --pixel-size-um")
        px_um = pixel_um_xy(x * sx, y * sy, cols, rows)
    za = key("Z Amplitude")
    name = key("Acquisition channel") or "Topography"

    def load():
        raw = np.frombuffer(buf, dtype, count=rows * cols, offset=size).reshape(rows, cols).astype(np.float64)
        if za is None:
            return raw, None
        z, zu = _bruker_number_unit(za)
        if dtype.startswith("<f"):
            return raw, zu                           # stored in the Z Amplitude unit
        span = np.ptp(raw)                           # integers: their full range is the Z Amplitude
        return (raw * (z / span) if span > 0 else raw), zu
    return [Channel(name, None, load)], px_um, {}
