"""Writing an exported controller table and its note (``markcal export``).

The byte-level codecs live in :mod:`markcal.stages.table_formats`; here the
table is written atomically beside a small HTML note that says how it is laid
out (layout, lens field, sign, range of entries, structure) with a picture of
the correction as the file carries it, so that a person can compare it with
the vendor tool's display before loading it into a machine.
"""
from __future__ import annotations

from markcal.reports.files import atomic_write_bytes, atomic_write_text
from markcal.reports.table_report import table_report_html

__all__ = ["export_note_rows", "note_path", "write_export"]


def note_path(table_path: str) -> str:
    """Where the note of a table written to ``table_path`` goes: ``<table_path>.html``."""
    return str(table_path) + ".html"


#: human labels of the facts ``export_table`` reports (a key not listed keeps its name, without underscores)
FACT_LABELS = {"units_per_mm": "scale (galvo units per mm)",
               "extrapolated_nodes": "nodes outside the measured plate (value at its nearest edge)",
               "max_entry_units": "largest entry (galvo units)",
               "interpolation_error_units": "interpolation error at the fiducials (galvo units)",
               "bits_per_mm": "scale (bits per mm)", "grid": "grid points",
               "filled_points": "undetected marks filled from the model",
               "unmarked_sites": "unmarked sites (orientation mark) filled from the model",
               "nodes": "nodes", "step_mm": "node step (mm)", "max_correction_um": "largest correction (µm)"}


def _fmt(v) -> str:
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def export_note_rows(t, facts: dict) -> list:
    """``[label, value]`` rows of the export note: what was written and how it is laid out.

    Parameters
    ----------
    t : Inspected
        The written bytes read back (:func:`markcal.pipeline.flows.export.inspect_bytes`).
    facts : dict
        What the export reported (scale, extrapolated nodes, interpolation error).
    """
    rows = [["layout", t.layout]]
    lens = t.facts.get("lens field (mm)")
    if lens is not None:
        rows.append(["lens field", f"{lens:.6g} mm"])
    if "sign" in t.facts:
        rows.append(["sign", {"subtract": "the controller drives nominal − entry (entry = −command offset)",
                              "add": "the controller drives nominal + entry (entry = command offset)"}.get(
                                  t.facts["sign"], f"table = −({_fmt(t.facts['sign'])}) × measured error")])
    elif t.format == "ctb":
        rows.append(["sign", f"entries are {'corrected positions' if t.facts['content'] == 'absolute' else 'offsets'}"
                             " = nominal + command offset (offset binary, 32768 at the centre)"])
    else:
        rows.append(["sign", "measured landing positions of the points commanded at the nominal grid"])
    rows += [[f"range: {k}", _fmt(v)] for k, v in t.facts.items()
             if any(w in k for w in ("values", "table (", "deviation", "corrections"))]
    rows += [[FACT_LABELS.get(k, k.replace("_", " ")), _fmt(v)] for k, v in facts.items()]
    return rows


def write_export(out: str, data: bytes, t, facts: dict, report: bool = True, provenance: dict | None = None) -> str | None:
    """Write the table and, unless ``report`` is false, its note (headed by ``provenance``); return the note's path."""
    atomic_write_bytes(out, data)
    if not report:
        return None
    path = note_path(out)
    atomic_write_text(path, table_report_html(t, title=f"markcal export — {t.format} table",
                                                     note_rows=export_note_rows(t, facts),
                                                     provenance=provenance))
    return path
