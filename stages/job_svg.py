"""SVG marking jobs read with svgelements and written back with the document kept.

Reads every shape (path, rect, circle, ellipse, line, polyline, polygon, and
``<use>`` copies) with its transforms, the viewBox and the root's width/height
units applied (svgelements, 96 px per inch), flattens arcs and Béziers to a
chordal tolerance and converts to mm. A subpath ending with ``Z`` or where it
started is a closed contour. The group of a stroke is its Inkscape layer label,
else its stroke colour (what laser software uses as layers). Text and images
are listed as unsupported and kept.

Writing parses the source document again, removes the elements that became
strokes and appends the strokes in marking order as ``<path>`` elements in the
root's user units, each with its source's own style and computed stroke and
fill, consecutive strokes of one layer inside a ``<g>`` with the layer's label.
"""
from __future__ import annotations

import io
import re
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass

import numpy as np

from .errors import MarkcalError
from .job_formats import JobFile, build_job, fmt_num, marked_strokes, paths_to_strokes

__all__ = ["read_svg", "write_svg", "SvgPayload", "MM_PER_PX"]

MM_PER_PX = 25.4 / 96.0
SVG_NS = "http://www.w3.org/2000/svg"
INKSCAPE_NS = "http://www.inkscape.org/namespaces/inkscape"
XLINK_NS = "http://www.w3.org/1999/xlink"
#: the most elements ``<use>`` references may expand into (a "use bomb" of nested references is refused)
MAX_USE_INSTANCES = 1_000_000
_SHAPES = {"path", "rect", "circle", "ellipse", "line", "polyline", "polygon", "use"}
#: px per unit, exact (svgelements rounds inch per mm to 0.0393701, 5e-7 off)
_UNITS = {"": 1.0, "px": 1.0, "mm": 96 / 25.4, "cm": 96 / 2.54, "in": 96.0, "pt": 96 / 72, "pc": 16.0,
          "q": 96 / 101.6}
_STYLE_KEYS = ("style", "class", "stroke", "fill", "stroke-width", "stroke-linecap", "stroke-linejoin", "opacity")
_PROBE = "markcal-probe"


@dataclass(frozen=True, eq=False)
class SvgPayload:
    data: bytes                # the source document with ids added to shapes and a probe path
    namespaces: tuple          # (prefix, uri) of the source
    sources: tuple             # per stroke: id of the element it came from
    styles: tuple              # per stroke: dict of attributes for the written path
    layers: tuple              # per stroke: dict of attributes of its layer group (or {})
    user_from_mm: tuple        # 2 x 3 affine: root user units from mm
    size: tuple                # the root's width / height as written in the source


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1] if isinstance(tag, str) else ""


def _parse_xml(data: bytes, source):
    try:
        ns = [v for _, v in ET.iterparse(io.BytesIO(data), events=("start-ns",))]
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise MarkcalError(f"not a readable SVG file (XML: {exc})", source) from None
    if _local(root.tag) != "svg":
        raise MarkcalError(f"not an SVG document (root element <{_local(root.tag)}>)", source)
    return root, tuple(dict(ns).items())


def _check_uses(by_id: dict, source) -> None:
    """Refuse ``<use>`` references that form a cycle (a group using itself) or expand past
    :data:`MAX_USE_INSTANCES` elements, before svgelements follows them."""
    def target(u):
        h = u.get("href") or u.get(f"{{{XLINK_NS}}}href") or ""
        return h[1:] if h.startswith("#") and h[1:] in by_id else None
    deps = {i: [t for u in el.iter() if _local(u.tag) == "use" and (t := target(u))] for i, el in by_id.items()}
    count, on_path = {}, set()
    for start in deps:
        if start in count:
            continue
        stack = [(start, iter(deps[start]))]
        on_path.add(start)
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                stack.pop()
                on_path.discard(node)
                count[node] = 1 + sum(count[t] for t in deps[node])
                if count[node] > MAX_USE_INSTANCES:
                    raise MarkcalError(f"<use> references under id '{node}' expand into more than "
                                       f"{MAX_USE_INSTANCES:,} elements", source)
            elif nxt in on_path:
                raise MarkcalError(f"<use> references form a cycle through id '{nxt}'", source)
            elif nxt not in count:
                on_path.add(nxt)
                stack.append((nxt, iter(deps[nxt])))


def _register(namespaces):
    for prefix, uri in namespaces:
        try:
            ET.register_namespace(prefix, uri)
        except ValueError:                          # reserved prefixes such as ns0
            pass


