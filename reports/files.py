"""Atomic file writers: write to a temporary name in the same folder, then rename."""
from __future__ import annotations

import csv
import io
import json
import os
import tempfile

import numpy as np


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that a reader never sees a half file."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".part", dir=folder)
    except OSError as exc:                        # name the file asked for, not the temporary one
        raise OSError(exc.errno, exc.strerror, path) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o666 & ~_umask())          # mkstemp makes 0600: give the file the process umask's mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path, text: str) -> None:
    """UTF-8 text; characters UTF-8 cannot hold (a non-UTF-8 file name's bytes) are written as ``\\udcXX``."""
    atomic_write_bytes(path, text.encode("utf-8", "backslashreplace"))


LOCK_NAME = ".markcal.lock"


def _input_within(out_path, inputs):
    """The first of ``inputs`` that is ``out_path`` itself or lies inside it (None when none does)."""
    out = os.path.realpath(out_path)
    for p in inputs:
        rp = os.path.realpath(p)
        if rp == out or rp.startswith(out.rstrip(os.sep) + os.sep):
            return p
    return None


def check_out_dir(out_dir, inputs=()) -> None:
    """Refuse an output folder that is an existing file, an input itself, a folder holding an input, or one
    that cannot be written in (:func:`check_writable`). Call it once, before any computation."""
    from markcal.stages.errors import MarkcalError
    check_path_length(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise MarkcalError("--out names an existing file, not a folder", out_dir)
    p = _input_within(out_dir, inputs)
    if p is not None:
        raise MarkcalError(f"--out is the input or a folder holding it ({p}): outputs could overwrite it; "
                           "choose another folder", out_dir)
    check_writable(out_dir)


def check_out_file(out_path, inputs=(), option: str = "--out") -> None:
    """Refuse an output *file* path that names a folder, an input, or lies in a folder that does not exist
    and cannot be made (checked before any computation). ``option`` names the flag in the messages."""
    from markcal.stages.errors import MarkcalError
    if os.path.isdir(out_path):
        raise MarkcalError(f"{option} names a folder; give the table file to write", out_path)
    p = _input_within(out_path, inputs)
    if p is not None:
        raise MarkcalError(f"{option} would overwrite an input ({p})", out_path)
    check_path_length(out_path)
    check_writable(os.path.dirname(os.path.abspath(out_path)), named=out_path)


def check_writable(folder, named=None) -> None:
    """Refuse, before any computation, an output folder that cannot be made or written in (``/proc/...``, a
    read-only mount): a probe folder is made in it, or in its nearest existing parent, and removed. The error
    names ``named`` (the file to write) when given, else the folder."""
    import tempfile

    from markcal.stages.errors import MarkcalError
    probe_in = os.path.abspath(folder)
    while not os.path.exists(probe_in) and os.path.dirname(probe_in) != probe_in:
        probe_in = os.path.dirname(probe_in)
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".markcal-probe-", dir=probe_in))
    except OSError as exc:
        raise MarkcalError(f"cannot write here ({exc.strerror or exc})", named or folder) from None


def check_path_length(path) -> None:
    """Refuse a path the file system cannot hold (a component over 255 bytes, the whole over 4095)."""
    from markcal.stages.errors import MarkcalError
    b = os.fsencode(os.path.abspath(path))
    name_max = 255
    if len(b) > 4095:
        raise MarkcalError(f"path is {len(b)} bytes long; at most 4095", path if len(b) < 300 else b[:120].decode(
            "utf-8", "replace") + "…")
    longest = max(b.split(os.fsencode(os.sep)), key=len)
    if len(longest) > name_max:
        raise MarkcalError(f"a path component is {len(longest)} bytes long; at most {name_max}", path)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _take_lock(out_dir) -> str:
    """Create ``out_dir``'s lock file; refuse while another live process holds it."""
    from markcal.stages.errors import MarkcalError
    path = os.path.join(out_dir, LOCK_NAME)
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(open(path).read().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _pid_alive(pid):
                raise MarkcalError(f"another markcal run (process {pid}) is writing into this folder; wait for it "
                                   f"or remove {LOCK_NAME} if there is none", out_dir) from None
            os.unlink(path)                 # stale (its process is gone) or our own
            continue
        with os.fdopen(fd, "w") as fh:
            fh.write(str(os.getpid()))
        return path
    raise MarkcalError("cannot take the output folder's lock", out_dir)


def start_outputs(out_dir) -> str:
    """Create ``out_dir``, remove what an earlier run wrote there; return the summary.json path.

    Every flow writes ``summary.json`` last, so a folder whose summary exists is
    complete: it goes first, with every file the earlier run listed in it
    (``outputs``), so a half-rewritten folder never looks complete and never
    mixes files of two runs. The caller has checked ``out_dir`` with
    :func:`check_out_dir`, once, before any work.
    """
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, "summary.json")
    if os.path.exists(path):
        try:
            with open(path, encoding="utf-8") as fh:
                old = json.load(fh).get("outputs", [])
        except (OSError, ValueError, AttributeError):
            old = []
        os.unlink(path)
        for name in old if isinstance(old, list) else []:
            p = os.path.join(out_dir, str(name))
            if os.path.basename(str(name)) == str(name) and name != "summary.json" and os.path.isfile(p):
                os.unlink(p)
    return path


