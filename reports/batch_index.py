"""OUT_DIR/index.html, summary.csv and summary.json of a batch run.

index.html is one self-contained page: counts, the summary table (one row per
input; sortable by clicking a header, filterable by text and status, all in
inline JavaScript), one table of key figures per flow, trend plots across
inputs in time order, and a relative link to every per-input report.
"""
from __future__ import annotations

import json
import os
import re

import numpy as np

from .files import atomic_write_text, write_csv, write_json
from .html import drawable, esc, img, new_figure, num, page, png_b64

__all__ = ["write_batch_index", "batch_index_html"]

STATUS_TEXT = {"pass": "pass", "fail": "out of tolerance", "done": "done (no tolerance)", "error": "failed to process"}

EXTRA_CSS = """
.st-pass{background:#e6f4ea}.st-fail{background:#fde2cf}.st-error{background:#f8c9c5}.st-done{background:#eef1f5}
td.reason{text-align:left;max-width:420px;font-size:.88em}
th.s{cursor:pointer;user-select:none}th.s:after{content:" \\2195";color:#999;font-size:.8em}
.counts span{display:inline-block;padding:4px 10px;margin:0 6px 6px 0;border-radius:4px;font-weight:600}
.wide{overflow-x:auto}.filters{margin:10px 0}.filters input{width:280px;padding:3px}
"""

SCRIPT = """
(function(){
  function val(td){var v=td.getAttribute('data-v');if(v===null)v=td.textContent;var f=parseFloat(v);
    return (v!==''&&!isNaN(f)&&isFinite(v))?f:v.toLowerCase();}
  document.querySelectorAll('table.sortable').forEach(function(t){
    t.querySelectorAll('th.s').forEach(function(th,i){th.addEventListener('click',function(){
      var tb=t.tBodies[0],rows=Array.prototype.slice.call(tb.rows),asc=th.getAttribute('data-asc')!=='1';
      t.querySelectorAll('th.s').forEach(function(h){h.removeAttribute('data-asc');});
      th.setAttribute('data-asc',asc?'1':'0');
      rows.sort(function(a,b){var x=val(a.cells[i]),y=val(b.cells[i]);
        if(typeof x!==typeof y){x=String(x);y=String(y);}return (x<y?-1:x>y?1:0)*(asc?1:-1);});
      rows.forEach(function(r){tb.appendChild(r);});});});});
  var q=document.getElementById('q'),st=document.getElementById('st');
  function filt(){var s=q.value.toLowerCase(),w=st.value,n=0;
    document.querySelectorAll('table.sortable tbody tr').forEach(function(r){
      var ok=(!s||r.textContent.toLowerCase().indexOf(s)>=0)&&(!w||r.getAttribute('data-status')===w);
      r.style.display=ok?'':'none';if(ok&&r.parentNode.parentNode.id==='summary')n++;});
    document.getElementById('nshown').textContent=n;}
  q.addEventListener('input',filt);st.addEventListener('change',filt);filt();
})();
"""


def _cell(v):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return '<td data-v="">–</td>'
    if isinstance(v, bool):
        return f'<td data-v="{int(v)}">{"yes" if v else "no"}</td>'
    if isinstance(v, (int, float)):
        return f'<td data-v="{float(v)!r}">{num(v, "")}</td>'
    return f'<td class="l" data-v="{esc(v)}">{esc(v)}</td>'


def _input_time(rec) -> str:
    """When the input was measured: the data's own timestamp (``data_time``) if its file has one, else the
    file's modification time."""
    return rec.get("data_time") or rec["input_mtime"]


def _rel(path, out_dir):
    return os.path.relpath(path, out_dir).replace(os.sep, "/")


def _judged_keys(rec) -> list:
    """Summary keys a record was checked against, failed ones first (from ``failed_checks`` and ``checks``)."""
    keys = [c.split(" ")[0] for c in (rec.get("failed_checks") or "").split("; ") + (rec.get("checks") or "").split("; ")
            if c.strip()]
    return list(dict.fromkeys(keys))


