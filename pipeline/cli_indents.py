"""Sub-commands of the indents flow: ``markcal indents`` and ``markcal render afm|om``."""
from __future__ import annotations

import os
import sys

from markcal.pipeline.cli_common import add_alias, add_run_options
from markcal.pipeline.progress import progress


def cmd_indents(args) -> int:
    from markcal.pipeline.flows.indents import indents_options, read_indents_spec, run_indents, with_spec_load
    from markcal.pipeline.cli_common import run_options
    from markcal.pipeline.registry import exit_status, get_flow, judge
    from markcal.reports.files import check_out_dir

    check_out_dir(args.out)                           # once, before any work
    say = progress(args.quiet)
    spec, load = read_indents_spec(args.array) if args.array else (None, None)
    flow = get_flow("indents")
    options = {**flow.descriptor.options, **{k: getattr(args, k) for k in flow.descriptor.options
                                             if getattr(args, k, None) is not None}}
    options = with_spec_load(options, load)           # a spec with only [indenter] load_mN: single imprints
    res = run_indents(args.images, spec, indents_options(options), progress=say)      # several files pooled
    judge("indents", res.summary, list(args.images), args.array, **run_options(args))
    say("writing tables and report")
    paths = flow.write(res, args.out, report=not args.no_report)
    s = res.summary
    judged = ("no array spec: nothing judged" if s['n_out_of_tolerance'] is None else
              f"{s['n_out_of_tolerance']} out of tolerance"
              + ("" if s['n_low_hd'] is None else f", {s['n_low_hd']} with H/D < {s['min_hd']}"))
    say(f"{s['n_imprints']} imprints in {s['n_files_ok']} file(s); mean diameter {s['mean_diameter_um']:.3f} µm; "
        f"{judged}")
    for src, msg in res.failed:
        print(f"markcal: error: {src}: {msg}", file=sys.stderr)
    print(os.path.abspath(paths.get("report.html", paths["summary.json"])))
    return exit_status(res.summary)


def cmd_render_afm(args) -> int:
    from markcal.fixtures.indent_maps import AfmOptions, render_afm, save_indent_render

    say = progress(args.quiet)
    if args.single:
        return _render_single(args, say)
    o = AfmOptions(rows=args.rows, cols=args.cols, pitch_um=args.pitch_um, nominal_um=args.nominal_um,
                   size_px=args.size_px, field_um=args.field_um, facet_bulge=args.facet_bulge)
    say(f"rendering AFM map, seed {args.seed}")
    save_indent_render(args.out, render_afm(args.seed, o), "heights",
                       formats={f.strip() for f in args.formats.split(",") if f.strip()})
    print(os.path.abspath(args.out))
    return 0


def _render_single(args, say) -> int:
    """One real-like imprint: heights.ibw (Height, Deflection, ZSensor in m), heights.tif / .gsf / .txt,
    truth.json."""
    from markcal.fixtures.indent_maps import tiff_bytes
    from markcal.fixtures.indent_single import SingleOptions, render_single, single_ibw
    from markcal.reports.files import atomic_write_bytes, atomic_write_text, write_json
    from markcal.stages.image_io import gsf_bytes
    from markcal.stages.text_maps import text_matrix
    o = SingleOptions(size_px=args.size_px, fill=args.fill, corner_margin_px=args.corner_margin_px,
                      cracks=args.cracks, crack_depth_nm=args.crack_depth_nm)
    say(f"rendering a single-imprint AFM map, seed {args.seed}")
    r = render_single(args.seed, o)
    os.makedirs(args.out, exist_ok=True)
    fmts = {f.strip() for f in args.formats.split(",") if f.strip()} | {"ibw"}
    atomic_write_bytes(os.path.join(args.out, "heights.ibw"), single_ibw(r))
    if "tif" in fmts:
        atomic_write_bytes(os.path.join(args.out, "heights.tif"), tiff_bytes(r.data, r.pixel_um, zunit="nm"))
    if "gsf" in fmts:
        ext_m = r.pixel_um * 1e-6 * r.data.shape[1]
        atomic_write_bytes(os.path.join(args.out, "heights.gsf"),
                           gsf_bytes(r.data.astype("float64") * 1e-9, ext_m, ext_m * r.data.shape[0] / r.data.shape[1],
                                     "m", "Height"))
    if "txt" in fmts:
        atomic_write_text(os.path.join(args.out, "heights.txt"),
                          text_matrix(r.data * 1e-9, r.pixel_um * 1e-6 * r.data.shape[1], r.pixel_um * 1e-6 * r.data.shape[0]))
    write_json(os.path.join(args.out, "truth.json"), r.truth)
    print(os.path.abspath(args.out))
    return 0


def cmd_render_om(args) -> int:
    from markcal.fixtures.indent_maps import OmOptions, render_om, save_indent_render

    say = progress(args.quiet)
    if args.single:
        return _render_micrograph(args, say)
    o = OmOptions(rows=args.rows, cols=args.cols, pitch_um=args.pitch_um, nominal_um=args.nominal_um,
                  size_px=args.size_px, pixel_um=args.pixel_size_um, bits=args.bits)
    say(f"rendering OM micrograph, seed {args.seed}")
    save_indent_render(args.out, render_om(args.seed, o), "image")
    print(os.path.abspath(args.out))
    return 0


