"""``markcal export`` and ``markcal inspect``."""
from __future__ import annotations

import os
import sys

from markcal.pipeline.cli_common import add_context_options
from markcal.pipeline.progress import progress


def _cor_ctb_options(args):
    from markcal.stages.table_formats import CorOptions, CtbOptions
    given = args.node_spacing is not None              # 0 or nan is refused, not taken for "the default"
    cor = CorOptions(node_spacing_units=args.node_spacing if given else 1024.0, outer=args.outer, sign=args.cor_sign)
    ctb = CtbOptions(node_spacing_bits=args.node_spacing if given else 65535.0 / 64.0, content=args.ctb_content,
                     outer=args.outer)
    return cor, ctb


def _warn(t) -> None:
    """Structural warnings go to stderr even with --quiet: they are about the file a machine will load."""
    for w in t.warnings:
        print(f"markcal: warning: {t.path}: {w}", file=sys.stderr, flush=True)


def cmd_export(args) -> int:
    from markcal.pipeline.cli_common import context_of
    from markcal.pipeline.flows.export import export_table, inspect_bytes
    from markcal.pipeline.registry import provenance
    from markcal.reports.export import FACT_LABELS, write_export
    from markcal.reports.files import check_out_file
    from markcal.stages.errors import MarkcalError
    from markcal.stages.table_formats import FORMATS

    if args.list:
        for name, (ext, desc) in FORMATS.items():
            print(f"{name:10s} {ext:5s} {desc}")
        return 0
    if not args.format or not args.source or not args.out:
        raise MarkcalError("usage: markcal export FORMAT RESULT_DIR --out FILE (markcal export --list names the formats)")
    say = progress(args.quiet)
    check_out_file(args.out, [args.source])
    say(f"writing a {args.format} table from {args.source}")
    cor, ctb = _cor_ctb_options(args)
    data, facts = export_table(args.format, args.source, lens_mm=args.lens_mm, cor=cor, ctb=ctb, rtc4=args.rtc4,
                               fill_missing=args.fill_missing, ax1=args.ax1, ax2=args.ax2, sign=args.sign,
                               allow_extrapolation=args.allow_extrapolation)
    t = inspect_bytes(data, args.out, lens_mm=args.lens_mm, cor=cor, ctb=ctb, sign=args.sign)
    note = write_export(args.out, data, t, facts, report=not args.no_report,
                        provenance=provenance(args.source, context=context_of(args)))
    _warn(t)
    say(t.layout)
    say(", ".join(f"{FACT_LABELS.get(k, k)} {v:.4g}" if isinstance(v, float) else f"{FACT_LABELS.get(k, k)} {v}"
                  for k, v in facts.items()))
    if facts.get("extrapolated_nodes"):
        say(f"note: {facts['extrapolated_nodes']} nodes lie outside the measured plate and carry the value at "
            "its nearest edge")
    print(os.path.abspath(args.out))
    if note:
        print(os.path.abspath(note))
    return 0


def cmd_inspect(args) -> int:
    from markcal.pipeline.cli_common import context_of
    from markcal.pipeline.flows.export import inspect_table
    from markcal.pipeline.registry import provenance
    from markcal.reports.files import atomic_write_text, write_csv, write_json
    from markcal.reports.table_report import table_report_html

    cor, ctb = _cor_ctb_options(args)
    progress(args.quiet)(f"reading {args.table}")
    t = inspect_table(args.table, lens_mm=args.lens_mm, cor=cor, ctb=ctb, sign=args.sign)
    _warn(t)
    out = args.out or os.path.splitext(os.path.basename(args.table))[0] + "_inspect"
    os.makedirs(out, exist_ok=True)
    import numpy as np
    gx, gy = np.meshgrid(t.x_mm, t.y_mm)
    unit = "um" if t.unit == "µm" else t.unit
    write_csv(os.path.join(out, "table.csv"), {"x_mm": gx.ravel(), "y_mm": gy.ravel(),
                                                f"u_{unit}": t.u.ravel(), f"v_{unit}": t.v.ravel()})
    prov = provenance(args.table, context=context_of(args))
    mag = np.hypot(t.u, t.v)
    write_json(os.path.join(out, "summary.json"),
               {"kind": "inspect", "format": t.format, "layout": t.layout, "unit": t.unit,
                "nodes_x": len(t.x_mm), "nodes_y": len(t.y_mm), "max_magnitude": float(mag.max()),
                "rms_magnitude": float(np.sqrt(np.mean(mag ** 2))), "warnings": list(t.warnings), **prov})
    atomic_write_text(os.path.join(out, "report.html"), table_report_html(t, provenance=prov))
    print(os.path.abspath(os.path.join(out, "report.html")))
    return 0


def _table_options(p):
    p.add_argument("--lens-mm", type=float, help="lens field size (mm): galvo scale = 65536 / lens-mm units per mm")
    p.add_argument("--node-spacing", type=float, default=None,
                   help="controller units between table nodes (cor default 1024, ctb default 65535/64)")
    p.add_argument("--outer", choices=["y", "x"], default="y",
                   help="cor, ctb: axis of the outer index of the 65 x 65 entries; y (default): the inner index runs "
                        "along x, as in EZCAD's and SCANLAB's own files; x: transposed")
    p.add_argument("--cor-sign", choices=["subtract", "add"], default="subtract",
                   help="cor: the controller drives nominal - entry (subtract, default) or nominal + entry")
    p.add_argument("--ctb-content", choices=["absolute", "offset"], default="absolute",
                   help="ctb: entries are corrected positions (default) or offsets, offset binary")
    p.add_argument("--sign", type=float, default=1.0, help="a3200: the table holds -sign x measured error")


def register(sub, render_sub) -> None:
    """Add ``export`` and ``inspect``."""
    ex = sub.add_parser("export", help="write a flow's correction as a controller table (cor, ctb, correXion, A3200)")
    ex.add_argument("format", nargs="?", help="cor, ctb, correxion or a3200 (see --list)")
    ex.add_argument("source", nargs="?", help="a scan flow output folder (cor, ctb, correxion) or selfcal output (a3200)")
    ex.add_argument("--out", help="table file to write")
    ex.add_argument("--list", action="store_true", help="name the formats and exit")
    _table_options(ex)
    ex.add_argument("--rtc4", action="store_true", help="correxion: for an RTC4 (16-bit) instead of an RTC5 (20-bit)")
    ex.add_argument("--fill-missing", action="store_true",
                    help="correxion: fill undetected fiducials from the correction model instead of refusing")
    ex.add_argument("--ax1", type=int, default=1, help="a3200: axis number of x")
    ex.add_argument("--ax2", type=int, default=2, help="a3200: axis number of y")
    ex.add_argument("--allow-extrapolation", action="store_true",
                    help="write even when most of the table lies outside the measured plate")
    ex.add_argument("--no-report", action="store_true", help="do not write the note <out>.html beside the table")
    ex.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_context_options(ex)
    ex.set_defaults(func=cmd_export)

    ins = sub.add_parser("inspect", help="read a controller table back and draw its field (report.html, table.csv)")
    ins.add_argument("table", help=".cor, .ctb, correXion input or A3200 file")
    ins.add_argument("--out", help="output folder (default: <name>_inspect)")
    ins.add_argument("--quiet", action="store_true", help="no progress lines (structural warnings still go to stderr)")
    _table_options(ins)
    add_context_options(ins)
    ins.set_defaults(func=cmd_inspect)
