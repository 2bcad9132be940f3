"""DXF marking jobs read and written with ezdxf.

Reads the modelspace: LINE, LWPOLYLINE and 2D POLYLINE (bulges as arcs), CIRCLE,
ARC, ELLIPSE and SPLINE flattened to a chordal tolerance, POINT, and INSERT
(block references expanded with their transforms, nested ones too). The layer
is the stroke's group (an entity on layer 0 inside a block takes the INSERT's
layer). Units from ``$INSUNITS``. Anything else (TEXT, HATCH, DIMENSION ...) is
listed as unsupported and left in the drawing.

Writing reads the source drawing again, deletes the modelspace entities that
became strokes and appends the strokes in marking order (LINE and POINT as
they were, the rest as LWPOLYLINE with the flattened vertices), each with its
source entity's layer, colour, linetype and lineweight; blocks, layers, header
and unsupported entities stay as they were.
"""
from __future__ import annotations

import io
import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .job_formats import JobFile, build_job, flatten_arc, marked_strokes, paths_to_strokes

__all__ = ["read_dxf", "write_dxf", "INSUNITS_MM", "DxfPayload"]

#: $INSUNITS code -> mm per drawing unit (0 = unitless, read as mm)
INSUNITS_MM = {0: 1.0, 1: 25.4, 2: 304.8, 4: 1.0, 5: 10.0, 6: 1000.0, 8: 25.4e-6, 9: 0.0254, 10: 914.4,
               13: 1e-3, 14: 100.0}
_GEOMETRY = {"LINE", "LWPOLYLINE", "POLYLINE", "CIRCLE", "ARC", "ELLIPSE", "SPLINE", "POINT"}
_ATTRIBS = ("color", "linetype", "lineweight", "true_color", "ltscale")


@dataclass(frozen=True, eq=False)
class DxfPayload:
    data: bytes                # the source file
    handles: tuple             # modelspace entities that became strokes (deleted when writing)
    types: tuple               # per stroke: source entity type
    attribs: tuple             # per stroke: dxfattribs for the written entity (layer, colour ...)
    mm_per_unit: float


def _load(data: bytes, source):
    import ezdxf
    from ezdxf import recover
    try:
        doc, auditor = recover.read(io.BytesIO(data))
    except (ezdxf.DXFStructureError, ezdxf.DXFError) as exc:
        raise MarkcalError(f"not a readable DXF file ({str(exc).splitlines()[0][:80]})", source) from None
    except (UnicodeDecodeError, ValueError, IndexError, EOFError) as exc:
        raise MarkcalError(f"not a readable DXF file ({type(exc).__name__})", source) from None
    return doc


def _bulge_path(points, closed, tol):
    """Vertices of an LWPOLYLINE given as (x, y, bulge) rows in its own (OCS) plane."""
    from ezdxf.math import bulge_to_arc
    pts = [(float(p[0]), float(p[1]), float(p[2])) for p in points]
    if not pts:
        return np.zeros((0, 2))
    out = [pts[0][:2]]
    segs = list(zip(pts, pts[1:] + ([pts[0]] if closed else [])))
    for (x0, y0, b), (x1, y1, _) in segs:
        if b != 0 and (x0, y0) != (x1, y1):
            c, a0, a1, r = bulge_to_arc((x0, y0), (x1, y1), b)
            sweep = (a1 - a0) % (2 * math.pi)
            if b < 0:                                   # bulge_to_arc swaps the ends of a clockwise arc
                a0, sweep = a1, -sweep
            v = flatten_arc((c.x, c.y), r, a0, sweep, tol)
            v[-1] = (x1, y1)
            out.extend(map(tuple, v))
        else:
            out.append((x1, y1))
    return np.array(out, float)


def _entity_path(e, tol):
    """(vertices (k, 2) in WCS drawing units, closed) of one supported entity."""
    t = e.dxftype()
    if t == "POINT":
        p = e.dxf.location
        return np.array([[p.x, p.y]]), False
    if t == "LINE":
        a, b = e.dxf.start, e.dxf.end
        return np.array([[a.x, a.y], [b.x, b.y]]), False
    if t == "LWPOLYLINE":
        closed = bool(e.closed)
        v = _bulge_path(e.get_points("xyb"), closed, tol)
        if len(v):
            z = float(e.dxf.elevation)
            w = np.array([[q.x, q.y] for q in e.ocs().points_to_wcs([(a, b, z) for a, b in v])])
            v = w
        return v, closed
    if t == "POLYLINE":
        if not (e.is_2d_polyline or e.is_3d_polyline):
            raise ValueError("mesh")
        closed = bool(e.is_closed)
        pts = [(v.dxf.location.x, v.dxf.location.y, v.dxf.bulge) for v in e.vertices]
        v = _bulge_path(pts, closed, tol)
        if e.is_2d_polyline and len(v):
            v = np.array([[q.x, q.y] for q in e.ocs().points_to_wcs([(a, b, 0.0) for a, b in v])])
        return v, closed
    if t == "CIRCLE":
        v = np.array([[q.x, q.y] for q in e.flattening(tol)])
        return v, True
    if t in ("ARC", "ELLIPSE", "SPLINE"):
        v = np.array([[q.x, q.y] for q in e.flattening(tol)])
        closed = t == "ELLIPSE" and abs(abs(e.dxf.end_param - e.dxf.start_param) - 2 * math.pi) < 1e-9
        return v, closed
    raise ValueError(t)