def _render_micrograph(args, say) -> int:
    """Single imprints in an OM or SEM micrograph: image.tif (16-bit, pixel size in the tags), truth.json."""
    from markcal.fixtures.indent_maps import tiff_bytes
    from markcal.fixtures.indent_micrograph import MicrographOptions, render_micrograph
    from markcal.reports.files import atomic_write_bytes, write_json
    o = MicrographOptions(style=args.style, pixel_um=args.pixel_size_um, n_imprints=args.n_imprints,
                          bar_rows=40 if args.style == "sem" else 0)
    say(f"rendering a {args.style.upper()} micrograph of {args.n_imprints} single imprint(s), seed {args.seed}")
    r = render_micrograph(args.seed, o)
    os.makedirs(args.out, exist_ok=True)
    atomic_write_bytes(os.path.join(args.out, "image.tif"), tiff_bytes(r.data, r.pixel_um))
    write_json(os.path.join(args.out, "truth.json"), r.truth)
    print(os.path.abspath(args.out))
    return 0


def _count(v):
    import argparse
    n = int(v)
    if not 1 <= n <= 4:
        raise argparse.ArgumentTypeError(f"must be 1 to 4, got {v}")
    return n


def _positive(v):
    import argparse
    x = float(v)
    if not x > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {v}")
    return x


def register(sub, render_sub) -> None:
    """Add ``indents`` to the top-level commands and ``afm``, ``om`` to ``render``."""
    p = sub.add_parser("indents", help="AFM maps / OM images of indentation arrays -> sizes, depths, positions, report")
    p.add_argument("images", nargs="+", help="images: .tif/.tiff (OM, SEM or AFM), .png/.jpg/.bmp micrographs "
                                               "(with --pixel-size-um), AFM maps .gsf, .gwy, .ibw, Bruker "
                                               "NanoScope (.spm, .000-.999; by content), Nanosurf .nid, JPK .jpk, "
                                               "WSxM .stp/.top, Gwyddion ASCII data matrix with its header "
                                               "(.txt; by content)")
    p.add_argument("--array", help="array spec (ARRAY.toml): [array] rows, cols, pitch_um, nominal_diameter_um; "
                                    "[indenter] load_mN (a file with only [indenter]: single imprints)")
    p.add_argument("--kind", choices=["afm", "om"], help="override the kind guessed from the file")
    p.add_argument("--pixel-size-um", type=_positive, help="pixel size (µm); overrides the file's")
    p.add_argument("--channel", help="AFM channel to measure (default: the height/topography channel, trace)")
    p.add_argument("--load-mN", type=_positive, help="indentation load (mN): Vickers hardness HV = 0.1891 F / d^2")
    p.add_argument("--objective-na", type=_positive,
                   help="OM arrays: the objective's numerical aperture; the blur is held at its Airy pattern "
                        "(550 nm light) instead of fitted")
    p.add_argument("--optics-from", metavar="IMAGE",
                   help="OM arrays of small imprints: a micrograph of larger imprints (2-3 µm and up) of the same "
                        "material and indenter under the same objective; its halo and edge-line darkness are held "
                        "here (near the resolution limit the image alone cannot tell them from the size)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_run_options(p)
    p.set_defaults(func=cmd_indents)

    for what, fn, hlp in (("afm", cmd_render_afm, "AFM height map of a Vickers indentation array"),
                          ("om", cmd_render_om, "OM micrograph of a Vickers indentation array")):
        r = render_sub.add_parser(what, help=hlp)
        r.add_argument("--seed", type=int, default=0)
        r.add_argument("--out", required=True)
        r.add_argument("--rows", type=int, default=5)
        r.add_argument("--cols", type=int, default=5)
        r.add_argument("--pitch-um", type=_positive, default=8.0)
        r.add_argument("--nominal-um", type=_positive, default=None,
                       help="nominal diameter (default: 1, 2 or 3 µm drawn from the seed)")
        r.add_argument("--size-px", type=int, default=512)
        if what == "afm":
            r.add_argument("--field-um", type=_positive, default=50.0)
            r.add_argument("--formats", default="tif,gsf", help="comma list of tif, gsf, ibw, txt (Gwyddion's ASCII data matrix)")
            r.add_argument("--facet-bulge", type=float, default=0.0,
                           help="convex facets (fraction of the depth), 0: planar")
            r.add_argument("--single", action="store_true",
                           help="one real-like imprint (bowed edges, pile-up lobes) as multi-channel IBW + truth")
            r.add_argument("--fill", type=float, default=None, help="--single: mean diagonal / field (0.4-0.9)")
            r.add_argument("--corner-margin-px", type=float, default=None,
                           help="--single: put the corner nearest a border this far from it (px)")
            r.add_argument("--cracks", type=int, choices=range(0, 5), default=0, metavar="{0..4}",
                           help="--single: corners with a radial crack (brittle materials such as glass)")
            r.add_argument("--crack-depth-nm", type=_positive, default=100.0,
                           help="--single: crack groove depth at the corner as the tip sees it (nm)")
        else:
            r.add_argument("--pixel-size-um", type=_positive, default=0.1, help="pixel size of the micrograph, µm")
            add_alias(r, "--pixel-um", "--pixel-size-um", type=_positive)
            r.add_argument("--bits", type=int, choices=[8, 16], default=8)
            r.add_argument("--single", action="store_true",
                           help="single Vickers imprints (facet shading, edge lines, halo; SEM: glow, info bar) "
                                "in a 360 x 480 micrograph + truth")
            r.add_argument("--style", choices=["om", "sem"], default="om", help="--single: light or electron")
            r.add_argument("--n-imprints", type=_count, default=1, help="--single: imprints in the field (1-4)")
        r.add_argument("--quiet", action="store_true")
        r.set_defaults(func=fn)