class OutputFolder:
    """One flow's output folder: each file written atomically and recorded; ``summary.json`` last.

    Creating it removes an old ``summary.json`` (see :func:`start_outputs`);
    :meth:`finish` writes the new one and returns output name -> path.
    """

    def __init__(self, out_dir):
        self.out_dir = os.fspath(out_dir)
        self.created = not os.path.isdir(self.out_dir)
        self.summary_path = start_outputs(self.out_dir)
        self.lock_path = _take_lock(self.out_dir)
        self.paths = {}
        _UNFINISHED.append(self)

    def abort(self) -> None:
        """Remove every file this run wrote (and the folder if this run made it and it is now empty)."""
        for p in list(self.paths.values()) + [self.lock_path]:
            if os.path.isfile(p):
                os.unlink(p)
        if self.created and os.path.isdir(self.out_dir) and not os.listdir(self.out_dir):
            os.rmdir(self.out_dir)
        if self in _UNFINISHED:
            _UNFINISHED.remove(self)

    def _path(self, name: str) -> str:
        p = self.paths[name] = os.path.join(self.out_dir, name)
        return p

    def csv(self, name: str, columns: dict) -> None:
        """A CSV table (dict of equal-length columns)."""
        write_csv(self._path(name), columns)

    def json(self, name: str, obj) -> None:
        """A JSON file."""
        write_json(self._path(name), obj)

    def text(self, name: str, text: str) -> None:
        """A text file (UTF-8), e.g. report.html."""
        atomic_write_text(self._path(name), text)

    def bytes(self, name: str, data: bytes) -> None:
        """A binary file."""
        atomic_write_bytes(self._path(name), data)

    def finish(self, summary: dict) -> dict:
        """Write ``summary.json`` (last, listing the files written as ``outputs``); return output name -> path."""
        summary["outputs"] = sorted(self.paths)
        write_json(self.summary_path, summary)
        self.paths["summary.json"] = self.summary_path
        if os.path.exists(self.lock_path):
            os.unlink(self.lock_path)
        if self in _UNFINISHED:
            _UNFINISHED.remove(self)
        return dict(self.paths)


#: output folders of this process that were started and not finished
_UNFINISHED: list = []


def abort_unfinished_outputs() -> None:
    """After a failure: remove the files of every output folder this process started but did not finish,
    so a failed run leaves nothing half-written (called by the CLI's error handler)."""
    for folder in list(_UNFINISHED):
        try:
            folder.abort()
        except OSError:
            _UNFINISHED.remove(folder)


def _fmt(v):
    if isinstance(v, (float, np.floating)):
        return repr(float(v)) if np.isfinite(v) else ""
    if isinstance(v, (np.integer,)):
        return str(int(v))
    return str(v)


def write_csv(path, columns: dict) -> None:
    """Write a dict of equal-length columns as CSV with a header row.

    Floats are written by ``repr`` (exact round trip; NaN and infinities as empty cells). Numeric and
    boolean columns are formatted column by column; a table with any other column goes through the
    ``csv`` module (quoting), cell by cell.
    """
    names = list(columns)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    cols = [np.asarray(columns[k]) for k in names]
    if all(c.ndim == 1 and c.dtype.kind in "fiub" for c in cols):
        text = [_column_text(c) for c in cols]
        if len(text) == 1:                      # the csv module writes a row of one empty cell as ""
            text = [[t or '""' for t in text[0]]]
        if text:
            buf.write("\n".join(map(",".join, zip(*text))))
            buf.write("\n" if len(text[0]) else "")
    else:
        n = len(cols[0]) if cols else 0
        for i in range(n):
            w.writerow([_fmt(c[i]) for c in cols])
    atomic_write_text(path, buf.getvalue())


def _column_text(col: np.ndarray) -> list:
    """Cells of one numeric column as :func:`_fmt` writes them."""
    if col.dtype.kind == "f":
        finite = np.isfinite(col)
        cells = list(map(repr, col.astype(float).tolist()))
        if not finite.all():
            for i in np.flatnonzero(~finite):
                cells[i] = ""
        return cells
    return list(map(str, col.tolist()))


def read_csv(path) -> dict:
    """Read a CSV written by ``write_csv`` into float (or str) columns."""
    with open(path, encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    names = rows[0]
    out = {}
    for j, k in enumerate(names):
        vals = [r[j] for r in rows[1:]]
        try:
            out[k] = np.array([float(v) if v != "" else np.nan for v in vals])
        except ValueError:
            out[k] = np.array(vals)
    return out


def jsonable(o):
    """``o`` with numpy arrays, scalars and tuples made plain JSON values (lists, int, float, bool)."""
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist())
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if np.isfinite(o) else None
    return o


def write_json(path, obj) -> None:
    atomic_write_text(path, json.dumps(jsonable(obj), indent=2) + "\n")


def write_ply(path, xyz_mm: np.ndarray, intensity: np.ndarray) -> None:
    """Binary little-endian PLY with float32 x, y, z, intensity."""
    from plyfile import PlyData, PlyElement
    v = np.empty(len(xyz_mm), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    v["x"], v["y"], v["z"] = xyz_mm[:, 0], xyz_mm[:, 1], xyz_mm[:, 2]
    v["intensity"] = intensity
    buf = io.BytesIO()
    PlyData([PlyElement.describe(v, "vertex")], text=False,
            comments=["markcal synthetic laser-line scan; units mm"]).write(buf)
    atomic_write_bytes(path, buf.getvalue())


def write_npy(path, array: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())
