"""Readers of vendor AFM files and physical pixel sizes, against reference values and truth.

Real files come from ``../shared/realdata`` (sources and licences in its README):
Bruker NanoScope (jmarini/nanoscope, MIT; AFM-SPM/TopoStats, GPL-3.0), Nanosurf NID
(syrupface/NSFopen, MIT), JPK and WSxM (AFM-SPM/AFMReader, LGPL-3.0), Gwyddion
(tuxu/gwyfile, MIT), Thermo/FEI SEM TIFF (vyastreb/sem2surface, BSD-3-Clause).
Tests that need them skip when the folder is absent. Synthetic files are written
here byte by byte from known heights, not with markcal's code.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from markcal.pipeline.cli import main
from markcal.stages.errors import MarkcalError
from markcal.stages.image_io import read_image
from realdata import realdata_root


REAL = realdata_root()


def _real(rel: str) -> str:
    p = REAL / rel
    if not p.is_file():
        pytest.skip(f"real file {rel} not present (../shared/realdata)")
    return str(p)


def _quiet_afmreader():
    afm = pytest.importorskip("AFMReader")
    from loguru import logger
    logger.disable("AFMReader")
    return afm


# ----------------------------------------------------------------------------- real files

def test_bruker_nanoscope_against_reference_csv():
    """Raw counts exactly, and jmarini/nanoscope's per-line flattened nm values within its 0.1 nm."""
    path = _real("afm/bruker_nanoscope/full_multiple_images.txt")
    raw_ref = np.loadtxt(REAL / "afm/bruker_nanoscope/reference_raw.csv", delimiter=",")
    conv_ref = np.loadtxt(REAL / "afm/bruker_nanoscope/reference_converted.csv", delimiter=",")
    im = read_image(path)
    assert im.shape == (512, 512) and im.kind == "afm"
    assert im.meta["channel"] == "Height retrace" and "Amplitude retrace" in im.meta["channels"]
    assert im.pixel_um == pytest.approx(2.0 / 512, rel=1e-12)           # "Scan size: 2 2 ~m", 512 samples
    nm_per_lsb = 0.006693481 * 12.95302                                    # header: V/LSB x Sens. Zscan nm/V
    stored = im.data[::-1]                                                 # file order: first line = bottom
    assert np.abs(stored / nm_per_lsb - raw_ref).max() < 1e-6
    x = np.arange(512)
    flat = np.array([row - np.polyval(np.polyfit(x, row, 1), x) for row in stored])
    assert np.abs(flat - conv_ref).max() < 0.1                             # reference is rounded, 0.087 nm/LSB
    with pytest.raises(MarkcalError, match="Amplitude retrace.*not a height"):
        read_image(path, channel="amplitude")


@pytest.mark.parametrize("name", ["old_bruker.002", "old_bruker.004"])
def test_bruker_legacy_against_afmreader(name):
    path = _real(f"afm/bruker_legacy/{name}")
    im = read_image(path)
    assert im.shape == (256, 256) and im.meta["channel"] == "Height trace"
    assert im.pixel_um == pytest.approx(15.0 / 256, rel=1e-12)
    afm = _quiet_afmreader()
    from AFMReader.spm import load_spm
    try:
        ref, px_nm = load_spm(path, "Height")
    except Exception as exc:  # noqa: BLE001  the independent reader, not markcal, failed (pySPM < 0.6)
        pytest.skip(f"AFMReader cannot read {name} here ({type(exc).__name__}: {exc})")
    assert px_nm == pytest.approx(im.pixel_um * 1e3, rel=1e-9)
    # pySPM scales by the soft Z scale / 2^16, markcal by the hard V/LSB value: 1.5e-5 apart
    assert np.allclose(im.data, ref, rtol=5e-5, atol=0.01)
    assert afm is not None


def test_jpk_reference_values_in_nm():
    """AFMReader 0.0.7 ``load_jpk(f, "height_trace")`` values are nm: the file's slot unit is m."""
    path = _real("afm/jpk_wsxm/sample_0.jpk")
    im = read_image(path)
    assert im.shape == (256, 256) and im.meta["channel"] == "height trace" and im.meta["z_unit_in_file"] == "m"
    assert im.pixel_um * 1e3 == pytest.approx(1.27702, abs=1e-5)
    assert abs(im.data.min() - 3303) <= 0.5 and abs(im.data.max() - 3361) <= 0.5
    assert abs(im.data.mean() - 3345.37) <= 0.005
    retrace = read_image(path, channel="height_retrace")
    assert retrace.meta["channel"] == "height retrace" and not np.array_equal(retrace.data, im.data)
    with pytest.raises(MarkcalError, match=r"no channel 'Deflection'.*measuredHeight trace"):
        read_image(path, channel="Deflection")


