"""Reading and writing plate specs (PLATE.toml)."""
from __future__ import annotations

import os
import tomllib

from markcal.stages.errors import MarkcalError
from markcal.stages.plate import PlateSpec


def load_toml(path, what: str = "config file") -> dict:
    """Read a TOML file; a missing file or bad TOML is a MarkcalError naming it."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise MarkcalError(f"no such {what}", path) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise MarkcalError(f"not valid TOML: {exc}", path) from None
    except OSError as exc:
        raise MarkcalError(f"cannot read ({exc})", path) from None


def check_sections(d: dict, allowed: dict, path) -> None:
    """Refuse sections and keys not in ``allowed`` (section -> set of keys): typos must not pass silently."""
    for sec, keys in d.items():
        if sec not in allowed or not isinstance(keys, dict):
            raise MarkcalError(f"unknown section [{sec}] (known: {', '.join(allowed)})", path)
        for k in keys:
            if k not in allowed[sec]:
                raise MarkcalError(f"unknown key '{k}' in [{sec}] (known: {', '.join(sorted(allowed[sec]))})", path)


def read_plate_spec(path) -> PlateSpec:
    """Read a PLATE.toml; unknown keys are an error so typos do not pass silently."""
    path = os.fspath(path)
    d = load_toml(path, "plate spec")
    allowed = {"grid": {"rows", "cols", "pitch_mm"}, "fiducial": {"ring_radii_mm"},
               "galvo": {"d_mm", "e_mm"}, "correction": {"grid_step_mm"}}
    check_sections(d, allowed, path)
    g, f = d.get("grid", {}), d.get("fiducial", {})
    gv, c = d.get("galvo", {}), d.get("correction", {})
    default = PlateSpec()
    try:
        spec = PlateSpec(
            rows=int(g.get("rows", default.rows)), cols=int(g.get("cols", default.cols)),
            pitch_mm=float(g.get("pitch_mm", default.pitch_mm)),
            ring_radii_mm=tuple(float(r) for r in f.get("ring_radii_mm", default.ring_radii_mm)),
            d_mm=float(gv.get("d_mm", default.d_mm)), e_mm=float(gv.get("e_mm", default.e_mm)),
            grid_step_mm=float(c.get("grid_step_mm", default.grid_step_mm)))
    except (TypeError, ValueError) as exc:
        raise MarkcalError(f"bad value: {exc}", path) from None
    if spec.rows < 3 or spec.cols < 3:
        raise MarkcalError("grid needs at least 3 rows and 3 columns", path)
    if spec.pitch_mm <= 0 or spec.grid_step_mm <= 0 or spec.d_mm <= 0 or spec.e_mm < 0:
        raise MarkcalError("pitch_mm, grid_step_mm and d_mm must be positive, e_mm non-negative", path)
    if not spec.ring_radii_mm or min(spec.ring_radii_mm) <= 0 or 2 * max(spec.ring_radii_mm) >= spec.pitch_mm:
        raise MarkcalError("ring_radii_mm must be positive and the rings must fit inside the pitch", path)
    return spec


def plate_spec_toml(spec: PlateSpec) -> str:
    """The TOML text of a plate spec (as the renderer writes it)."""
    radii = ", ".join(repr(float(r)) for r in spec.ring_radii_mm)
    return (
        "[grid]\n"
        f"rows = {spec.rows}\n"
        f"cols = {spec.cols}\n"
        f"pitch_mm = {spec.pitch_mm!r}   # centre-to-centre, grid centred on the galvo origin\n"
        "[fiducial]\n"
        f"ring_radii_mm = [{radii}]\n"
        "[galvo]\n"
        f"d_mm = {spec.d_mm!r}   # X-mirror to the plane centre (paper 004 sec. 2.3)\n"
        f"e_mm = {spec.e_mm!r}   # between the mirror axes\n"
        "[correction]\n"
        f"grid_step_mm = {spec.grid_step_mm!r}\n"
    )


def read_selfcal_setup(path):
    """Read a self-calibration ``setup.toml``: ``n``, ``pitch_mm``, ``k``, ``views``.

    Unknown keys are an error. ``k = 0`` (or no ``k``) means an XY-only session.
    """
    from markcal.stages.selfcal import SelfcalSetup

    path = os.fspath(path)
    d = load_toml(path, "setup file")
    allowed = {"n", "pitch_mm", "k", "views"}
    for key in d:
        if key not in allowed:
            raise MarkcalError(f"unknown key '{key}' (expected {', '.join(sorted(allowed))})", path)
    for key in ("n", "pitch_mm"):
        if key not in d:
            raise MarkcalError(f"missing key '{key}'", path)
    try:
        n, k = d["n"], d.get("k", 0)
        if not isinstance(n, int) or not isinstance(k, int):
            raise ValueError("n and k must be integers")
        views = tuple(int(v) for v in d.get("views", [0, 1, 2, 3]))
        setup = SelfcalSetup(n=n, pitch_mm=float(d["pitch_mm"]), k=k, views=views)
    except (TypeError, ValueError) as exc:
        raise MarkcalError(f"bad value: {exc}", path) from None
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    return setup


def selfcal_setup_toml(setup) -> str:
    """The TOML text of a self-calibration setup (as the renderer writes it)."""
    return (
        f"n = {setup.n}              # sites per side (odd); m, n run from -(n-1)/2 to (n-1)/2\n"
        f"pitch_mm = {setup.pitch_mm!r}     # site interval\n"
        f"k = {setup.k}              # angular lines (multiple of 4; 0 = XY only)\n"
        f"views = [{', '.join(str(v) for v in setup.views)}]   # 0 aligned, 1 turned +90 deg, "
        "2 turned +360/k deg, 3 shifted one pitch along +X\n"
    )