def _walk(entities, layer_of_insert, tol, scale, out, unsupported, top_handle, depth=0):
    """Expand entities (INSERTs recursively) into (path, closed, type, attribs, handle) rows."""
    for e in entities:
        t = e.dxftype()
        layer = e.dxf.get("layer", "0")
        if layer == "0" and layer_of_insert is not None:
            layer = layer_of_insert
        handle = top_handle if top_handle is not None else e.dxf.handle
        if t == "INSERT":
            if depth > 16:
                raise MarkcalError("block references nested more than 16 deep")
            try:
                subs = list(e.virtual_entities())
            except Exception as exc:                       # ezdxf refuses e.g. non-uniform scaled arcs
                unsupported[f"INSERT ({type(exc).__name__})"] += 1
                continue
            _walk(subs, layer, tol, scale, out, unsupported, handle, depth + 1)
            continue
        if t not in _GEOMETRY:
            unsupported[t] += 1
            continue
        try:
            v, closed = _entity_path(e, tol / scale)
        except ValueError:
            unsupported[f"{t} (mesh)"] += 1
            continue
        if len(v) == 0:
            continue
        attribs = {"layer": layer}
        for k in _ATTRIBS:
            if e.dxf.hasattr(k):
                attribs[k] = e.dxf.get(k)
        out.append((v * scale, closed, t, attribs, handle))


def read_dxf(data: bytes, tolerance_mm: float = 0.01, source=None) -> JobFile:
    """Read a DXF job (bytes of the file), mm.

    Parameters
    ----------
    data : bytes
    tolerance_mm : float
        Chordal tolerance of flattened curves, mm.
    source : path, optional

    Raises
    ------
    MarkcalError
        Unreadable or truncated DXF, unsupported ``$INSUNITS``, no geometry.
    """
    doc = _load(data, source)
    code = int(doc.header.get("$INSUNITS", 0))
    if code not in INSUNITS_MM:
        from ezdxf.units import unit_name
        raise MarkcalError(f"unsupported units: $INSUNITS = {code} ({unit_name(code)}); "
                           "use mm, cm, m, inch, foot, mil or micron", source)
    scale = INSUNITS_MM[code]
    rows, unsupported = [], Counter()
    try:
        _walk(doc.modelspace(), None, tolerance_mm, scale, rows, unsupported, None)
    except MarkcalError as exc:
        raise exc.with_path(source) from None
    if not rows:
        extra = f" (only {', '.join(f'{k} x{v}' for k, v in sorted(unsupported.items()))})" if unsupported else ""
        raise MarkcalError(f"no geometry: no entities the path flow can mark{extra}", source)
    strokes = paths_to_strokes([r[0] for r in rows], [r[1] for r in rows])
    job = build_job(strokes, source)
    notes = ("$INSUNITS is 0 (unitless): read as mm",) if code == 0 else ()
    handles = tuple(dict.fromkeys(r[4] for r in rows))
    payload = DxfPayload(bytes(data), handles, tuple(r[2] for r in rows), tuple(r[3] for r in rows), scale)
    return JobFile(job, "dxf", tuple(r[3]["layer"] for r in rows), dict(unsupported), notes, payload)


def write_dxf(jf: JobFile, tour) -> bytes:
    """The DXF drawing with its strokes in the order of ``tour`` (see the module notes)."""
    p: DxfPayload = jf.payload
    doc = _load(p.data, None)
    msp = doc.modelspace()
    for h in p.handles:
        e = doc.entitydb.get(h)
        if e is not None and e.is_alive:
            msp.delete_entity(e)
    for s, kind, xy in marked_strokes(jf.job, tour):
        q = np.asarray(xy, float) / p.mm_per_unit
        at = dict(p.attribs[s])
        if kind == "point":
            msp.add_point((q[0, 0], q[0, 1]), dxfattribs=at)
        elif p.types[s] == "LINE" and len(q) == 2:
            msp.add_line(tuple(q[0]), tuple(q[1]), dxfattribs=at)
        else:
            msp.add_lwpolyline([tuple(r) for r in q], format="xy", close=kind == "contour", dxfattribs=at)
    buf = io.StringIO()
    doc.write(buf)
    return buf.getvalue().encode(doc.output_encoding, errors="dxfreplace")