def test_wsxm_stp_reference_and_top_equals_stp():
    stp = read_image(_real("afm/jpk_wsxm/sample_0.stp"))
    top = read_image(_real("afm/jpk_wsxm/sample_0.top"))
    for im in (stp, top):
        assert im.shape == (512, 512) and im.pixel_um * 1e3 == pytest.approx(0.9765625, rel=1e-12)
    assert stp.data.min() == pytest.approx(-80.8, abs=0.005) and stp.data.max() == pytest.approx(-21.05, abs=0.005)
    assert stp.data.mean() == pytest.approx(-57.4899, abs=5e-4)
    # the int16 .top of the same scan: its full range spans "Z Amplitude: 59.7449 nm"
    assert np.abs(top.data - stp.data).max() < 1e-6
    # AFMReader's load_top rescales to [0, int(Z Amplitude)] = [0, 59]: its published mean follows from ours
    assert (top.data - top.data.min()).mean() * 59 / 59.7449 == pytest.approx(23.0194, abs=5e-4)


@pytest.mark.parametrize("name,scan_um,channel", [("grid1", 3.0, "Z-Axis trace"), ("circles", 50.0, "Topography trace"),
                                                   ("sapphire", 2.5, "Z-Axis trace")])
def test_nid_scan_sizes_and_nsfopen(name, scan_um, channel):
    path = _real(f"afm/nanosurf_nid/{name}.nid")
    im = read_image(path)
    assert im.shape == (256, 256) and im.meta["channel"] == channel
    assert im.pixel_um * 256 == pytest.approx(scan_um, rel=1e-9)
    nsf = pytest.importorskip("NSFopen.read")
    try:
        ref = nsf.read(path).data["Image"]["Forward"][channel.split(" ")[0]]
    except Exception as exc:                                   # NSFopen breaks with some pandas versions
        pytest.skip(f"NSFopen cannot read {name}.nid here: {exc}")
    # NSFopen gives m in file order; an upward scan stores the bottom line first
    up = b"Scan direction=Up" in Path(path).read_bytes()[:20000]
    ref = np.asarray(ref, float)[::-1] if up else np.asarray(ref, float)
    assert np.abs(im.data - ref * 1e9).max() < 1e-6


