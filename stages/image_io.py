"""Readers of OM images and AFM height maps. Everything leaves here in µm and nm.

Like ``stages/io`` (point clouds) this is the one place of the indents flow
that reads files; units are converted here and nowhere else.

Supported:

- TIFF (tifffile): grey-scale 8/16-bit (OM) or float (AFM heights). Pixel size
  from ImageJ metadata (``unit`` + resolution), OME-XML ``PhysicalSizeX``, or
  the TIFF resolution tags (inch or cm units). Float heights carry their unit in
  the ImageJ key ``zunit`` (nm, um, m); without it a map whose range is below
  1e-4 is taken to be in m, otherwise in nm.
- Gwyddion Simple Field ``.gsf`` (hand-written reader; the format is a text
  header plus little-endian float32).
- Gwyddion ``.gwy`` (gwyfile): the first channel titled Height/Topography/Z,
  else the first channel.
- Igor binary wave ``.ibw`` (igor2) as Asylum Research writes it: a 3-D wave
  whose layers are labelled (``HeightRetrace``, ``AmplitudeRetrace``, ...);
  the Height layer is read (the trace before the retrace), heights in m.

Every reader returns an :class:`Image`, row 0 at the top of the scan, x to the
right, y down the rows.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from .errors import MarkcalError
from .io import existing_file

__all__ = ["Image", "read_image", "parse_gsf", "gsf_bytes"]

#: length unit name -> µm
_LEN_UM = {"m": 1e6, "mm": 1e3, "cm": 1e4, "um": 1.0, "µm": 1.0, "μm": 1.0, "micron": 1.0,
           "microns": 1.0, "micrometer": 1.0, "micrometre": 1.0, "nm": 1e-3, "inch": 25400.0,
           "\\u00B5m": 1.0, "pixel": None, "": None}
#: height unit name -> nm
_Z_NM = {"m": 1e9, "mm": 1e6, "um": 1e3, "µm": 1e3, "μm": 1e3, "micron": 1e3, "nm": 1.0, "pm": 1e-3,
         "a": 0.1, "å": 0.1}


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
    """

    data: np.ndarray
    pixel_um: float
    kind: str
    source: str
    meta: dict = field(default_factory=dict, repr=False)

    @property
    def shape(self) -> tuple:
        return self.data.shape


def read_image(path, pixel_size_um: float | None = None, kind: str | None = None) -> Image:
    """Read an OM image or AFM height map.

    Parameters
    ----------
    path : path
        ``.tif/.tiff``, ``.gsf``, ``.gwy`` or ``.ibw``.
    pixel_size_um : float, optional
        Pixel size (µm); overrides whatever the file says.
    kind : {"afm", "om"}, optional
        Overrides the guess.

    Raises
    ------
    MarkcalError
        Missing or unreadable file, not an image, no pixel size, all-NaN or
        constant data. The message names the file.
    """
    path, ext = existing_file(path)
    readers = {".tif": _read_tiff, ".tiff": _read_tiff, ".gsf": _read_gsf, ".gwy": _read_gwy,
               ".ibw": _read_ibw}
    if ext not in readers:
        raise MarkcalError(f"unknown image extension '{ext}' (use .tif, .tiff, .gsf, .gwy or .ibw)", path)
    try:
        data, px, guess, meta = readers[ext](path)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    except (ValueError, OSError, EOFError, KeyError, IndexError, TypeError, AssertionError, RuntimeError,
            UnicodeDecodeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise MarkcalError(f"not a readable {ext[1:].upper()} image ({first})", path) from None
    data = np.asarray(data, np.float64)
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
        meta = dict(meta, pixel_source="override")
    if px is None or not np.isfinite(px) or px <= 0:
        raise MarkcalError("image has no pixel size: give --pixel-size-um", path)
    if kind is not None:
        if kind not in ("afm", "om"):
            raise MarkcalError(f"kind must be afm or om, got {kind!r}", path)
        guess = kind
    return Image(data=data, pixel_um=float(px), kind=guess, source=path, meta=meta)


# ----------------------------------------------------------------------------- TIFF

def _unit_um(name) -> float | None:
    if name is None:
        return None
    key = str(name).strip().lower().replace("\\u00b5", "µ")
    return _LEN_UM.get(key)


def _read_tiff(path):
    import tifffile
    with tifffile.TiffFile(path) as tf:
        page = tf.pages[0]
        arr = page.asarray()
        ij = tf.imagej_metadata or {}
        ome = tf.ome_metadata
        tags = page.tags
        xres = tags.get("XResolution")
        runit = tags.get("ResolutionUnit")
        desc = page.description or ""
    arr = np.squeeze(arr)
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):           # RGB(A) micrograph: luminance
        arr = arr[..., :3].astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    if arr.ndim != 2:
        raise MarkcalError(f"not a single-plane image (shape {arr.shape})")
    meta = {"format": "tiff", "dtype": str(arr.dtype)}
    px = None
    src = None
    if ome:
        m = re.search(r'PhysicalSizeX="([0-9.eE+-]+)"', ome)
        if m:
            u = re.search(r'PhysicalSizeXUnit="([^"]+)"', ome)
            scale = _unit_um(u.group(1)) if u else 1.0           # OME default unit: µm
            if scale:
                px, src = float(m.group(1)) * scale, "ome"
    if px is None and xres is not None:
        num, den = xres.value if isinstance(xres.value, tuple) else (xres.value, 1)
        per_unit = num / den if den else 0.0
        unit_code = int(runit.value) if runit is not None else 2
        scale = None
        if ij.get("unit") is not None:
            scale = _unit_um(ij.get("unit"))
        elif unit_code == 2:
            scale = 25400.0
        elif unit_code == 3:
            scale = 1e4
        # a 72 or 96 dpi default written by an image editor is no pixel size
        if scale and per_unit > 0 and not (unit_code == 2 and ij.get("unit") is None and per_unit in (72, 96, 300)):
            px, src = scale / per_unit, ("imagej" if ij.get("unit") else "resolution tags")
    meta["pixel_source"] = src
    if np.issubdtype(arr.dtype, np.floating):
        zunit = ij.get("zunit") or _desc_key(desc, "zunit")
        data = arr.astype(np.float64)
        fin = data[np.isfinite(data)]
        if zunit is not None:
            if str(zunit).lower() not in _Z_NM:
                raise MarkcalError(f"unknown height unit '{zunit}'")
            data = data * _Z_NM[str(zunit).lower()]
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