def _flatten(seg, tol_px: float):
    """Vertices after the start of a curved segment, chordal deviation <= tol_px (adaptive bisection)."""
    out = []

    def point(t):
        q = seg.point(t)
        return np.array([q.x, q.y], float)

    def rec(t0, p0, t1, p1, depth):
        tm = 0.5 * (t0 + t1)
        pm = point(tm)
        chord = p1 - p0
        n = np.hypot(*chord)
        probes = [pm, point(0.5 * (t0 + tm)), point(0.5 * (tm + t1))]
        if n > 0:
            dev = max(abs(chord[0] * (q[1] - p0[1]) - chord[1] * (q[0] - p0[0])) / n for q in probes)
        else:
            dev = max(np.hypot(*(q - p0)) for q in probes)
        if depth >= 2 and (dev <= tol_px or depth > 24):
            out.append(p1)
            return
        rec(t0, p0, tm, pm, depth + 1)
        rec(tm, pm, t1, p1, depth + 1)

    rec(0.0, point(0.0), 1.0, point(1.0), 0)
    return out


def _subpaths(shape, tol_px):
    """(vertices in px, closed) per subpath of a transformed svgelements shape."""
    from svgelements import Close, Line, Move
    paths, cur, closed = [], None, False
    for seg in shape.segments(transformed=True):
        if isinstance(seg, Move):
            if cur:
                paths.append((cur, closed))
            cur, closed = [np.array([seg.end.x, seg.end.y], float)], False
            continue
        if cur is None:
            cur = [np.array([seg.start.x, seg.start.y], float)]
        if isinstance(seg, Close):
            closed = True
            if seg.end is not None:
                cur.append(np.array([seg.end.x, seg.end.y], float))
        elif isinstance(seg, Line):
            cur.append(np.array([seg.end.x, seg.end.y], float))
        else:
            cur.extend(_flatten(seg, tol_px))
    if cur:
        paths.append((cur, closed))
    return paths