def _main_figure(rec, flows):
    """The figure that decides this input's verdict (its first failed check, else its first check; a scan's
    calibration plate: the predicted residual, a validation plate: its deviation), else the flow's first trend."""
    e = flows.get(rec["flow"])
    if e is None or rec["status"] == "error":
        return "", None
    names = dict(zip(e.key_figures, e.captions))
    names.update(dict(e.trends))
    k = next((k for k in _judged_keys(rec) if k in rec), e.trends[0][0] if e.trends else None)
    return (names.get(k, k), rec.get(k)) if k else ("", None)


def _readable_checks(text: str, e) -> str:
    """``rms_mm 0.25 > 0.05`` -> ``scan deviation RMS, mm 0.25 > 0.05``: summary keys as their captions."""
    if e is None or not text:
        return text
    names = dict(zip(e.key_figures, e.captions))
    names.update(dict(e.trends))
    text = re.sub(r"[A-Za-z_][A-Za-z0-9_]*", lambda m: names.get(m.group(0), m.group(0)), text)
    return text.replace("<=", "≤").replace(">=", "≥")


def _tolerance_line(rs, shown) -> str:
    """The limits the inputs of one flow were judged on; one line per set (a scan's calibration and validation
    plates are judged on different figures)."""
    sets = {}
    for r in rs:
        if r["checks"]:
            sets.setdefault(r["checks"], []).append(str(r.get("kind") or ""))
    if not sets:
        return "<p>tolerance: none (status done)</p>"
    if len(sets) == 1:
        return f"<p>tolerance: {esc(_readable_checks(next(iter(sets)), shown))}</p>"
    items = "".join(f"<li>{esc(', '.join(sorted(set(k for k in kinds if k))) or 'some inputs')}: "
                    f"{esc(_readable_checks(c, shown))}</li>" for c, kinds in sets.items())
    return f"<p>tolerance, by the input's purpose:</p><ul>{items}</ul>"


def _summary_table(records, flows, out_dir) -> str:
    head = ["input", "group", "flow", "status", "main figure", "value", "failed checks / reason", "report"]
    ths = "".join(f'<th class="s{" l" if i < 3 or i >= 6 else ""}">{h}</th>' for i, h in enumerate(head))
    rows = []
    for r in records:
        k, v = _main_figure(r, flows)
        link = (f'<a href="{esc(_rel(r["report"], out_dir))}">report</a>' if r["report"] else
                (f'<a href="{esc(_rel(r["out_dir"], out_dir))}/summary.json">summary</a>'
                 if r["status"] != "error" else "–"))
        why = r["reason"] if r["status"] == "error" else _readable_checks(r["failed_checks"] or r["checks"],
                                                                          flows.get(r["flow"]))
        rows.append(f'<tr class="st-{r["status"]}" data-status="{r["status"]}">'
                    f'<td class="l" data-v="{esc(r["name"])}" title="{esc(r["input"])}">{esc(r["name"])}</td>'
                    f'{_cell(r["group"])}{_cell(r["flow"])}'
                    f'<td class="l" data-v="{r["status"]}">{STATUS_TEXT[r["status"]]}</td>'
                    f'{_cell(k)}{_cell(v)}<td class="reason" data-v="{esc(why)}">{esc(why)}</td>'
                    f'<td class="l" data-v="">{link}</td></tr>')
    return (f'<table id="summary" class="sortable"><thead><tr>{ths}</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table>')


def _flow_table(keys, records, flow, captions=None) -> str:
    head = ["input", "group", "status", "input time", *(captions or keys), "runtime, s", "reused"]
    tips = ["", "", "", "the data's own timestamp, else the file's modification time", *keys, "runtime_s", "reused"]
    ths = "".join(f'<th class="s{" l" if i < 2 else ""}" title="{esc(t)}">{esc(h)}</th>'
                  for i, (h, t) in enumerate(zip(head, tips)))
    rows = []
    for r in records:
        rows.append(f'<tr class="st-{r["status"]}" data-status="{r["status"]}">'
                    f'<td class="l" data-v="{esc(r["name"])}">{esc(r["name"])}</td>{_cell(r["group"])}'
                    f'<td class="l" data-v="{r["status"]}">{STATUS_TEXT[r["status"]]}</td>{_cell(_input_time(r))}'
                    + "".join(_cell(r.get(k)) for k in keys) + _cell(r["runtime_s"]) + _cell(r["reused"]) + "</tr>")
    return (f'<div class="wide"><table class="sortable" id="flow-{esc(flow)}"><thead><tr>{ths}</tr></thead>'
            f'<tbody>{"".join(rows)}</tbody></table></div>')


