"""Readers of OM images and AFM height maps. Everything leaves here in µm and nm.

Like ``stages/io`` (point clouds) this is the one place of the indents flow
that reads files; units are converted here and nowhere else.

The format is recognised by the file's content (the extension only for Igor
waves, which have no magic bytes). Supported:

- Vendor SPM files (``stages/afm_files``): Bruker NanoScope (``.spm``,
  ``.000``-``.00x``, legacy), Nanosurf ``.nid``, JPK ``.jpk``, WSxM ``.stp``/``.top``.
- TIFF (tifffile): grey-scale 8/16-bit (OM) or float (AFM heights). Pixel size
  from OME-XML ``PhysicalSizeX``, ImageJ metadata (``unit`` + resolution), the
  FEI/Thermo ``PixelWidth`` (tag 34682, m), the Zeiss SmartSEM ``Image Pixel Size``
  (tag 34118) or the resolution tags in cm; an inch (dpi) resolution is a screen or
  editor setting and never taken as a pixel size, nor a cm value equal to 72/96/150/300 dpi. Float heights carry their unit in
  the ImageJ key ``zunit`` (nm, um, m); without it a map whose range is below
  1e-4 is taken to be in m, otherwise in nm.
- Gwyddion Simple Field ``.gsf`` (hand-written reader; the format is a text
  header plus little-endian float32). ``XYUnits`` and ``ZUnits`` must be given.
- Gwyddion ``.gwy`` (gwyfile): the channel titled Height/Topography/Z unless
  one is named. A field without a lateral or height unit is refused.
- Gwyddion's ASCII data matrix export with its comment header (``# Value units: m``; any extension,
  ``stages/text_maps``); without the header the height unit is unknown and the file is refused.
- Igor binary wave ``.ibw`` (igor2) as Asylum Research writes it: a 3-D wave
  whose layers are labelled (``HeightRetrace``, ``AmplitudeRetrace``, ...);
  the Height layer is read (the trace before the retrace), heights in the wave's
  data units (empty: m on an Asylum image, refused otherwise).

Every reader returns an :class:`Image`, row 0 at the top of the scan, x to the
right, y down the rows.
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field

import numpy as np

from .afm_files import OTHER_DIRECTION, Channel, height_nm_per_unit, is_jpk, length_um, other_direction, \
    pick_channel, pixel_um_xy, read_spm_file, sniff_format
from .errors import MarkcalError
from .io import existing_file
from .text_maps import is_text_matrix, parse_text_matrix

__all__ = ["Image", "read_image", "parse_gsf", "gsf_bytes"]

_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_PICTURE_MAGIC = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"BM")          # PNG, JPEG, BMP
#: resolutions (per inch) that image editors and screens write by default
_SCREEN_DPI = (72.0, 96.0, 150.0, 300.0)


@dataclass(frozen=True)
class Image:
    """One image as read from a file.

    Attributes
    ----------
    data : ndarray (rows, cols), float64
        AFM: heights in nm. OM: grey values (counts) as stored.
    pixel_um : float
        Pixel size (µm), the same along x and y.
    kind : str
        ``"afm"`` or ``"om"`` as guessed from the file (height data or grey values).
    source : str
        The file path.
    meta : dict
        What the reader found (format, channel, units, notes).
    other_direction : ndarray (rows, cols) or None
        AFM: the same channel scanned the other way (the retrace of a trace, and back), in nm and the same
        orientation, where the file holds it (IBW, Bruker, NID, JPK); None otherwise.
    """

    data: np.ndarray
    pixel_um: float
    kind: str
    source: str
    meta: dict = field(default_factory=dict, repr=False)
    other_direction: np.ndarray | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple:
        return self.data.shape


def read_image(path, pixel_size_um: float | None = None, kind: str | None = None,
               channel: str | None = None) -> Image:
    """Read an OM image or AFM height map.

    Parameters
    ----------
    path : path
        TIFF, GSF, GWY, IBW, Bruker NanoScope, Nanosurf NID, JPK or WSxM file
        (recognised by content).
    pixel_size_um : float, optional
        Pixel size (µm); overrides whatever the file says.
    kind : {"afm", "om"}, optional
        Overrides the guess.
    channel : str, optional
        Channel of a multi-channel file (``"Height"``, ``"ZSensor retrace"``);
        default the height/topography channel, trace direction.

    Raises
    ------
    MarkcalError
        Missing or unreadable file, not an image, unknown channel (the message
        lists the file's channels), height unit unknown, no pixel size or a
        lateral size without a unit, pixels more than ``MAX_PIXEL_ASPECT`` times
        longer one way, all-NaN or constant data. The message names the file.
        Pixels that are not square are resampled to square ones (``meta["resampled"]``).
    """
    path, ext = existing_file(path)
    with open(path, "rb") as fh:
        head = fh.read(64)
    fmt = sniff_format(head)
    if fmt is not None:
        name = fmt
        reader = lambda p: (*_spm(p, fmt, channel),)             # noqa: E731
    else:
        by_ext = {".tif": _read_tiff, ".tiff": _read_tiff, ".gsf": _read_gsf, ".gwy": _read_gwy, ".ibw": _read_ibw,
                  ".png": _read_picture, ".jpg": _read_picture, ".jpeg": _read_picture, ".bmp": _read_picture}
        if head[:4] in _TIFF_MAGIC:
            name, read = "tiff", _read_tiff
        elif head.startswith(b"GWYP"):
            name, read = "gwy", _read_gwy
        elif head.startswith(_GSF_MAGIC[:21]):
            name, read = "gsf", _read_gsf
        elif head.startswith(_PICTURE_MAGIC):
            name, read = "picture", _read_picture
        elif is_text_matrix(head) or ext in (".txt", ".asc", ".dat", ".csv"):
            name, read = "text matrix", _read_text
        elif ext in by_ext:                       # no magic (Igor) or a damaged file: its reader says what is wrong
            name, read = ext[1:], by_ext[ext]
        else:
            raise MarkcalError("not a known image format (TIFF, PNG, JPEG, BMP, GSF, GWY, IBW, Bruker NanoScope, "
                               "Nanosurf NID, JPK, WSxM, Gwyddion text matrix)", path)
        reader = lambda p: read(p, channel)                      # noqa: E731
    try:
        data, px, guess, meta = reader(path)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    except (ValueError, OSError, EOFError, KeyError, IndexError, TypeError, AssertionError, RuntimeError,
            UnicodeDecodeError, struct.error, ZeroDivisionError, OverflowError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MarkcalError(f"not a readable {name.upper()} image ({first})", path) from None
    data = np.asarray(data, np.float64)
    other = meta.pop(OTHER_DIRECTION, None)
    if data.ndim != 2 or min(data.shape) < 8:
        raise MarkcalError(f"not a 2-D image (shape {data.shape})", path)
    fin = np.isfinite(data)
    if not fin.any():
        raise MarkcalError("image is all NaN", path)
    if np.ptp(data[fin]) == 0:
        raise MarkcalError("image is constant (no data)", path)
    if pixel_size_um is not None:
        if not (pixel_size_um > 0 and np.isfinite(pixel_size_um)):
            raise MarkcalError(f"--pixel-size-um must be positive, got {pixel_size_um}", path)
        px = float(pixel_size_um)
        meta = dict({k: v for k, v in meta.items() if k != "pixel_problem"}, pixel_source="override")
    if isinstance(px, tuple):
        # the other scan direction resampled alike: along y (fewer lines than points, the usual case) the fast axis
        # and the z loop's lag along it are untouched; along x both directions' lag is read in the new pixels
        if other is not None and np.shape(other) == data.shape:
            other = _square_pixels(np.asarray(other, np.float64), *px, meta, path)[0]
        else:
            other = None
        data, px, meta = _square_pixels(data, *px, meta, path)
        fin = np.isfinite(data)
    if px is None or not np.isfinite(px) or px <= 0:
        raise MarkcalError(f"{meta.get('pixel_problem', 'image has no pixel size')}: give --pixel-size-um", path)
    if kind is not None:
        if kind not in ("afm", "om"):
            raise MarkcalError(f"kind must be afm or om, got {kind!r}", path)
        guess = kind
    if guess == "afm":
        # an interrupted scan: the lines never scanned hold one value each (0 in the file) and would stand
        # as a plateau beside the map; a scanned line always has noise
        top = np.max(np.where(fin, data, -np.inf), axis=1)
        blank = (top == np.min(np.where(fin, data, np.inf), axis=1)) & (fin.sum(axis=1) >= 8)
        if blank.all():
            raise MarkcalError("every scan line is constant (no data)", path)
        if blank.any():
            data = data.copy()
            data[blank] = np.nan
            meta = dict(meta, blank_rows=int(blank.sum()))
        if other is not None:
            other = np.array(other, np.float64)
            other[~np.isfinite(data)] = np.nan
            if not np.isfinite(other).any():
                other = None
    else:
        other = None
    return Image(data=data, pixel_um=float(px), kind=guess, source=path, meta=meta, other_direction=other)


#: longest pixel side over the shortest that is still resampled to a map (beyond: lines, not a map)
MAX_PIXEL_ASPECT = 8.0


def _square_pixels(data, px_um, py_um, meta, path):
    """A map of pixels px_um x py_um (along x, along y) resampled to square pixels of the shorter side.

    Linear interpolation between the rows (or columns) of the longer side, which keeps every sample's
    height range and leaves NaN where a neighbour is missing. Returns (data, pixel_um, meta).
    """
    if not (px_um > 0 and py_um > 0 and np.isfinite(px_um) and np.isfinite(py_um)):
        raise MarkcalError(f"pixel size {px_um:g} x {py_um:g} µm is not positive", path)
    if max(px_um, py_um) > MAX_PIXEL_ASPECT * min(px_um, py_um):
        raise MarkcalError(f"pixels of {px_um * 1e3:g} x {py_um * 1e3:g} nm are more than {MAX_PIXEL_ASPECT:g} times "
                           "longer one way: lines, not a map", path)
    along_y = py_um > px_um
    z = data if along_y else data.T
    short, long_ = (px_um, py_um) if along_y else (py_um, px_um)
    n_old = z.shape[0]
    n_new = int(round(n_old * long_ / short))
    check_image_size((n_new, z.shape[1]), path)             # the resampled map must fit in memory too
    # markcal places pixel (i, j) at (j, i) x its size: old row i at i long_, new row j at j short (the last
    # new rows, past the old last line, hold it)
    pos = np.clip(np.arange(n_new) * short / long_, 0.0, n_old - 1.0)
    i0 = np.minimum(np.floor(pos).astype(int), n_old - 2) if n_old > 1 else np.zeros(n_new, int)
    w = (pos - i0)[:, None]
    out = z[i0] * (1.0 - w) + z[np.minimum(i0 + 1, n_old - 1)] * w
    out = out if along_y else out.T
    rows, cols = data.shape
    note = (f"{cols} x {rows} samples of {px_um * 1e3:.4g} x {py_um * 1e3:.4g} nm resampled to "
            f"{out.shape[1]} x {out.shape[0]} square pixels of {short * 1e3:.4g} nm (linear, along "
            f"{'y' if along_y else 'x'})")
    return out, float(short), dict(meta, resampled=note)


# ----------------------------------------------------------------------------- TIFF

def _spm(path, fmt, channel):
    data, px, meta = read_spm_file(path, fmt, channel)
    return data, px, "afm", meta


def _single_channel(name, channel):
    """Check a requested channel against the one channel of a single-channel file."""
    if channel is not None:
        pick_channel([Channel(name, None, None)], channel)


#: the largest image (pixels) read: 40000² float64 is 12.8 GB; markcal holds a few float64 copies
MAX_IMAGE_PIXELS = 200_000_000


def check_image_size(shape, path=None) -> None:
    """Refuse an image whose declared size would not fit in memory, before it is decoded."""
    n = int(np.prod([int(v) for v in shape])) if len(shape) else 0
    if n > MAX_IMAGE_PIXELS:
        raise MarkcalError(f"image declares {' x '.join(str(int(v)) for v in shape)} = {n:,} values; at most "
                           f"{MAX_IMAGE_PIXELS:,} are read (a few float64 copies must fit in memory)", path)


def _read_tiff(path, channel=None):
    import tifffile
    with tifffile.TiffFile(path) as tf:
        if is_jpk(tf):
            return _spm(path, "jpk", channel)
        page = tf.pages[0]
        check_image_size(page.shape, path)
        arr = page.asarray()
        ij = tf.imagej_metadata or {}
        ome = tf.ome_metadata
        fei = tf.fei_metadata or {}
        zeiss = tf.sem_metadata or {}
        tags = page.tags
        xres = tags.get("XResolution")
        runit = tags.get("ResolutionUnit")
        desc = page.description or ""
    arr = np.squeeze(arr)
    arr = _luminance(arr)
    if arr.ndim != 2:
        raise MarkcalError(f"not a single-plane image (shape {arr.shape})")
    meta = {"format": "tiff", "dtype": str(arr.dtype)}
    px, src = _tiff_pixel_um(ome, ij, fei, xres, runit, zeiss)
    _single_channel("image", channel)
    meta["pixel_source"] = src
    if np.issubdtype(arr.dtype, np.floating):
        zunit = ij.get("zunit") or _desc_key(desc, "zunit")
        data = arr.astype(np.float64)
        fin = data[np.isfinite(data)]
        if zunit is not None:
            if height_nm_per_unit(zunit) is None:
                raise MarkcalError(f"unknown height unit '{zunit}'")
            data = data * height_nm_per_unit(zunit)
            meta["z_unit_in_file"] = str(zunit)
        elif fin.size and np.ptp(fin) < 1e-4:
            data = data * 1e9
            meta["z_unit_in_file"] = "m (guessed from the range)"
        else:
            meta["z_unit_in_file"] = "nm (assumed)"
        return data, px, "afm", meta
    if arr.dtype == bool:
        raise MarkcalError("binary (1-bit) image: not a micrograph")
    meta["bits"] = int(arr.dtype.itemsize * 8)
    return arr.astype(np.float64), px, "om", meta


def _luminance(arr):
    """An RGB(A) micrograph as luminance (Rec. 601 weights); anything else as it is."""
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        return arr[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    return arr


def _read_picture(path, channel=None):
    """A PNG, JPEG or BMP micrograph (Pillow): grey values, RGB as luminance; no pixel size.

    These formats carry only a print or screen resolution (PNG pHYs, JPEG JFIF density, BMP pels per
    metre; 72 or 96 dpi when nobody set it), never a microscope's pixel: ``--pixel-size-um`` gives it.
    """
    from .plate_image import read_pixels
    arr, dpi, _camera = read_pixels(path, "")
    arr = np.squeeze(arr)
    bits = int(arr.dtype.itemsize * 8)
    arr = _luminance(arr)
    if arr.ndim != 2:
        raise MarkcalError(f"not a single-plane image (shape {arr.shape})")
    _single_channel("image", channel)
    res = f" (its {dpi[0]:.0f} dpi is a print or screen setting)" if dpi else ""
    meta = {"format": "picture", "bits": bits, "pixel_source": None,
            "pixel_problem": f"a PNG, JPEG or BMP file holds no microscope pixel size{res}"}
    return arr.astype(np.float64), None, "om", meta


def _tiff_pixel_um(ome, ij, fei, xres, runit, zeiss=None):
    """Pixel size (µm) and its source from OME-XML, ImageJ, FEI, Zeiss or cm resolution tags."""
    if ome:
        m = re.search(r'PhysicalSizeX="([0-9.eE+-]+)"', ome)
        if m:
            u = re.search(r'PhysicalSizeXUnit="([^"]+)"', ome)
            scale = length_um(u.group(1)) if u else 1.0          # OME default unit: µm
            if scale:
                return float(m.group(1)) * scale, "ome"
    per_unit = 0.0
    if xres is not None:
        num, den = xres.value if isinstance(xres.value, tuple) else (xres.value, 1)
        per_unit = num / den if den else 0.0
    unit_code = int(runit.value) if runit is not None else 2
    ij_scale = length_um(ij.get("unit")) if ij.get("unit") is not None else None
    if ij_scale and str(ij.get("unit")).strip().lower() != "inch" and per_unit > 0:
        return ij_scale / per_unit, "imagej"
    pw = (fei.get("Scan") or {}).get("PixelWidth") if isinstance(fei, dict) else None
    if pw:
        return float(pw) * 1e6, "fei"                           # FEI/Thermo PixelWidth: m
    # Zeiss SmartSEM (tag 34118, CZ_SEM, parsed by tifffile): ('Image Pixel Size', 65.1, 'nm')
    for key in ("ap_image_pixel_size", "ap_pixel_size"):
        v = (zeiss or {}).get(key)
        if isinstance(v, tuple) and len(v) == 3 and isinstance(v[1], (int, float)) and v[1] > 0 and length_um(v[2]):
            return float(v[1]) * length_um(v[2]), "zeiss"
    # resolution tags: only centimetres, and not an editor's dpi default written in cm
    if unit_code == 3 and per_unit > 0 and not any(abs(per_unit * 2.54 - d) < 0.01 * d for d in _SCREEN_DPI):
        return 1e4 / per_unit, "resolution tags"
    return None, None


def _desc_key(desc, key):
    m = re.search(rf"^{key}=(.*)$", desc or "", re.M)
    return m.group(1).strip() if m else None


# ----------------------------------------------------------------------------- GSF

_GSF_MAGIC = b"Gwyddion Simple Field 1.0\n"


def parse_gsf(buf: bytes):
    """Parse Gwyddion Simple Field bytes.

    Returns
    -------
    ndarray (YRes, XRes) float32, dict
        The field in its ZUnits and the header (keys as in the file).
    """
    if not buf.startswith(_GSF_MAGIC):
        raise MarkcalError("not a Gwyddion Simple Field file (bad magic line)")
    end = buf.find(b"\x00")
    if end < 0:
        raise MarkcalError("GSF header has no NUL terminator")
    header = {}
    for line in buf[len(_GSF_MAGIC):end].decode("utf-8").splitlines():
        if "=" in line:
            k, v = line.split("=", 1)
            header[k.strip()] = v.strip()
    start = end + (4 - end % 4)                      # 1-4 NULs pad the header to a multiple of 4
    xres, yres = int(header["XRes"]), int(header["YRes"])
    if xres < 1 or yres < 1:
        raise MarkcalError(f"GSF declares {xres} x {yres} pixels: no image")
    check_image_size((yres, xres))
    need = 4 * xres * yres
    if len(buf) - start < need:
        raise MarkcalError(f"GSF data truncated ({len(buf) - start} of {need} bytes)")
    data = np.frombuffer(buf, "<f4", count=xres * yres, offset=start).reshape(yres, xres)
    return data, header


def gsf_bytes(z, xreal_m: float, yreal_m: float, zunit: str = "m", title: str = "Height",
              extra: dict | None = None) -> bytes:
    """Gwyddion Simple Field bytes of a (rows, cols) field in ``zunit``; lateral sizes in m."""
    z = np.asarray(z, "<f4")
    lines = [f"XRes = {z.shape[1]}", f"YRes = {z.shape[0]}", f"XReal = {xreal_m!r}", f"YReal = {yreal_m!r}",
             "XYUnits = m", f"ZUnits = {zunit}", f"Title = {title}"]
    lines += [f"{k} = {v}" for k, v in (extra or {}).items()]
    head = _GSF_MAGIC + ("\n".join(lines) + "\n").encode("utf-8")
    head += b"\x00" * (4 - len(head) % 4)
    return head + z.tobytes()


def _read_gsf(path, channel=None):
    with open(path, "rb") as fh:
        buf = fh.read()
    data, h = parse_gsf(buf)
    _single_channel(h.get("Title") or "Height", channel)
    zu = h.get("ZUnits")
    if height_nm_per_unit(zu) is None:
        raise MarkcalError(f"height unit ZUnits '{zu}' is not a length" if zu else "no height unit (ZUnits)")
    meta = {"format": "gsf", "title": h.get("Title", ""), "z_unit_in_file": zu}
    xy = length_um(h.get("XYUnits"))
    px = None
    if xy is None:
        meta["pixel_problem"] = f"lateral size has no length unit (XYUnits '{h.get('XYUnits', '')}')"
    elif "XReal" in h:
        px = float(h["XReal"]) * xy / data.shape[1]
        if "YReal" in h:
            px = pixel_um_xy(float(h["XReal"]) * xy, float(h["YReal"]) * xy, data.shape[1], data.shape[0])
    return data.astype(np.float64) * height_nm_per_unit(zu), px, "afm", meta


# ----------------------------------------------------------------------------- text matrix

def _read_text(path, channel=None):
    with open(path, "rb") as fh:
        buf = fh.read()
    if b"\x00" in buf[:4096]:
        raise MarkcalError("not a text matrix (binary bytes)")
    try:
        text = buf.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = buf.decode("latin-1")
    data, px, meta = parse_text_matrix(text, channel)
    return data, px, "afm", meta


# ----------------------------------------------------------------------------- GWY

def _gwy_unit(f, key):
    u = f.get(key)
    return (u.get("unitstr") or "") if u is not None else ""


def _read_gwy(path, channel=None):
    import gwyfile
    obj = gwyfile.load(path)
    fields = gwyfile.util.get_datafields(obj)
    if not fields:
        raise MarkcalError("no data channel in the .gwy file")
    chans = [Channel(str(t), None, None) for t in fields]
    try:
        title = pick_channel(chans, channel).name
    except MarkcalError:
        if channel is not None:
            raise
        title = chans[0].name                     # one unnamed-height channel: take the first
    f = fields[title]
    data = np.asarray(f.data, np.float64)
    xy, zu = _gwy_unit(f, "si_unit_xy"), _gwy_unit(f, "si_unit_z")
    if height_nm_per_unit(zu) is None:
        what = f"is in '{zu}', not a length" if zu else "has no height unit"
        more = "; its lateral size has no unit either: give --pixel-size-um" if length_um(xy) is None else ""
        raise MarkcalError(f"channel '{title}' {what}{more}")
    meta = {"format": "gwy", "channel": title, "channels": [c.name for c in chans], "z_unit_in_file": zu}
    px = None
    if length_um(xy) is None:
        meta["pixel_problem"] = f"lateral size {f.xreal:g} has no length unit"
    elif f.xreal:
        px = float(f.xreal) * length_um(xy) / data.shape[1]
        if f.get("yreal"):
            px = pixel_um_xy(float(f.xreal) * length_um(xy), float(f["yreal"]) * length_um(xy),
                             data.shape[1], data.shape[0])
    return data * height_nm_per_unit(zu), px, "afm", meta


# ----------------------------------------------------------------------------- IBW

def _ibw_note(note) -> dict:
    text = note.decode("latin-1") if isinstance(note, (bytes, bytearray)) else str(note)
    out = {}
    for line in re.split(r"[\r\n]+", text):
        if ":" in line:
            k, v = line.split(":", 1)
            out[k.strip()] = v.strip()
    return out


def _read_ibw(path, channel=None):
    from igor2 import binarywave
    w = binarywave.load(path)["wave"]
    data = np.asarray(w["wData"])
    if data.dtype.kind not in "fiu":
        raise MarkcalError("Igor wave holds no numeric data")
    hdr = w["wave_header"]
    labels = w.get("labels") or [[], [], [], []]
    note = _ibw_note(w.get("note", b""))
    layer_names = [lab.decode("latin-1") if isinstance(lab, bytes) else str(lab)
                   for lab in (labels[2] if len(labels) > 2 else [])]
    layer_names = layer_names[1:] if layer_names else []        # the first is the dimension's own label
    other_plane = None                    # the same layer scanned the other way (trace / retrace)
    if data.ndim == 3:
        if layer_names:
            chans = [_ibw_channel(n, i) for i, n in enumerate(layer_names)]
            pick = pick_channel(chans, channel).load()
        else:
            _single_channel("layer 0", channel)
            pick = 0
        plane = data[:, :, pick]
        channel = layer_names[pick] if layer_names else "layer 0"
        if layer_names:
            other = other_direction(chans, chans[pick])
            if other is not None:
                other_plane = data[:, :, other.load()]
    elif data.ndim == 2:
        _single_channel("wave", channel)
        plane, channel = data, "wave"
    else:
        raise MarkcalError(f"Igor wave has {data.ndim} dimensions, need an image")
    # Igor: dim 0 = x (fast scan), dim 1 = y growing upwards -> rows from the top
    img = np.asarray(plane, np.float64).T[::-1]
    sfa = float(hdr["sfA"][0])
    dim_units = hdr["dimUnits"]
    try:
        xunit = b"".join(dim_units[0]).decode("latin-1").strip("\x00") or "m"
    except TypeError:
        xunit = "m"
    px = None
    if sfa > 0 and length_um(xunit):
        px = sfa * length_um(xunit)
        sfa_y = float(hdr["sfA"][1])
        if sfa_y > 0:                     # a scan of fewer lines than points (or the other way) on the field
            px = pixel_um_xy(px * img.shape[1], sfa_y * length_um(xunit) * img.shape[0],
                             img.shape[1], img.shape[0])
    elif "ScanSize" in note:
        px = float(note["ScanSize"]) * 1e6 / img.shape[1]
    zscale, z_unit = _ibw_height_unit(w, hdr, bool(layer_names) or "ScanSize" in note, channel)
    meta = {"format": "ibw", "channel": channel, "layers": layer_names, "z_unit_in_file": z_unit,
            "scan_size_um": float(note["ScanSize"]) * 1e6 if "ScanSize" in note else None,
            "imaging_mode": note.get("ImagingMode", "")}
    if other_plane is not None:
        meta[OTHER_DIRECTION] = np.asarray(other_plane, np.float64).T[::-1] * zscale
    return img * zscale, px, "afm", meta


def _ibw_height_unit(w, hdr, asylum: bool, channel: str) -> tuple:
    """nm per stored unit of an Igor wave's heights and the unit as found: the wave's data units (extended ones
    first), else, for an Asylum Research image (labelled layers or its note's ``ScanSize``) whose data units
    are empty, Asylum's convention of SI metres for its height layers. Raises where neither tells a length."""
    ext = w.get("data_units", b"") or b""
    short = b"".join(hdr["dataUnits"]) if not isinstance(hdr["dataUnits"], bytes) else hdr["dataUnits"]
    unit = (ext or short).decode("latin-1").replace("\x00", "").strip()
    if unit:
        nm = height_nm_per_unit(unit)
        if nm is None:
            raise MarkcalError(f"channel '{channel}' is in '{unit}', not a height unit")
        return nm, unit
    if asylum:
        return 1e9, "m (Asylum's convention: the wave's data units are empty)"
    raise MarkcalError("Igor wave has no data units and is not an Asylum Research image: its height unit is "
                       "unknown")


def _ibw_channel(label, index) -> Channel:
    """An Asylum layer label (``HeightRetrace``) as a channel; ``load()`` gives the layer index."""
    m = re.match(r"(.+?)(Trace|Retrace)$", label)
    name, direction = (m.group(1), m.group(2).lower()) if m else (label, None)
    return Channel(name, direction, lambda: index)