def _root_size_px(root, source) -> dict:
    """Root width / height converted to px exactly; the original texts are returned."""
    orig = {}
    for k in ("width", "height"):
        v = (root.get(k) or "").strip()
        if not v:
            continue
        m = re.fullmatch(r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([A-Za-z%]*)", v)
        if not m or m.group(2).lower() not in _UNITS:
            raise MarkcalError(f"unsupported units: <svg {k}={v!r}> (use px, mm, cm, in, pt, pc or a number)",
                               source)
        orig[k] = v
        root.set(k, repr(float(m.group(1)) * _UNITS[m.group(2).lower()]))
    return orig


def read_svg(data: bytes, tolerance_mm: float = 0.01, source=None) -> JobFile:
    """Read an SVG job (bytes of the file), mm.

    Parameters
    ----------
    data : bytes
    tolerance_mm : float
        Chordal tolerance of flattened arcs and Béziers, mm.
    source : path, optional

    Raises
    ------
    MarkcalError
        Not XML / not SVG (truncated files fail here), unsupported root units, no geometry.
    """
    from svgelements import SVG, Shape, Use
    root, namespaces = _parse_xml(data, source)
    size = _root_size_px(root, source)
    _register(namespaces)
    parents = {c: p for p in root.iter() for c in p}
    in_defs = set()
    for d in root.iter(f"{{{SVG_NS}}}defs"):
        in_defs.update(d.iter())
    k = 0
    for el in root.iter():
        if _local(el.tag) in _SHAPES and not el.get("id"):
            el.set("id", f"markcal-{k}")
            k += 1
    by_id = {el.get("id"): el for el in root.iter() if el.get("id")}
    _check_uses(by_id, source)
    ET.SubElement(root, f"{{{SVG_NS}}}path", {"id": _PROBE, "d": "M 0 0 L 1 0 L 0 1", "fill": "none"})
    tagged = ET.tostring(root, encoding="utf-8", xml_declaration=True)
    try:
        svg = SVG.parse(io.BytesIO(tagged), reify=True, ppi=96.0)
    except Exception as exc:                             # svgelements raises plain errors on bad values
        raise MarkcalError(f"not a readable SVG file ({type(exc).__name__}: {str(exc)[:60]})", source) from None
    tol_px = tolerance_mm / MM_PER_PX
    paths, flags, sources, styles, layers, groups = [], [], [], [], [], []
    unsupported = Counter()
    probe = None
    use_id = None
    for el in svg.elements():
        name = type(el).__name__
        if isinstance(el, Use):
            use_id = el.id
            continue
        if not isinstance(el, Shape):
            if name in ("Text", "SVGText", "Image", "SVGImage"):
                unsupported[name.replace("SVG", "").lower()] += 1
            continue
        if el.id == _PROBE:
            seg = [np.array([s.end.x, s.end.y]) for s in el.segments(transformed=True)]
            probe = seg
            continue
        xml_el = by_id.get(el.id)
        src = el.id
        if xml_el is None or xml_el in in_defs:
            if use_id is None:
                unsupported[f"{name.lower()} (no source element)"] += 1
                continue
            src = use_id
            xml_el = by_id.get(use_id)
        layer_el = _layer_of(xml_el, parents)
        stroke = str(el.stroke) if el.stroke is not None and el.stroke.value is not None else None
        fill = str(el.fill) if el.fill is not None and el.fill.value is not None else "none"
        style = {a: xml_el.get(a) for a in _STYLE_KEYS if xml_el is not None and xml_el.get(a) is not None}
        style.setdefault("stroke", stroke or "none")
        style.setdefault("fill", fill)
        layer = dict(layer_el.attrib) if layer_el is not None else {}
        group = layer.get(f"{{{INKSCAPE_NS}}}label") or (stroke or "")
        for p, closed in _subpaths(el, tol_px):
            paths.append(np.asarray(p) * MM_PER_PX)
            flags.append(closed)
            sources.append(src)
            styles.append(style)
            layers.append(layer)
            groups.append(group)
    if not paths:
        extra = f" (only {', '.join(f'{k} x{v}' for k, v in sorted(unsupported.items()))})" if unsupported else ""
        raise MarkcalError(f"no geometry: no shapes the path flow can mark{extra}", source)
    job = build_job(paths_to_strokes(paths, flags), source)
    o, ex, ey = probe[0] * MM_PER_PX, (probe[1] - probe[0]) * MM_PER_PX, (probe[2] - probe[0]) * MM_PER_PX
    a = np.linalg.inv(np.column_stack([ex, ey]))               # user from mm: u = A (mm - o)
    aff = np.column_stack([a, -a @ o])
    payload = SvgPayload(tagged, namespaces, tuple(sources), tuple(styles), tuple(layers),
                         tuple(map(tuple, aff)), tuple(size.items()))
    return JobFile(job, "svg", tuple(groups), dict(unsupported), (), payload)


def _layer_of(el, parents):
    while el is not None:
        el = parents.get(el)
        if el is not None and _local(el.tag) == "g" and el.get(f"{{{INKSCAPE_NS}}}groupmode") == "layer":
            return el
    return None


def write_svg(jf: JobFile, tour) -> bytes:
    """The SVG document with its strokes in the order of ``tour`` (see the module notes)."""
    p: SvgPayload = jf.payload
    _register(p.namespaces)
    root = ET.fromstring(p.data)
    for k, v in p.size:
        root.set(k, v)
    parents = {c: par for par in root.iter() for c in par}
    drop = set(p.sources) | {_PROBE}
    for el in list(root.iter()):
        if el.get("id") in drop and el in parents:
            parents[el].remove(el)
    for el in root.iter():
        if (el.get("id") or "").startswith("markcal-"):
            del el.attrib["id"]
    aff = np.asarray(p.user_from_mm)
    out = ET.SubElement(root, f"{{{SVG_NS}}}g", {"id": "markcal-ordered"})
    run_key, run = None, None
    for s, kind, xy in marked_strokes(jf.job, tour):
        layer = p.layers[s]
        if run is None or (jf.groups[s], layer) != run_key:
            attrs = {k: v for k, v in layer.items() if k not in ("transform", "id")}
            run = ET.SubElement(out, f"{{{SVG_NS}}}g", attrs)
            run_key = (jf.groups[s], layer)
        u = np.asarray(xy) @ aff[:, :2].T + aff[:, 2]
        pts = " L ".join(f"{fmt_num(a)},{fmt_num(b)}" for a, b in u)
        d = f"M {pts}" + (" Z" if kind == "contour" else "") + (f" L {fmt_num(u[0, 0])},{fmt_num(u[0, 1])}"
                                                                  if kind == "point" else "")
        ET.SubElement(run, f"{{{SVG_NS}}}path", {**p.styles[s], "d": d})
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)