def _read_gsf(path):
    with open(path, "rb") as fh:
        buf = fh.read()
    data, h = parse_gsf(buf)
    xy = _unit_um(h.get("XYUnits", "m"))
    if xy is None:
        raise MarkcalError(f"unknown lateral unit '{h.get('XYUnits')}'")
    px = float(h["XReal"]) * xy / data.shape[1] if "XReal" in h else None
    zu = h.get("ZUnits", "m").lower()
    if zu not in _Z_NM:
        raise MarkcalError(f"unknown height unit '{h.get('ZUnits')}'")
    return data.astype(np.float64) * _Z_NM[zu], px, "afm", {"format": "gsf", "title": h.get("Title", ""),
                                                              "z_unit_in_file": zu}


# ----------------------------------------------------------------------------- GWY

_HEIGHT_TITLES = ("height", "topography", "z", "zsensor", "heightretrace", "height retrace")


def _read_gwy(path):
    import gwyfile
    obj = gwyfile.load(path)
    fields = gwyfile.util.get_datafields(obj)
    if not fields:
        raise MarkcalError("no data channel in the .gwy file")
    title = next((t for t in fields if str(t).strip().lower() in _HEIGHT_TITLES), next(iter(fields)))
    f = fields[title]
    data = np.asarray(f.data, np.float64)
    xy = (f.get("si_unit_xy") or {}).get("unitstr", "m") if f.get("si_unit_xy") is not None else "m"
    zu = (f.get("si_unit_z") or {}).get("unitstr", "m") if f.get("si_unit_z") is not None else "m"
    xy_um = _unit_um(xy or "m")
    if xy_um is None:
        raise MarkcalError(f"unknown lateral unit '{xy}'")
    if (zu or "m").lower() not in _Z_NM:
        raise MarkcalError(f"channel '{title}' is not a height (unit '{zu}')")
    px = float(f.xreal) * xy_um / data.shape[1] if f.xreal else None
    return data * _Z_NM[(zu or "m").lower()], px, "afm", {"format": "gwy", "channel": str(title),
                                                           "z_unit_in_file": zu or "m"}


# ----------------------------------------------------------------------------- IBW

def _ibw_note(note) -> dict:
    text = note.decode("latin-1") if isinstance(note, (bytes, bytearray)) else str(note)
    out = {}
    for line in re.split(r"[\r\n]+", text):
        if ":" in line:
            k, v = line.split(":", 1)
            out[k.strip()] = v.strip()
    return out


def _read_ibw(path):
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
    if data.ndim == 3:
        names_l = [n.lower() for n in layer_names]
        pick = next((i for i, n in enumerate(names_l) if n.startswith("height")), None)
        if pick is None:
            pick = next((i for i, n in enumerate(names_l) if n.startswith("zsensor")), None)
        if pick is None:
            if layer_names:
                raise MarkcalError(f"no Height channel among {layer_names}")
            pick = 0
        plane = data[:, :, pick]
        channel = layer_names[pick] if layer_names else "layer 0"
    elif data.ndim == 2:
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
    if sfa > 0 and _unit_um(xunit):
        px = sfa * _unit_um(xunit)
    elif "ScanSize" in note:
        px = float(note["ScanSize"]) * 1e6 / img.shape[1]
    fin = img[np.isfinite(img)]
    # Asylum stores heights in m; a wave in nm would have a range far above 1e-4
    zscale = 1e9 if fin.size and np.ptp(fin) < 1e-3 else 1.0
    meta = {"format": "ibw", "channel": channel, "layers": layer_names,
            "z_unit_in_file": "m" if zscale == 1e9 else "nm (guessed from the range)",
            "scan_size_um": float(note["ScanSize"]) * 1e6 if "ScanSize" in note else None,
            "imaging_mode": note.get("ImagingMode", "")}
    return img * zscale, px, "afm", meta