def test_unitless_gwy_refused_and_cli_exit_1(tmp_path, capsys):
    path = _real("afm/gwyddion/test.gwy")
    with pytest.raises(MarkcalError, match="--pixel-size-um"):
        read_image(path)
    out = str(tmp_path / "out")
    assert main(["indents", path, "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ") and "test.gwy" in err[0]
    assert not os.path.exists(os.path.join(out, "summary.json"))


def test_sem_pixel_from_fei_tag_not_dpi():
    im = read_image(_real("sem_vickers/Indent_20230912_7kV_spot4.5_FOV100um_multiBSE_A_05.tif"))
    assert im.meta["pixel_source"] == "fei"
    assert im.pixel_um == pytest.approx(0.0651042, rel=1e-6)            # 100 µm field / 1536 px
    assert im.shape == (1103, 1536) and im.kind == "om"


def test_unitless_gwy_with_pixel_size_given_still_refused_for_its_heights():
    """The real test.gwy has no unit string at all (xreal = yreal = 128; realdata README): a pixel size given on the
    command line answers the lateral unit, not the height unit, so the map is still refused, for that reason."""
    path = _real("afm/gwyddion/test.gwy")
    with pytest.raises(MarkcalError, match="channel 'Test' has no height unit"):
        read_image(path, pixel_size_um=0.5)


# ----------------------------------------------------------------------------- TIFF resolution tags

def test_tiff_dpi_tags_never_a_pixel_size(tmp_path):
    import tifffile
    img = (np.random.default_rng(0).random((32, 32)) * 4000).astype(np.uint16)
    for res, unit in [((56, 1), "INCH"), ((2540, 1), "INCH"), ((72 / 2.54, 1), "CENTIMETER")]:
        p = str(tmp_path / f"r{res[0]:.0f}{unit}.tif")
        tifffile.imwrite(p, img, resolution=res, resolutionunit=unit)
        with pytest.raises(MarkcalError, match="no pixel size: give --pixel-size-um"):
            read_image(p)
    p = str(tmp_path / "ij.tif")                                 # ImageJ unit + resolution: physical
    tifffile.imwrite(p, img, imagej=True, resolution=(1 / 0.125, 1 / 0.125), metadata={"unit": "um"})
    assert read_image(p).pixel_um == pytest.approx(0.125)


@pytest.mark.parametrize("ext", ["png", "jpg", "bmp"])
def test_picture_micrographs_read_as_grey_with_no_pixel_size(tmp_path, ext):
    """PNG, JPEG and BMP micrographs (Pillow): RGB to luminance, 8 bits; their dpi is never a pixel size."""
    from PIL import Image
    grey = np.tile(np.arange(0, 256, 4, dtype=np.uint8), (48, 1))           # 48 x 64 ramp
    rgb = np.stack([grey, grey, grey], axis=-1)
    p = str(tmp_path / f"om.{ext}")
    Image.fromarray(rgb).save(p, **({"dpi": (96, 96)} if ext != "jpg" else {"quality": 95}))
    with pytest.raises(MarkcalError, match="holds no microscope pixel size.*give --pixel-size-um"):
        read_image(p)
    im = read_image(p, pixel_size_um=0.2)
    assert im.kind == "om" and im.shape == (48, 64) and im.pixel_um == 0.2 and im.meta["bits"] == 8
    tol = 2.0 if ext == "jpg" else 1e-9                                      # JPEG is lossy
    assert np.max(np.abs(im.data - grey)) <= tol


def test_truncated_png_is_one_line_error(tmp_path, capsys):
    from PIL import Image
    p = tmp_path / "cut.png"
    Image.fromarray((np.random.default_rng(1).random((64, 64)) * 255).astype(np.uint8)).save(p)
    p.write_bytes(p.read_bytes()[:200])
    out = tmp_path / "out"
    assert main(["indents", str(p), "--pixel-size-um", "0.1", "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"markcal: error: {p}:"), err
    assert not (out / "summary.json").exists()


# ----------------------------------------------------------------------------- synthetic Bruker and NID

def _bruker_bytes(images, scan_nm, sens_nm_per_v, version="0x09300201"):
    """A NanoScope file: text header then, per image, (name, direction, bpp, heights_nm rows top first)."""
    offset = 8192
    lines = ["\\*File list", f"\\Version: {version}", "\\*Scanner list", f"\\@Sens. Zscan: V {sens_nm_per_v} nm/V",
             "\\@Sens. Amplitude: V 1.000000 "]
    blobs = []
    for name, direction, bpp, z_nm in images:
        rows, cols = z_nm.shape
        hard = 0.0125                                          # V per 16-bit LSB
        per_lsb = hard * 65536 / 2 ** (8 * bpp) * sens_nm_per_v
        raw = np.round(z_nm[::-1] / per_lsb).astype("<i2" if bpp == 2 else "<i4")
        sens = "Sens. Zscan" if name != "Amplitude" else "Sens. Amplitude"
        lines += ["\\*Ciao image list", f"\\Data offset: {offset}", f"\\Data length: {raw.nbytes}",
                  f"\\Bytes/pixel: {bpp}", f"\\Samps/line: {cols}", f"\\Number of lines: {rows}",
                  f"\\Scan size: {scan_nm} {scan_nm * rows / cols} nm", f"\\Line direction: {direction}",
                  f'\\@2:Image Data: S [{name}] "{name}"',
                  f"\\@2:Z scale: V [{sens}] ({hard} V/LSB) {hard * 65536} V"]
        blobs.append(raw.tobytes())
        offset += raw.nbytes
    head = ("\r\n".join(lines + ["\\*File list end"]) + "\r\n").encode("latin-1")
    return head.ljust(8192, b"\x1a") + b"".join(blobs)


def test_bruker_synthetic_units_channels_orientation(tmp_path):
    rng = np.random.default_rng(3)
    z = np.cumsum(rng.normal(0, 2.0, (48, 64)), axis=1)               # nm, row 0 = top
    z[:4] += 300.0                                                       # a feature at the top
    z4 = z * 5.0
    buf = _bruker_bytes([("Height", "Trace", 2, z), ("Height", "Retrace", 4, z4), ("Amplitude", "Trace", 2, z)],
                        scan_nm=6400.0, sens_nm_per_v=9.5)
    p = tmp_path / "scan.003"                                           # numbered name, found by content
    p.write_bytes(buf)
    im = read_image(str(p))
    per_lsb2 = 0.0125 * 9.5
    assert im.meta["channel"] == "Height trace" and im.pixel_um == pytest.approx(0.1)
    assert np.abs(im.data - z).max() <= per_lsb2 / 2 + 1e-9             # quantised to half an LSB
    assert im.data[:4].mean() > im.data[4:].mean() + 250                 # top row on top
    r4 = read_image(str(p), channel="height retrace")
    assert np.abs(r4.data - z4).max() <= per_lsb2 / 65536 / 2 + 1e-9     # 32-bit: finer LSB
    with pytest.raises(MarkcalError, match="not a height"):
        read_image(str(p), channel="Amplitude")
    trunc = tmp_path / "cut.spm"
    trunc.write_bytes(buf[:-100])
    with pytest.raises(MarkcalError, match="truncated"):
        read_image(str(trunc), channel="Amplitude")
    with pytest.raises(MarkcalError, match=r"cut\.spm: .*truncated"):
        read_image(str(trunc))


def _nid_bytes(chans, size_m, bits=32):
    """A Nanosurf NID: INI header, '#!', then each channel's signed integers (rows top first)."""
    head = ["[DataSet]", "Version=2", "GroupCount=1", "Gr0-Name=Scan forward", "Gr0-ID=0",
            f"Gr0-Count={len(chans)}"]
    head += [f"Gr0-Ch{i}=DataSet-0:{i}" for i in range(len(chans))]
    head += ["", "[DataSet\\DataSetInfos\\Scan]", "Scan direction=Down", ""]
    data = []
    for i, (name, unit, vals) in enumerate(chans):
        rows, cols = vals.shape
        lo, rng = float(vals.min()), float(np.ptp(vals))
        raw = np.round((vals - lo) / rng * (2.0 ** bits - 1) - 2.0 ** (bits - 1)).astype("<i4")
        head += [f"[DataSet-0:{i}]", f"Points={cols}", f"Lines={rows}", "Dim0Unit=m", f"Dim0Range={size_m}",
                 "Dim1Unit=m", f"Dim1Range={size_m * rows / cols}", f"Dim2Name={name}", f"Dim2Unit={unit}",
                 f"Dim2Range={rng}", f"Dim2Min={lo}", "SaveMode=Binary", f"SaveBits={bits}", "SaveSign=Signed", ""]
        data.append(raw.tobytes())
    return "\r\n".join(head).encode("utf-8") + b"#!" + b"".join(data)


def test_nid_synthetic_units_and_refusals(tmp_path):
    rng = np.random.default_rng(4)
    z_um = rng.normal(0.0, 0.2, (32, 40))
    amp_v = rng.random((32, 40))
    p = tmp_path / "m.nid"
    p.write_bytes(_nid_bytes([("Topography", "µm", z_um), ("Amplitude", "V", amp_v)], size_m=8e-6))
    im = read_image(str(p))
    assert im.meta["channel"] == "Topography trace" and im.pixel_um == pytest.approx(0.2)
    assert np.abs(im.data - z_um * 1e3).max() < 1e-5                    # µm -> nm, 32-bit quantisation
    with pytest.raises(MarkcalError, match="'V', not a height"):
        read_image(str(p), channel="amplitude")
    with pytest.raises(MarkcalError, match=r"no channel 'Phase' in the file \(channels: Topography trace, Amp"):
        read_image(str(p), channel="Phase")
    p.write_bytes(_nid_bytes([("Topography", "µm", z_um)], size_m=8e-6)[:-64])
    with pytest.raises(MarkcalError, match="truncated"):
        read_image(str(p))


# ----------------------------------------------------------------------------- cross-checks of two readers

def test_gwyfile_and_afmreader_agree_on_gwy(tmp_path):
    """markcal-independent: gwyfile and AFMReader read the same written .gwy alike; markcal gives nm."""
    from gwyfile.objects import GwyContainer, GwyDataField
    z_m = np.random.default_rng(5).normal(0, 5e-9, (64, 64))
    obj = GwyContainer()
    obj["/0/data/title"] = "Height"
    obj["/0/data"] = GwyDataField(z_m, xreal=3.2e-6, yreal=3.2e-6, si_unit_xy="m", si_unit_z="m")
    path = str(tmp_path / "h.gwy")
    obj.tofile(path)
    _quiet_afmreader()
    from AFMReader.gwy import load_gwy
    import gwyfile
    a, px_nm = load_gwy(path, "Height")
    b = gwyfile.util.get_datafields(gwyfile.load(path))["Height"].data
    assert np.allclose(np.asarray(a), np.asarray(b) * 1e9, rtol=1e-12) and px_nm == pytest.approx(50.0)
    im = read_image(path)
    assert np.allclose(im.data, z_m * 1e9, atol=1e-9) and im.pixel_um == pytest.approx(0.05)


def test_igor2_and_afmreader_agree_on_asylum_ibw(tmp_path):
    from igor2 import binarywave

    from markcal.fixtures.indent_maps import AfmOptions, asylum_ibw, render_afm
    r = render_afm(6, AfmOptions(rows=1, cols=1, size_px=64, field_um=4.0, nominal_um=1.0))
    path = str(tmp_path / "a.ibw")
    with open(path, "wb") as fh:
        fh.write(asylum_ibw(r))
    _quiet_afmreader()
    from AFMReader.ibw import load_ibw
    a, px_nm = load_ibw(path, "HeightRetrace")
    w = binarywave.load(path)["wave"]
    names = [n.decode() for n in w["labels"][2][1:]]
    b = np.asarray(w["wData"])[:, :, names.index("HeightRetrace")]
    # AFMReader: rotated so row 0 is the top, in nm
    assert np.allclose(np.asarray(a), b.T[::-1] * 1e9, rtol=1e-6) and px_nm == pytest.approx(4000 / 64, rel=1e-6)
    im = read_image(path)
    assert np.allclose(im.data, np.asarray(a), rtol=1e-6, atol=1e-6)
    zs = read_image(path, channel="zsensor")
    assert zs.meta["channel"] == "ZSensorRetrace"
    with pytest.raises(MarkcalError, match="no channel 'Deflection'.*Height retrace, Amplitude retrace"):
        read_image(path, channel="Deflection")


def test_non_square_pixels_resampled_to_square(tmp_path, capsys):
    """A scan of 64 points x 32 lines on a square field (y pixel twice the x pixel), as IBW (x and y deltas,
    sfA) and GSF (XReal/YReal). Read as square pixels, every length along y would be half its size (session
    14 refused such files). Now resampled to 64 x 64 pixels of 100 nm, linear between the lines: the pit on
    lines 10-19 (y 2.0-3.8 µm, line 0 at y = 0) has its full 50 nm on rows 20-38 and half on rows 19 and 39
    (half a line from its edge lines), nothing beyond. Pixels ten times longer one way are lines, not a map: refused
    with one line."""
    from markcal.fixtures.indent_maps import ibw_bytes
    from markcal.stages.image_io import gsf_bytes
    z = np.tile(np.arange(64) * 1e-10, (32, 1))                     # a slope of 0.1 nm per column
    z[10:20, 20:40] -= 5e-8
    cases = {"a.ibw": ibw_bytes({"HeightTrace": z}, (1e-7, 2e-7)),
             "a.gsf": gsf_bytes(z, 64e-7, 64e-7)}
    expect = np.full(64, 3.0)
    expect[20:39] -= 50.0
    expect[[19, 39]] -= 25.0
    for name, blob in cases.items():
        path = str(tmp_path / name)
        with open(path, "wb") as fh:
            fh.write(blob)
        img = read_image(path)
        assert img.pixel_um == pytest.approx(0.1) and img.data.shape == (64, 64)
        np.testing.assert_allclose(img.data[:, 30], expect, atol=1e-4)
        np.testing.assert_allclose(img.data[:, 10], 1.0, atol=1e-4)
        assert "64 x 32 samples of 100 x 200 nm resampled to 64 x 64 square pixels of 100 nm" in img.meta["resampled"]
    path = str(tmp_path / "lines.ibw")
    with open(path, "wb") as fh:
        fh.write(ibw_bytes({"HeightTrace": z}, (1e-7, 1e-6)))
    out = str(tmp_path / "out_lines")
    assert main(["indents", path, "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"markcal: error: {path}: pixels of 100 x 1000 nm are more than 8")
    assert not os.path.exists(os.path.join(out, "summary.json"))


def test_zeiss_smartsem_pixel_size_tag(tmp_path):
    """Zeiss SmartSEM writes its header as text in TIFF tag 34118 (CZ_SEM), parsed by tifffile; the pixel
    size is ``Image Pixel Size`` (newer) or ``Pixel Size`` (older), with its unit. Written here byte by
    byte as SmartSEM lays it out (unnamed numbers, then KEY / name = value unit pairs), beside a 96 dpi
    resolution tag that must not be taken."""
    import tifffile
    img = (np.arange(64 * 80) % 251).reshape(64, 80).astype(np.uint16)
    for pairs, want in [
        ([("AP_PIXEL_SIZE", "Pixel Size = 65.10 nm"), ("AP_IMAGE_PIXEL_SIZE", "Image Pixel Size = 65.10 nm")], 0.0651),
        ([("AP_PIXEL_SIZE", "Pixel Size = 1.250 µm")], 1.25),
        ([("AP_WD", "WD = 8.5 mm"), ("AP_PIXEL_SIZE", "Pixel Size = 812.5 pm")], 0.0008125),
    ]:
        text = "\r\n".join(["0", "0"] + [x for kv in pairs for x in kv] + ["END", ""]).encode("latin-1")
        path = str(tmp_path / f"z{want}.tif")
        tifffile.imwrite(path, img, resolution=(96, 96), resolutionunit="INCH",
                         extratags=[(34118, "B", len(text), text, True)])
        im = read_image(path)
        assert im.meta["pixel_source"] == "zeiss" and im.pixel_um == pytest.approx(want, rel=1e-9)


_REAL_AFM = ["bruker_legacy/old_bruker.002", "bruker_legacy/old_bruker.004", "bruker_nanoscope/full_multiple_images.txt",
             "jpk_wsxm/sample_0.jpk", "jpk_wsxm/sample_0.stp", "jpk_wsxm/sample_0.top", "nanosurf_nid/circles.nid",
             "nanosurf_nid/grid1.nid", "nanosurf_nid/sapphire.nid"]


@pytest.mark.parametrize("rel", _REAL_AFM)
def test_real_maps_keep_every_line_and_hold_no_imprint(rel, tmp_path, capsys):
    """The real AFM maps (none shows an indentation imprint, realdata README): every scan line is kept (a
    real line has noise; only exactly constant lines, an interrupted scan's, are left out), and the indents
    flow finds no imprint: one line, exit 1, no summary.json. Session 11 reported 5 "imprints" on
    circles.nid (depth / diameter under 0.003), 1 on grid1.nid (0.014) and 1 on the NanoScope file (0.023);
    with the measuring of session 12 and no 0.02 floor on H/D, circles.nid gives 14 (H/D <= 0.0022)."""
    path = _real(f"afm/{rel}")
    im = read_image(path)
    assert "blank_rows" not in im.meta and np.isfinite(im.data).all()
    out = str(tmp_path / "out")
    assert main(["indents", path, "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("markcal: error: ") and err[0].endswith("no imprint found")
    assert not os.path.exists(os.path.join(out, "summary.json"))


def test_real_grating_pits_through_the_crack_check(tmp_path, capsys, monkeypatch):
    """The real grating grid1.nid (square pits, no imprint: realdata README) takes the session 17 crack
    check (valley traced, tongues tested) on its pits' corners, and still holds no imprint: one line, exit 1."""
    from markcal.stages import indent_single
    calls = []
    check = indent_single.unless_crack
    monkeypatch.setattr(indent_single, "unless_crack", lambda *a: calls.append(1) or check(*a))
    path = _real("afm/nanosurf_nid/grid1.nid")
    assert main(["indents", path, "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert calls                                   # the check ran on real pits
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith("no imprint found")


def test_resampled_map_must_fit_too(tmp_path, monkeypatch):
    """The size limit holds for the map resampled to square pixels as for the file's own: 64 points x 32 lines
    (2048 values) on a square field becomes 64 x 64; with a limit of 3000 values the file is refused."""
    from markcal.stages import image_io
    from markcal.stages.image_io import gsf_bytes
    monkeypatch.setattr(image_io, "MAX_IMAGE_PIXELS", 3000)
    path = str(tmp_path / "a.gsf")
    with open(path, "wb") as fh:
        fh.write(gsf_bytes(np.tile(np.arange(64) * 1e-10, (32, 1)), 64e-7, 64e-7))
    with pytest.raises(MarkcalError, match=r"64 x 64 = 4,096 values"):
        read_image(path)


def test_real_bruker_map_line_flatten_and_clipping_against_references():
    """The real NanoScope file as stored is no line-flattened map: its raw counts (jmarini/nanoscope's
    ``reference_raw.csv``) have lines whose means differ, so neither the reference's values nor markcal's
    read of them carry the signature. That library's own export flattened by line (``reference_converted.csv``,
    each line's least-squares line, in whole counts, taken off; heights to 3 digits) does: it is recognised as
    each row's line taken off. (The rounding to counts and digits scatters the lines' slopes by 0.003 nm, over
    2 % of this smooth map's 0.09 nm noise; the agreement allows for the rounding it finds.) Its lowest count
    occurs once in the reference: no clipped floor."""
    from markcal.stages.indent_select import clipped_floor
    from markcal.stages.indent_unflatten import LineFlatten, detect_line_flatten
    path = _real("afm/bruker_nanoscope/full_multiple_images.txt")
    raw_ref = np.loadtxt(REAL / "afm/bruker_nanoscope/reference_raw.csv", delimiter=",")
    conv_ref = np.loadtxt(REAL / "afm/bruker_nanoscope/reference_converted.csv", delimiter=",")
    im = read_image(path)
    assert np.ptp(raw_ref.mean(axis=1)) > 100                      # counts: the lines' means differ widely
    assert detect_line_flatten(raw_ref) is None and detect_line_flatten(im.data) is None
    assert detect_line_flatten(conv_ref) == LineFlatten(axis=0, order=1, how="poly")
    assert np.sum(raw_ref == raw_ref.min()) < 8 and clipped_floor(im.data) is None
    assert "resampled" not in im.meta


@pytest.mark.parametrize("rel,pixel_nm", [("afm/jpk_wsxm/sample_0.jpk", 1.27702), ("afm/jpk_wsxm/sample_0.stp", 0.9765625),
                                          ("afm/jpk_wsxm/sample_0.top", 0.9765625),
                                          ("afm/bruker_nanoscope/full_multiple_images.txt", 2000 / 512)])
def test_real_maps_square_pixels_kept(rel, pixel_nm):
    """Real maps of square pixels (the references' pixel sizes, from AFMReader and the NanoScope header) are
    read as they are: not resampled, the reference pixel size."""
    im = read_image(_real(rel))
    assert "resampled" not in im.meta and im.pixel_um * 1e3 == pytest.approx(pixel_nm, rel=1e-5)


@pytest.mark.parametrize("rel", ["afm/bruker_legacy/old_bruker.002", "afm/bruker_nanoscope/full_multiple_images.txt",
                                 "afm/jpk_wsxm/sample_0.jpk", "afm/jpk_wsxm/sample_0.stp", "afm/nanosurf_nid/circles.nid",
                                 "afm/nanosurf_nid/sapphire.nid"])
def test_real_maps_written_to_few_digits_are_not_taken_for_flattened(rel):
    """The line-flatten test allows for the rounding of a text export (session 16): the real maps, as read and
    written to 3, 4 or 5 significant digits, are still no line-flattened maps (their lines' fits differ by far
    more than that rounding)."""
    from markcal.stages.indent_unflatten import Rounding, detect_line_flatten
    z = read_image(_real(rel)).data
    z = z - np.nanmedian(z)
    for digits in (3, 4, 5):
        scale = 10.0 ** (np.floor(np.log10(np.maximum(np.abs(z), 1e-300))) - digits + 1)
        written = np.round(z / scale) * scale
        assert Rounding.of(written).digits == digits
        assert detect_line_flatten(written) is None


def test_real_nanoscope_map_through_a_gwyddion_text_export(tmp_path):
    """The real NanoScope map written as Gwyddion's ASCII data matrix (heights in m, 7 digits, the header's
    field size) and read back: its reference counts x the header's nm per count, within the export's rounding,
    and the header's pixel size (2 µm over 512 samples)."""
    from markcal.stages.text_maps import text_matrix
    im = read_image(_real("afm/bruker_nanoscope/full_multiple_images.txt"))
    raw_ref = np.loadtxt(REAL / "afm/bruker_nanoscope/reference_raw.csv", delimiter=",")
    p = tmp_path / "nanoscope.txt"
    rows, cols = im.shape
    p.write_text(text_matrix(im.data * 1e-9, cols * im.pixel_um * 1e-6, rows * im.pixel_um * 1e-6, digits=7),
                 encoding="utf-8")
    txt = read_image(str(p))
    nm_per_lsb = 0.006693481 * 12.95302                                    # header: V/LSB x Sens. Zscan nm/V
    assert txt.pixel_um == pytest.approx(2.0 / 512, rel=1e-6) and txt.meta["format"] == "text"
    assert np.abs(txt.data[::-1] / nm_per_lsb - raw_ref).max() < 0.01     # file order: first line = bottom


@pytest.mark.parametrize("unit, nm_per_unit", [("m", 1e9), ("um", 1e3), ("nm", 1.0)])
def test_ibw_heights_from_the_waves_data_units(tmp_path, unit, nm_per_unit):
    """The wave's data units decide the heights' scale (before: m or nm guessed from the range, so a map in µm
    was read 1000 times too deep)."""
    from markcal.fixtures.indent_maps import ibw_bytes
    z = np.random.default_rng(3).normal(0, 2.0, (16, 16))
    path = tmp_path / "u.ibw"
    path.write_bytes(ibw_bytes({"HeightTrace": z}, 1e-7, data_unit=unit))
    img = read_image(str(path))
    assert np.allclose(img.data, z * nm_per_unit, rtol=1e-6, atol=1e-6 * nm_per_unit)
    assert img.meta["z_unit_in_file"] == unit


def test_ibw_without_data_units(tmp_path):
    """Empty data units: an Asylum image (labelled layers) is in metres by Asylum's convention and says so; a bare
    2-D wave gives no height unit and is refused in one line; a unit that is no length is refused."""
    from markcal.fixtures.indent_maps import ibw_bytes
    z = np.random.default_rng(4).normal(0, 1e-9, (16, 16))
    path = tmp_path / "asylum.ibw"
    path.write_bytes(ibw_bytes({"HeightTrace": z, "AmplitudeTrace": z}, 1e-7, data_unit=""))
    img = read_image(str(path))
    assert np.allclose(img.data, z * 1e9, atol=1e-6) and "Asylum" in img.meta["z_unit_in_file"]
    bare = tmp_path / "bare.ibw"
    bare.write_bytes(_two_d_ibw(z, ""))
    with pytest.raises(MarkcalError, match="no data units"):
        read_image(str(bare))
    volts = tmp_path / "volts.ibw"
    volts.write_bytes(_two_d_ibw(z, "V"))
    with pytest.raises(MarkcalError, match="'V', not a height unit"):
        read_image(str(volts))


def _two_d_ibw(z, unit):
    """A plain 2-D Igor wave (no layer labels, no note) with data units ``unit``: the fixture's one-layer 3-D wave
    with its third dimension set to 0 and its labels cut off (TN003: BinHeader5 dimLabelsSize[2] at byte 44,
    WaveHeader5 nDim[2] at 64 + 76), the checksum made again."""
    import struct
    from markcal.fixtures.indent_maps import ibw_bytes
    raw = bytearray(ibw_bytes({"H": z}, 1e-7, data_unit=unit))
    labels = struct.unpack_from("<i", raw, 44)[0]
    struct.pack_into("<i", raw, 44, 0)
    struct.pack_into("<i", raw, 64 + 76, 0)
    del raw[len(raw) - labels:]
    struct.pack_into("<h", raw, 2, 0)
    total = int(np.frombuffer(bytes(raw[:384]), "<i2").astype(np.int64).sum())
    struct.pack_into("<h", raw, 2, ((-total + 32768) % 65536) - 32768)
    return bytes(raw)


def test_real_grating_pits_are_flat_bottomed_by_both_shares(monkeypatch):
    """The real grating grid1.nid (square pits, no imprint): the flat-bottom gate asks two things since session 25,
    over 8.5 % of a pit deeper than 80 % of its depth and over 40 % deeper than half (a mean of trace and retrace
    flattens a pyramid's floor past the first alone: 8.5-10 %, while its half-depth share stays 0.25-0.38). Every
    pit of the grating over the first is over the second too (measured 0.43-0.74), so the gate itself, not only the
    H/D and pyramid tests behind it, still refuses them; and none is taken for an imprint."""
    from markcal.pipeline.flows import indents as flow
    from markcal.stages import indent_select as sel
    seen = []
    accept = sel.accept_imprints
    monkeypatch.setattr(flow.sel, "accept_imprints", lambda imps, *a, **k: seen.extend(imps) or accept(imps, *a, **k))
    with pytest.raises(MarkcalError, match="no imprint found"):
        flow.measure_file(_real("afm/nanosurf_nid/grid1.nid"), None, flow.IndentsOptions())
    deep = [m for m in seen if m is not None and m.floor_share > sel.MAX_FLOOR_SHARE]
    assert len(deep) >= 10, len(deep)
    assert all(m.half_share > sel.MAX_PYRAMID_HALF_SHARE for m in deep), sorted(m.half_share for m in deep)
    assert all(sel._flat_bottomed(m) for m in deep)
