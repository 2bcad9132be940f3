"""Height maps as text: Gwyddion's *ASCII data matrix* export with its informational header.

Gwyddion (File > Save As > "ASCII data matrix", "Add informational comment header") writes::

    # Channel: Height
    # Width: 20.000 µm
    # Height: 20.000 µm
    # Value units: m
    -1.2345e-09\t-1.2301e-09\t...

one line per scan line, top line first, values in the value unit (tab-separated; a comma as the decimal
separator where the locale has one; the labels translated with the user interface). Several channels
exported into one file follow each other, each with its header. Width and Height are the field's size, so
the pixel size is Width over the values per line. The values keep the digits asked for on export (5 by
default): :mod:`markcal.stages.indent_unflatten` allows for that rounding.

A matrix without the header has no height unit and no lateral size; it is refused, not guessed.
"""
from __future__ import annotations

import io
import re

import numpy as np

from .afm_files import Channel, height_nm_per_unit, length_um, pick_channel, pixel_um_xy
from .errors import MarkcalError

__all__ = ["is_text_matrix", "parse_text_matrix", "text_matrix"]

#: Gwyddion's header labels in its user-interface languages (English, Czech, German, Spanish, French,
#: Italian, Portuguese, Russian)
_LABELS = {
    "channel": ("channel", "kanál", "kanal", "canal", "canale", "канал"),
    "width": ("width", "šířka", "breite", "anchura", "largeur", "larghezza", "largura", "ширина"),
    "height": ("height", "výška", "höhe", "altura", "hauteur", "altezza", "высота"),
    "value_units": ("value units", "jednotky hodnot", "einheiten", "unidades de valor", "unités",
                    "unità valore", "единицы измерения"),
}
_HEADER = re.compile(r"^#\s*(?P<key>[^:=：]+?)\s*[:=：]\s*(?P<value>.*?)\s*$")
_NUMBER_UNIT = re.compile(r"^(?P<num>[-+]?(?:\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE][-+]?\d+)?)\s*(?P<unit>.*)$")


def _field(key: str) -> str | None:
    k = key.strip().lower()
    return next((name for name, labels in _LABELS.items() if k in labels), None)


def is_text_matrix(head: bytes) -> bool:
    """True when a file's first bytes are a Gwyddion header line (``# Channel: ...``, ``# Width: ...``)."""
    text = head.lstrip(b"\xef\xbb\xbf").decode("utf-8", "replace")
    m = _HEADER.match(text.splitlines()[0]) if text.startswith("#") else None
    return m is not None and _field(m["key"]) is not None


def _value(text: str) -> float:
    return float(text.replace(",", ".")) if "." not in text else float(text)


def _numbers(line: str) -> list[float]:
    """A data line's values: separated by tabs, spaces or semicolons; commas separate values too when they
    are not the decimal separator (points present, or nothing else separates)."""
    sep = r"[\s;,]+" if ("." in line or not re.search(r"[\s;]", line)) else r"[\s;]+"
    return [_value(t) for t in re.split(sep, line)]


def _blocks(text: str):
    """(header dict, data lines as (line number, text)) per channel block: a header opens a block after
    data lines."""
    blocks, head, rows = [], {}, []
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            if rows:
                blocks.append((head, rows))
                head, rows = {}, []
            m = _HEADER.match(s)
            if m is not None and _field(m["key"]) is not None:
                head[_field(m["key"])] = m["value"]
            continue
        rows.append((n, s))
    if rows:
        blocks.append((head, rows))
    return blocks


def _matrix(lines) -> np.ndarray:
    """The values of a block's data lines, (lines, values per line)."""
    body = "\n".join(s for _, s in lines)
    if "," not in body and ";" not in body:
        try:                                           # numpy's parser: 0.1-0.2 s for a 1024 x 1024 export
            return np.loadtxt(io.StringIO(body), dtype=np.float64, ndmin=2)
        except ValueError:
            pass                                       # line by line, to say which line is wrong
    rows = []
    for n, s in lines:
        try:
            rows.append(_numbers(s))
        except ValueError:
            raise MarkcalError(f"line {n} of the text matrix is neither a header nor numbers: {s[:40]!r}") from None
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise MarkcalError(f"text matrix lines hold {min(widths)} to {max(widths)} values (a truncated or "
                           "ragged file)")
    return np.asarray(rows, np.float64)


def _size_um(text: str | None) -> float | None:
    m = _NUMBER_UNIT.match(text or "")
    if m is None:
        return None
    per = length_um(m["unit"])
    return None if per is None else _value(m["num"]) * per


def parse_text_matrix(text: str, channel: str | None = None):
    """The channel's heights (nm), pixel size (µm, or an (x, y) tuple) and meta from a text matrix.

    The channel is chosen as in every AFM reader (:func:`markcal.stages.afm_files.pick_channel`).

    Raises
    ------
    MarkcalError
        No numbers; lines of different lengths; no header or no height unit (``Value units``); a height
        unit that is not a length; the named channel absent.
    """
    blocks = _blocks(text)
    if not blocks:
        raise MarkcalError("text matrix holds no numbers")
    chans = [Channel(h.get("channel") or "Height", None, None) for h, _ in blocks]
    if len(blocks) == 1 and channel is None:
        index = 0
    else:
        picked = pick_channel(chans, channel)
        index = next(i for i, c in enumerate(chans) if c is picked)
    head, lines = blocks[index]
    data = _matrix(lines)
    name = chans[index].name
    unit = head.get("value_units")
    if unit is None:
        raise MarkcalError("text matrix has no header with its height unit ('# Value units: m'; export it with "
                           "Gwyddion's informational comment header)")
    scale = height_nm_per_unit(unit)
    if scale is None:
        raise MarkcalError(f"channel '{name}' is in '{unit}', not a height in a length unit")
    meta = {"format": "text", "channel": name, "channels": [c.name for c in chans], "z_unit_in_file": unit}
    w_um, h_um = _size_um(head.get("width")), _size_um(head.get("height"))
    px = None
    if w_um is None:
        meta["pixel_problem"] = (f"lateral size '{head['width']}' has no length unit" if "width" in head
                                 else "text matrix gives no lateral size ('# Width: 20.000 µm')")
    elif h_um is None:
        px = w_um / data.shape[1]
    else:
        px = pixel_um_xy(w_um, h_um, data.shape[1], data.shape[0])
    return data * scale, px, meta


def text_matrix(z, width_m: float, height_m: float, unit: str = "m", channel: str = "Height",
                digits: int = 5) -> str:
    """A (rows, cols) field as Gwyddion's ASCII data matrix export writes it (header, ``digits``
    significant digits, tab-separated, top line first)."""
    z = np.asarray(z, np.float64)
    head = [f"# Channel: {channel}", f"# Width: {width_m * 1e6:.7g} µm", f"# Height: {height_m * 1e6:.7g} µm",
            f"# Value units: {unit}"]
    body = ["\t".join(f"{v:.{digits - 1}e}" for v in row) for row in z]
    return "\n".join(head + body) + "\n"