def _limit(records, key):
    tol = {}
    for r in records:
        for c in (r["checks"] or "").split("; "):
            parts = c.split(" ")
            if len(parts) == 3 and parts[0] == key:
                tol[parts[1]] = float(parts[2])
    return tol


def _trend_plot(flow, key, label, records, kinds=()) -> str:
    """One trend figure; ``kinds``: the flow's key figures, the first text-valued one splits the lines."""
    rs = sorted([r for r in records if r["status"] != "error"], key=lambda r: (_input_time(r), r["name"]))
    vals = [r.get(key) for r in rs]
    keep = [i for i, v in enumerate(vals) if isinstance(v, (int, float)) and np.isfinite(v)]
    if not keep:
        return ""
    fig = new_figure(7.5, 3.0)
    ax = fig.add_subplot(111)
    groups = sorted({rs[i]["group"] for i in keep})
    markers = "osD^v<>ph*"
    colours = {"pass": "#2e7d32", "fail": "#d9342b", "done": "#3b7dd8"}
    # an input not judged on this figure (e.g. a calibration plate on its uncorrected deviation) is drawn hollow
    judged = {i: key in _judged_keys(rs[i]) for i in keep}
    some_judged = any(judged.values())
    for gi, g in enumerate(groups):
        for st, c in colours.items():
            for on in (True, False):
                idx = [i for i in keep if rs[i]["group"] == g and rs[i]["status"] == st
                       and (judged[i] == on or not some_judged)]
                if idx and (on or some_judged):
                    ax.scatter(idx, [vals[i] for i in idx], marker=markers[gi % len(markers)], s=36, zorder=3,
                               facecolors=c if on else "none", edgecolors=c, linewidths=1.2,
                               label=f"{g or '(top)'}: {STATUS_TEXT[st]}" + ("" if on else ", not judged on this"))
    # a line joins the inputs of one group (machine) and one kind (a scan's purpose, a servo trace's kind) only
    kind_key = next((k for k in kinds if any(isinstance(rs[i].get(k), str) for i in keep)), None)
    for g, kd in sorted({(rs[i]["group"], str(rs[i].get(kind_key, ""))) for i in keep}):
        gi_keep = [i for i in keep if rs[i]["group"] == g and str(rs[i].get(kind_key, "")) == kd]
        ax.plot(gi_keep, [vals[i] for i in gi_keep], color="#999", lw=0.8, zorder=2)
    if all(float(vals[i]).is_integer() for i in keep):        # counts: whole-number axis from 0
        from matplotlib.ticker import MaxNLocator
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        top = max([vals[i] for i in keep] + list(_limit(rs, key).values()))
        ax.set_ylim(-0.5, max(top, 1) + 0.5)
    for op, lim in _limit(rs, key).items():
        ax.axhline(lim, color="#d9342b", ls="--", lw=1, label=f"limit {'≤' if op == '<=' else '≥' if op == '>=' else op} {lim:g}")
    ax.set_xticks(keep)
    ax.set_xticklabels([drawable(rs[i]["name"].split("/")[-1]) for i in keep], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(label)
    stamped = sum(bool(rs[i].get("data_time")) for i in keep)
    ax.set_xlabel("input, in time order (" + ("the data's own timestamps" if stamped == len(keep) else
                                              "file modification times" if not stamped else
                                              f"the data's own timestamp for {stamped} of {len(keep)}, else the "
                                              "file's modification time") + ")")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    hollow = " Hollow: an input whose verdict does not use this figure (a scan plate of the other purpose)." \
        if some_judged and not all(judged.values()) else ""
    return img(png_b64(fig), f"{flow} {key} trend",
               f"<b>{esc(flow)}</b>: {esc(label)} per input in time order; colour = status, marker = group "
               f"(sub-folder, e.g. the machine); dashed line = the pass/fail limit.{hollow}")


def batch_index_html(result, out_dir) -> str:
    """The whole index page of a batch result (``records``, ``flows``, counts; see ``pipeline/batch.py``)."""
    recs = result.records
    counts = "".join(f'<span class="st-{s}">{result.count(s)} {STATUS_TEXT[s]}</span>'
                     for s in ("pass", "fail", "done", "error"))
    parts = [f"<style>{EXTRA_CSS}</style>",
             f'<div class="counts"><span>{len(recs)} inputs</span>{counts}</div>',
             f'<div class="verdict">{result.n_run} processed in this run, {result.n_reused} reused from an earlier '
             f"run (outputs complete and newer than the input); {result.wall_s:.1f} s wall time.</div>"]
    bad_groups = sorted({(r["group"] or "(top)") for r in recs if r["status"] == "fail"})
    if bad_groups:
        parts.append(f'<div class="note">out of tolerance in: {esc(", ".join(bad_groups))}</div>')
    parts.append('<div class="filters">filter: <input id="q" type="search" placeholder="text in any column">'
                 ' status: <select id="st"><option value="">all</option>'
                 + "".join(f'<option value="{s}">{STATUS_TEXT[s]}</option>' for s in STATUS_TEXT)
                 + '</select> <span id="nshown"></span> rows shown; click a column header to sort</div>')
    parts.append("<h2>Summary</h2>")
    parts.append(_summary_table(recs, result.flows, out_dir))
    for f, shown in result.flows.items():
        rs = [r for r in recs if r["flow"] == f]
        parts.append(f"<h2>{esc(f)}: key figures</h2>")
        parts.append(_tolerance_line(rs, shown))
        parts.append(_flow_table(list(shown.key_figures), rs, f, list(shown.captions)))
        for key, label in shown.trends:
            parts.append(_trend_plot(f, key, label, rs, shown.key_figures))
    if result.ignored:
        parts.append("<h2>Files not recognised</h2><p>No flow claims these files; they were not processed:</p><ul>"
                     + "".join(f"<li><code>{esc(p)}</code></li>" for p in result.ignored) + "</ul>")
    parts.append("<footer><b>Data files beside this page</b><ul>"
                 "<li><code>summary.csv</code> — one row per input (columns in the README)</li>"
                 "<li><code>summary.json</code> — counts and the same rows</li>"
                 "<li><code>&lt;input name&gt;/</code> — each input's outputs, as its single command writes them"
                 "</li></ul></footer>")
    parts.append(f"<script>{SCRIPT}</script>")
    return page("markcal batch", parts, source=os.path.abspath(out_dir))


def _csv_value(v):
    return "" if v is None else v


def write_batch_index(result, out_dir) -> dict:
    """Write summary.csv, index.html and (last) summary.json into ``out_dir``; return name -> path."""
    os.makedirs(out_dir, exist_ok=True)
    p = {n: os.path.join(out_dir, n) for n in ("summary.csv", "index.html", "summary.json")}
    cols = result.columns
    write_csv(p["summary.csv"], {c: np.array([_csv_value(r.get(c)) for r in result.records], dtype=object)
                                 for c in cols})
    atomic_write_text(p["index.html"], batch_index_html(result, out_dir))
    write_json(p["summary.json"], {
        "n_inputs": len(result.records), "n_pass": result.count("pass"), "n_fail": result.count("fail"),
        "n_done": result.count("done"), "n_error": result.count("error"), "n_run": result.n_run,
        "n_reused": result.n_reused, "wall_s": result.wall_s, "exit_code": result.exit_code,
        "columns": cols, "rows": [{c: r.get(c) for c in cols} for r in result.records],
        "ignored": list(result.ignored)})
    return p


def read_summary(out_dir) -> dict:
    """Read a batch's summary.json."""
    with open(os.path.join(out_dir, "summary.json"), encoding="utf-8") as fh:
        return json.load(fh)
