"""Flatbed or camera images of a marked plate: reading, pixel size, and the raster the detection uses.

An image needs no plane fit and no projection: its pixels are the plate
raster, x to the right (columns), y down the rows, in mm through the pixel
size. The pixel size comes from ``--pixel-size-mm`` or from the file's
resolution (TIFF XResolution/ResolutionUnit, PNG pHYs, JPEG JFIF density, as
Pillow and tifffile report them); 72 and 96 dpi are what screens and image
editors write when nobody measured anything, so they are refused like a
missing resolution. A flatbed scanner's dpi is its real sampling.

Grey or RGB (luminance, Rec. 601 weights), 8 or 16 bit. Marks brighter than
the plate (laser-marked anodised aluminium) are inverted so the rings are
always darker. Integer pixels stay integers (one copy of a grey image, none
more); the ring fits convert only the samples they use.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .io import existing_file
from .plane import Plane
from .project import Raster

IMAGE_EXTS = (".tif", ".tiff", ".png", ".jpg", ".jpeg")
#: resolutions (per inch) written by screens and editors, not by a measuring device
DEFAULT_DPI = (72.0, 96.0)
#: a mark site needs this many pixels across the 0.2 mm ring gap
MIN_GAP_PX = 3.0


@dataclass(frozen=True)
class PlateImage:
    """Grey pixels (uint8/uint16 as read, float32 otherwise; rings darker) and the pixel size (mm)."""

    intensity: np.ndarray
    pixel_mm: float
    pixel_size_from: str
    bits: int
    inverted: bool


def _focal_text(focal, make, model) -> str | None:
    """'focal length 35 mm, Canon EOS 5D' from EXIF values (a rational may come as a pair), or None."""
    try:
        f = float(focal[0]) / float(focal[1]) if isinstance(focal, tuple) else float(focal)
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    if not (np.isfinite(f) and f > 0):
        return None
    who = " ".join(str(v).strip("\0 ") for v in (make, model) if v)
    return f"focal length {f:g} mm" + (f", {who}" if who else "")


def read_pixels(path: str, ext: str) -> tuple:
    """Pixels as an array, the resolution as (dpi_x, dpi_y) or None, and the camera the EXIF names or None."""
    if ext in (".tif", ".tiff"):
        import tifffile
        try:
            with tifffile.TiffFile(path) as tf:
                page = tf.pages[0]
                arr = page.asarray()
                tags = page.tags
                exif = tags["ExifTag"].value if "ExifTag" in tags else {}
                camera = _focal_text(exif.get("FocalLength") if isinstance(exif, dict) else None,
                                     *(tags[k].value if k in tags else None for k in ("Make", "Model")))
                dpi = None
                if "XResolution" in tags and "YResolution" in tags:
                    unit = tags["ResolutionUnit"].value if "ResolutionUnit" in tags else 2
                    per = {2: 1.0, 3: 2.54}.get(int(unit))
                    xr, yr = (tags[k].value for k in ("XResolution", "YResolution"))
                    if per is not None and xr[1] and yr[1]:
                        dpi = (xr[0] / xr[1] * per, yr[0] / yr[1] * per)
        except (OSError, ValueError, tifffile.TiffFileError, IndexError, KeyError) as exc:
            raise MarkcalError(f"cannot read TIFF ({exc})") from None
        return arr, dpi, camera
    from PIL import Image, UnidentifiedImageError
    Image.MAX_IMAGE_PIXELS = 400_000_000
    try:
        with Image.open(path) as im:
            dpi = im.info.get("dpi")
            try:        # a damaged EXIF block says nothing about a camera; the pixels may still be fine
                exif = im.getexif()
                camera = _focal_text(exif.get_ifd(0x8769).get(0x920A), exif.get(0x010F), exif.get(0x0110))
            except (OSError, ValueError, TypeError, KeyError, SyntaxError):
                camera = None
            if im.mode in ("P", "PA", "LA", "RGBA", "CMYK", "YCbCr", "1"):
                im = im.convert("RGB")
            arr = np.asarray(im)
    except (OSError, ValueError, UnidentifiedImageError, Image.DecompressionBombError) as exc:
        raise MarkcalError(f"cannot read image ({exc})") from None
    return arr, (tuple(float(v) for v in dpi) if dpi else None), camera


def _grey(arr: np.ndarray) -> tuple:
    """Grey pixels (8/16-bit integers stay integers: no float copy of a large image) and the bit depth."""
    import cv2
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8)
    if arr.dtype not in (np.uint8, np.uint16) and not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float32)
    bits = 8 * arr.dtype.itemsize if arr.dtype in (np.uint8, np.uint16) else 32
    if arr.ndim == 3 and arr.shape[0] in (3, 4) and arr.shape[-1] not in (3, 4):     # planar RGB TIFF
        arr = np.moveaxis(arr, 0, -1)
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        if arr.dtype not in (np.uint8, np.uint16, np.float32):
            arr = arr.astype(np.float32)
        code = cv2.COLOR_RGB2GRAY if arr.shape[-1] == 3 else cv2.COLOR_RGBA2GRAY   # Rec. 601 weights
        return cv2.cvtColor(np.ascontiguousarray(arr), code), bits
    if arr.ndim != 2:
        raise MarkcalError(f"image has shape {arr.shape}: expected a grey or RGB picture")
    return (arr if arr.dtype in (np.uint8, np.uint16) else arr.astype(np.float32)), bits


def read_plate_image(path, pixel_size_mm: float | None = None, refuse_camera: bool = True) -> PlateImage:
    """Read a plate image (TIFF, PNG, JPEG), grey or RGB, 8/16 bit.

    Parameters
    ----------
    pixel_size_mm : float, optional
        Side of a pixel on the plate (mm); default: from the file's resolution.
    refuse_camera : bool
        Refuse a file whose EXIF gives a lens focal length (a camera took it).

    Raises
    ------
    MarkcalError
        Unreadable file, a camera's image, unknown pixel size, unsupported layout.
    """
    path, ext = existing_file(path)
    arr, dpi, camera = read_pixels(path, ext)
    if camera and refuse_camera:
        raise MarkcalError(f"the image was taken through a camera lens (EXIF: {camera}): markcal cannot tell a "
                           "camera's perspective and lens distortion from the galvo's on one image of the marked "
                           "plate: image the plate on a flatbed scanner or measure it with a 3D scanner (--view "
                           "flatbed takes the image as a flat view)")
    if dpi is not None:     # PNG stores pixels per metre: 1200 dpi comes back as 1199.998
        dpi = tuple(float(np.rint(d)) if abs(d - np.rint(d)) < 0.02 else float(d) for d in dpi)
    if pixel_size_mm is not None:
        if not (np.isfinite(pixel_size_mm) and pixel_size_mm > 0):
            raise MarkcalError(f"--pixel-size-mm must be positive (got {pixel_size_mm})")
        px, src = float(pixel_size_mm), "--pixel-size-mm"
    elif dpi is None or not all(np.isfinite(dpi)) or min(dpi) <= 0:
        raise MarkcalError("the image has no pixel size (no resolution tags): give --pixel-size-mm")
    elif any(abs(d - s) < 0.5 for d in dpi for s in DEFAULT_DPI):
        raise MarkcalError(f"the image's resolution is {dpi[0]:g} dpi, a screen/editor default rather "
                           "than a measured one: give --pixel-size-mm")
    elif abs(dpi[0] / dpi[1] - 1) > 1e-3:
        raise MarkcalError(f"the image has non-square pixels ({dpi[0]:g} x {dpi[1]:g} dpi)")
    else:
        px, src = 25.4 / dpi[0], f"{dpi[0]:g} dpi resolution tag"
    grey, bits = _grey(arr)
    del arr
    if grey.shape[0] < 16 or grey.shape[1] < 16:
        raise MarkcalError(f"the image is only {grey.shape[1]} x {grey.shape[0]} pixels")
    if not np.all(np.isfinite(grey[::7, ::7])):
        raise MarkcalError("the image holds NaN or infinite pixels")
    # marks are a few percent of the plate: their side of the median has the longer tail
    sub = grey[::4, ::4]
    lo, med, hi = np.percentile(sub, [1, 50, 99])
    inverted = bool(hi - med > 1.2 * (med - lo))
    if inverted:
        if not grey.flags.writeable:
            grey = grey.copy()
        np.subtract(grey.max(), grey, out=grey)
    return PlateImage(intensity=grey, pixel_mm=px, pixel_size_from=src, bits=bits, inverted=inverted)


def check_image_size(image: PlateImage, spec) -> None:
    """Refuse images too coarse to resolve the ring gap or too small to hold a few marks."""
    radii = sorted(spec.ring_radii_mm)
    gap = radii[1] - radii[0] if len(radii) > 1 else radii[0]
    if gap / image.pixel_mm < MIN_GAP_PX:
        raise MarkcalError(f"pixels of {image.pixel_mm:.3f} mm give {gap / image.pixel_mm:.1f} samples across "
                           f"the {gap:g} mm ring gap; at least {MIN_GAP_PX:g} are needed")
    h, w = image.intensity.shape
    need = 2 * spec.pitch_mm
    if min(h, w) * image.pixel_mm < need:
        raise MarkcalError(f"the image covers {w * image.pixel_mm:.1f} x {h * image.pixel_mm:.1f} mm, too small "
                           f"for a grid of pitch {spec.pitch_mm:.2f} mm (needs {need:.1f} mm a side)")


def image_raster(image: PlateImage) -> Raster:
    """The image as a plate raster (u = column, v = row, mm; every pixel valid; no copy)."""
    return Raster(intensity=image.intensity, u_mm=None, v_mm=None, valid=None, u0_mm=0.0, v0_mm=0.0,
                  pixel_mm=image.pixel_mm)


def coarse_raster(raster: Raster, target_mm: float) -> Raster:
    """Area-averaged copy with pixels of about ``target_mm`` (the detection's coarse steps)."""
    import cv2
    f = max(1, int(round(target_mm / raster.pixel_mm)))
    if f == 1:
        return raster
    h, w = raster.intensity.shape
    small = cv2.resize(raster.intensity[:h // f * f, :w // f * f], (w // f, h // f), interpolation=cv2.INTER_AREA)
    return Raster(intensity=small, u_mm=None, v_mm=None, valid=None, u0_mm=raster.u0_mm, v0_mm=raster.v0_mm,
                  pixel_mm=raster.pixel_mm * f)


def flat_plane() -> Plane:
    """The image plane as the plate plane: (u, v) -> (u, v, 0)."""
    return Plane(origin_mm=np.zeros(3), normal=np.array([0.0, 0.0, 1.0]), e_u=np.array([1.0, 0.0, 0.0]),
                 e_v=np.array([0.0, 1.0, 0.0]), rms_mm=0.0, inlier_fraction=1.0, threshold_mm=0.0)


#: a flat (flatbed-like) view: opposite edges of the fitted mark grid agree in length within this
#: fraction. A galvo's own field gives up to 0.10 % on a 19 x 19 plate (200 rendered machines at any turn);
#: a camera tilted 1 deg whose view spans +-0.2 rad gives up to 0.7 % (2 tan(tilt) x half-extent / distance).
MAX_KEYSTONE = 0.003
#: the limit when the pixel size comes from the file's own scanner resolution tag (cameras write none, or a
#: 72/96 dpi screen default that is refused): above the 1.5 % a raw, uncorrected galvo field shows on the
#: two real EZCAD tables, so a flatbed image of a plate marked without lens correction is taken; a camera
#: tilted more than about 3 deg is still refused
MAX_KEYSTONE_SCANNER_DPI = 0.02
#: ``--view``: "auto" refuses an image with more keystone (a camera); "flatbed" takes it as a flat view
VIEWS = ("auto", "flatbed")


@dataclass(frozen=True)
class ViewGeometry:
    """How far the detected grid is from a flat, orthographic view.

    ``keystone``: the largest relative length difference of opposite edges of
    the grid's outline under the best homography (0 for any similarity or
    affine map); ``perspective_mm``: the largest shift the homography's
    perspective terms cause at the outline's corners beyond the best affine map.
    """

    keystone: float
    perspective_mm: float


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares (normalised DLT) homography src -> dst, 3 x 3, H[2, 2] = 1."""
    def norm(p):
        c = p.mean(axis=0)
        s = np.sqrt(2.0) / max(np.mean(np.linalg.norm(p - c, axis=1)), 1e-12)
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])
    ts, td = norm(src), norm(dst)
    a = np.c_[src, np.ones(len(src))] @ ts.T
    b = np.c_[dst, np.ones(len(dst))] @ td.T
    z, o = np.zeros((len(a), 3)), np.ones(len(a))
    rows = np.vstack([np.c_[a, z, -b[:, :1] * a], np.c_[z, a, -b[:, 1:2] * a]])
    h = np.linalg.svd(rows)[2][-1].reshape(3, 3)
    h = np.linalg.inv(td) @ h @ ts
    return h / h[2, 2]


def _apply(h: np.ndarray, p: np.ndarray) -> np.ndarray:
    q = np.c_[p, np.ones(len(p))] @ h.T
    return q[:, :2] / q[:, 2:]


def view_geometry(uv_mm: np.ndarray, pitch_mm: float) -> ViewGeometry:
    """Perspective of the detected marks: homography from the ideal lattice to the detected centres.

    Parameters
    ----------
    uv_mm : ndarray, shape (n, 2)
        Detected mark centres (image mm).
    pitch_mm : float
        The plate's pitch.
    """
    from .register import lattice_coords
    lat = lattice_coords(uv_mm, pitch_mm)
    src = lat.k[lat.good] * pitch_mm
    dst = np.asarray(uv_mm, float)[lat.good]
    if len(src) < 8 or np.linalg.matrix_rank(src - src.mean(axis=0)) < 2:
        return ViewGeometry(0.0, 0.0)
    return perspective_of(src, dst)


def perspective_of(src_mm: np.ndarray, dst_mm: np.ndarray) -> ViewGeometry:
    """Keystone and perspective shift of the best homography from ideal points to measured ones."""
    src, dst = np.asarray(src_mm, float), np.asarray(dst_mm, float)
    h = _homography(src, dst)
    lo, hi = src.min(axis=0), src.max(axis=0)
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    c = _apply(h, corners)
    edge = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)          # bottom, right, top, left
    keystone = max(abs(edge[0] / edge[2] - 1), abs(edge[1] / edge[3] - 1))
    a_aff = np.linalg.lstsq(np.c_[src, np.ones(len(src))], _apply(h, src), rcond=None)[0]
    persp = np.linalg.norm(c - np.c_[corners, np.ones(4)] @ a_aff, axis=1).max()
    return ViewGeometry(float(keystone), float(persp))

def check_flat_view(uv_mm: np.ndarray, pitch_mm: float, refuse: bool = True,
                    max_keystone: float = MAX_KEYSTONE) -> ViewGeometry:
    """The view's perspective (``view_geometry``); refused above ``max_keystone`` when ``refuse``.

    Raises
    ------
    MarkcalError
        Keystone above ``max_keystone``: the message gives it and what to do.
    """
    g = view_geometry(uv_mm, pitch_mm)
    if refuse and g.keystone > max_keystone:
        raise MarkcalError(
            f"the image shows perspective: opposite edges of the mark grid differ in length by "
            f"{100 * g.keystone:.2f} % (keystone; the marks sit up to {g.perspective_mm:.2f} mm off a flat view; "
            f"refused above {100 * max_keystone:.1f} %): a camera view? markcal cannot tell a camera's perspective "
            "and lens distortion from the galvo's on one image of the marked plate: image the plate on a "
            "flatbed scanner or measure it with a 3D scanner; if this is a flatbed image (a plate marked with "
            "no lens correction can show up to 1.5 %), give --view flatbed")
    return g
