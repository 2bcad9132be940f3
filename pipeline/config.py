"""Every spec and config file markcal reads, through one strict declarative schema.

A schema maps section -> key -> :class:`Key` (section ``""`` holds top-level
keys). :func:`read_config` refuses unknown sections and keys (listing the known
ones), wrong types, values out of range and missing required keys, each with
one line naming the file; it returns every key with its default filled in.
"""
from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, fields, replace

from markcal.pipeline.tables import read_input_bytes
from markcal.stages.errors import MarkcalError
from markcal.stages.limits import check_text_ends
from markcal.stages.plate import PURPOSES, PlateSpec


def read_bytes(path, what: str = "config file") -> bytes:
    """A config file's bytes (:func:`~markcal.pipeline.tables.read_input_bytes`: "no such <what>" when missing)."""
    return read_input_bytes(path, what, missing=f"no such {what}")


def parse_toml(data: bytes, path) -> dict:
    """TOML text (UTF-8 bytes) -> dict; bad TOML is a MarkcalError naming ``path``."""
    try:
        return tomllib.loads(data.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise MarkcalError(f"not valid TOML: {exc}", path) from None


def load_toml(path, what: str = "config file") -> dict:
    """Read a TOML file; a missing file or bad TOML is a MarkcalError naming it."""
    return parse_toml(read_bytes(path, what), os.fspath(path))


@dataclass(frozen=True)
class Key:
    """One key of a config file.

    Attributes
    ----------
    type : str
        ``float``, ``int``, ``bool``, ``str``, ``floats`` or ``ints`` (non-empty lists).
    default : object
        Value when the key is absent (ignored when ``required``).
    required : bool
        The key must be given.
    min, max : float, optional
        Inclusive bounds of a number (of every element of a list).
    positive : bool
        The number must be > 0 (finite).
    choices : tuple
        Allowed values of a ``str``.
    also : tuple
        Literal values accepted besides the type (e.g. ``"auto"``).
    unit : str
        Unit of the value, for messages and documentation.
    """

    type: str
    default: object = None
    required: bool = False
    min: float | None = None
    max: float | None = None
    positive: bool = False
    choices: tuple = ()
    also: tuple = ()
    unit: str = ""


def _where(sec: str, key: str) -> str:
    return f"[{sec}] {key}" if sec else key


def _number(v, is_int: bool, spec: Key, where: str, path):
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (is_int and not isinstance(v, int)):
        raise MarkcalError(f"{where} must be {'an integer' if is_int else 'a number'} (got {v!r})", path)
    if not math.isfinite(v):
        raise MarkcalError(f"{where} must be finite (got {v!r})", path)
    unit = f" {spec.unit}" if spec.unit else ""
    if spec.positive and not v > 0:
        raise MarkcalError(f"{where} must be positive (got {v!r}{unit})", path)
    if spec.min is not None and v < spec.min:
        raise MarkcalError(f"{where} must be at least {spec.min:g}{unit} (got {v!r})", path)
    if spec.max is not None and v > spec.max:
        raise MarkcalError(f"{where} must be at most {spec.max:g}{unit} (got {v!r})", path)
    return int(v) if is_int else float(v)


def _value(v, spec: Key, sec: str, key: str, path):
    where = _where(sec, key)
    if spec.also and v in spec.also and not isinstance(v, bool):
        return v
    t = spec.type
    if t in ("float", "int"):
        return _number(v, t == "int", spec, where, path)
    if t in ("floats", "ints"):
        if not isinstance(v, list) or not v:
            raise MarkcalError(f"{where} must be a non-empty list of numbers", path)
        return tuple(_number(x, t == "ints", spec, where, path) for x in v)
    if t == "bool":
        if not isinstance(v, bool):
            raise MarkcalError(f"{where} must be true or false (got {v!r})", path)
        return v
    if t == "str":
        if not isinstance(v, str):
            raise MarkcalError(f"{where} must be a string (got {v!r})", path)
        if spec.choices and v not in spec.choices:
            raise MarkcalError(f"{where} must be one of {', '.join(spec.choices)} (got {v!r})", path)
        return v
    raise ValueError(f"unknown schema type {t!r}")


def parse_config(d: dict, schema: dict, path) -> dict:
    """Check a loaded TOML dict against ``schema``; return section -> key -> value, defaults filled."""
    top = schema.get("", {})
    out = {sec: {k: spec.default for k, spec in keys.items()} for sec, keys in schema.items()}
    for name, v in d.items():
        if name in top:
            out[""][name] = _value(v, top[name], "", name, path)
            continue
        if name not in schema or name == "" or not isinstance(v, dict):
            if top and name not in schema:
                raise MarkcalError(f"unknown key '{name}' (known: {', '.join(sorted(top))})", path)
            raise MarkcalError(f"unknown section [{name}] (known: {', '.join(s for s in schema if s)})", path)
        keys = schema[name]
        for k, kv in v.items():
            if k not in keys:
                raise MarkcalError(f"unknown key '{k}' in [{name}] (known: {', '.join(sorted(keys))})", path)
            out[name][k] = _value(kv, keys[k], name, k, path)
    for sec, keys in schema.items():
        given = d if sec == "" else d.get(sec, {})
        for k, spec in keys.items():
            if spec.required and k not in given:
                raise MarkcalError(f"missing key '{k}'" + (f" in [{sec}]" if sec else ""), path)
    return out


def read_config(path, schema: dict, what: str = "config file") -> dict:
    """Load a TOML file and check it against ``schema`` (see :func:`parse_config`)."""
    path = os.fspath(path)
    return parse_config(load_toml(path, what), schema, path)


# ------------------------------------------------------------------ plate spec (scan)

_DEFAULT_PLATE = PlateSpec()
PLATE_SCHEMA = {
    "grid": {"rows": Key("int", required=True, min=3, max=1000), "cols": Key("int", required=True, min=3, max=1000),
             "pitch_mm": Key("float", required=True, positive=True, max=1000.0, unit="mm")},
    "fiducial": {"ring_radii_mm": Key("floats", _DEFAULT_PLATE.ring_radii_mm, positive=True, max=500.0, unit="mm"),
                 "orientation_mark": Key("ints", (), min=0)},
    "galvo": {"d_mm": Key("float", _DEFAULT_PLATE.d_mm, positive=True, max=10_000.0, unit="mm"),
              "e_mm": Key("float", _DEFAULT_PLATE.e_mm, min=0.0, max=10_000.0, unit="mm")},
    "correction": {"grid_step_mm": Key("float", _DEFAULT_PLATE.grid_step_mm, min=1e-3, unit="mm")},
    "plate": {"purpose": Key("str", _DEFAULT_PLATE.purpose, choices=PURPOSES)},
}


#: the most nodes of the correction grid a plate spec may ask for ([correction] grid_step_mm over the field)
MAX_CORRECTION_NODES = 1_000_000


def read_plate_spec(path) -> PlateSpec:
    """Read a PLATE.toml (``[grid] rows cols pitch_mm``, required; ``[fiducial] ring_radii_mm``,
    ``[galvo] d_mm e_mm``, ``[correction] grid_step_mm``, ``[plate] purpose`` (``calibration``: marked
    without the correction; ``validation``: marked through it); lengths in mm).

    ``[fiducial] orientation_mark = [row, col]`` declares a grid site left
    unmarked, which tells the plate's orientation at any angle. An empty file,
    or one cut before its ``[grid]`` keys, is refused (no silent defaults)."""
    path = os.fspath(path)
    data = read_bytes(path, "plate spec")                   # read once: the checks below and the TOML
    if not data.strip():
        raise MarkcalError("empty plate spec: needs [grid] rows, cols and pitch_mm", path)
    check_text_ends(data, path)
    c = parse_config(parse_toml(data, path), PLATE_SCHEMA, path)
    spec = PlateSpec(**c["grid"], **c["fiducial"], **c["galvo"], **c["correction"], **c["plate"])
    hx, hy = spec.half_extent_mm
    nodes = (2 * math.ceil(hx / spec.grid_step_mm) + 1) * (2 * math.ceil(hy / spec.grid_step_mm) + 1)
    if nodes > MAX_CORRECTION_NODES:
        raise MarkcalError(f"[correction] grid_step_mm = {spec.grid_step_mm:g} mm gives {nodes:,.0f} correction nodes "
                           f"over the ±{hx:g} x ±{hy:g} mm field; at most {MAX_CORRECTION_NODES:,} (a coarser step)",
                           path)
    if 2 * max(spec.ring_radii_mm) >= spec.pitch_mm:
        raise MarkcalError("ring_radii_mm must be positive and the rings must fit inside the pitch", path)
    mark = spec.orientation_mark
    if mark and (len(mark) != 2 or mark[0] >= spec.rows or mark[1] >= spec.cols):
        raise MarkcalError(f"[fiducial] orientation_mark must be [row, col] of a grid site (got {list(mark)})", path)
    return spec


# ------------------------------------------------------------------ selfcal setup

SELFCAL_SCHEMA = {"": {"n": Key("int", required=True, min=3, max=401),
                       "pitch_mm": Key("float", required=True, positive=True, max=10_000.0, unit="mm"),
                       "k": Key("int", 0, min=0, max=3600), "views": Key("ints", (0, 1, 2, 3), min=0, max=3)}}


def read_selfcal_setup(path):
    """Read a self-calibration ``setup.toml``: ``n``, ``pitch_mm``, ``k`` (0 = XY only), ``views``."""
    from markcal.stages.selfcal import SelfcalSetup

    path = os.fspath(path)
    c = read_config(path, SELFCAL_SCHEMA, "setup file")[""]
    try:
        return SelfcalSetup(**c)
    except MarkcalError as exc:
        raise exc.with_path(path) from None


# ------------------------------------------------------------------ indentation array spec

def _array_schema() -> dict:
    from markcal.stages.indent_single import INDENTERS
    return {"array": {"rows": Key("int", required=True, min=1), "cols": Key("int", required=True, min=1),
                      "pitch_um": Key("float", required=True, positive=True, unit="µm"),
                      "nominal_diameter_um": Key("float", required=True, positive=True, unit="µm")},
            "indenter": {"kind": Key("str", "vickers", choices=tuple(INDENTERS)),
                         "load_mN": Key("float", None, positive=True, unit="mN")}}


def read_array_spec(path):
    """Read ARRAY.toml: ``[array] rows cols pitch_um nominal_diameter_um`` (µm) and
    ``[indenter] kind load_mN`` (optional: Vickers; the load gives the hardness)."""
    from markcal.stages.indent_array import ArraySpec

    path = os.fspath(path)
    c = read_config(path, _array_schema(), "array spec")
    a, ind = c["array"], c["indenter"]
    spec = ArraySpec(**a, indenter=ind["kind"], load_mN=ind["load_mN"])
    if spec.nominal_diameter_um >= spec.pitch_um and spec.rows * spec.cols > 1:
        raise MarkcalError("nominal_diameter_um must be smaller than pitch_um", path)
    return spec


# ------------------------------------------------------------------ servo simulation config

def _servo_schema() -> dict:
    from markcal.stages.servo_control import PIDGains
    from markcal.stages.servo_cases import ServoConfig
    from markcal.stages.servo_plant import PlantParams
    from markcal.stages.servo_reading import NAMED_READINGS
    c, g, p = ServoConfig(), PIDGains(), PlantParams()

    def num(default, unit="", **limits):
        return Key("float", default, unit=unit, **limits)
    return {
        "plant": {f.name: num(getattr(p, f.name), positive=f.name == "ts_s") for f in fields(PlantParams)},
        "controller": {**{f.name: num(getattr(g, f.name)) for f in fields(PIDGains)},
                       "u_max_v": num(c.u_max_v, "V", positive=True), "friction_v": num(c.friction_v, "V", min=0.0)},
        "repetitive": {"tau": num(c.rc_tau), "kr": num(c.rc_kr), "m": Key("int", "auto", also=("auto",), min=0,
                                                                           max=100_000)},
        "step": {"strokes_mm": Key("floats", c.strokes_mm, unit="mm", min=-10_000.0, max=10_000.0),
                 "velocity_mm_s": num(c.velocity_mm_s, "mm/s", positive=True, max=1e6),
                 "acceleration_mm_s2": num(c.acceleration_mm_s2, "mm/s²", positive=True, max=1e9),
                 "jerk_mm_s3": num(c.jerk_mm_s3, "mm/s³", positive=True),
                 "dwell_s": num(c.dwell_s, "s", min=0.0, max=600.0)},
        "sine": {"amplitudes_mm": Key("floats", c.amplitudes_mm, unit="mm", positive=True, max=10_000.0),
                 "frequencies_hz": Key("floats", c.frequencies_hz, unit="Hz", min=1e-3, max=1e4),
                 "periods": num(c.periods, positive=True, max=1000.0)},
        "metrics": {"settle_band_um": num(c.settle_band_um, "µm", positive=True)},
        "model": {"reading": Key("str", "best", choices=tuple(NAMED_READINGS))},
    }


#: the most samples one simulated case may have (memory: ~10 float arrays per sample)
MAX_SERVO_SAMPLES = 20_000_000


def read_servo_config(path):
    """Read a servo CONFIG.toml: ``[plant] [controller] [repetitive] [step] [sine] [metrics] [model]``.

    Missing keys take the paper's values; ``[repetitive] m`` is a whole number of
    samples or ``"auto"``. The result is validated (physical, stable).
    """
    from markcal.stages.servo_control import PIDGains
    from markcal.stages.servo_plant import PlantParams
    from markcal.stages.servo_cases import ServoConfig, validate_config
    from markcal.stages.servo_reading import NAMED_READINGS

    path = os.fspath(path)
    c = read_config(path, _servo_schema(), "config file")
    gain_names = {f.name for f in fields(PIDGains)}
    ctrl, rep = c["controller"], c["repetitive"]
    cfg = ServoConfig(plant=replace(PlantParams(), **c["plant"]),
                      gains=replace(PIDGains(), **{k: v for k, v in ctrl.items() if k in gain_names}),
                      rc_tau=rep["tau"], rc_kr=rep["kr"], rc_m=None if rep["m"] == "auto" else rep["m"],
                      u_max_v=ctrl["u_max_v"], friction_v=ctrl["friction_v"],
                      reading=NAMED_READINGS[c["model"]["reading"]],
                      **c["step"], **c["sine"], **c["metrics"])
    try:
        validate_config(cfg)
    except MarkcalError as exc:
        raise exc.with_path(path) from None
    longest_s = max([max(cfg.periods, cfg.reading.cca_sine_periods) / f for f in cfg.frequencies_hz]
                    + [abs(x) / cfg.velocity_mm_s + cfg.velocity_mm_s / cfg.acceleration_mm_s2 + cfg.dwell_s
                       for x in cfg.strokes_mm])
    if longest_s / cfg.plant.ts_s > MAX_SERVO_SAMPLES:
        raise MarkcalError(f"the longest case would be {longest_s / cfg.plant.ts_s:.3g} samples ({longest_s:.4g} s at "
                           f"ts_s = {cfg.plant.ts_s:g} s); at most {MAX_SERVO_SAMPLES:,} (fewer periods, a higher "
                           "frequency or a shorter dwell)", path)
    return cfg


# ------------------------------------------------------------------ batch.toml

def read_batch_config(path, flow_options: dict, flow_tolerances: dict) -> dict:
    """Read batch.toml: ``[<flow>]`` option defaults and ``[<flow>.tolerance]`` limits.

    Parameters
    ----------
    path : path or None
        The file (None: the defaults).
    flow_options, flow_tolerances : dict
        Flow name -> default options / default ``max_<key>``/``min_<key>`` limits.

    Returns
    -------
    dict
        Flow name -> {"options": dict, "tolerances": dict}, defaults filled in.
    """
    cfg = {n: {"options": dict(o), "tolerances": dict(flow_tolerances.get(n, {}))} for n, o in flow_options.items()}
    if path is None:
        return cfg
    path = os.fspath(path)
    d = load_toml(path, "batch config")
    for flow, sec in d.items():
        if flow not in cfg or not isinstance(sec, dict):
            raise MarkcalError(f"unknown flow [{flow}] (known: {', '.join(cfg)})", path)
        tol = sec.get("tolerance", {})
        if not isinstance(tol, dict):
            raise MarkcalError(f"[{flow}.tolerance] must be a table", path)
        for tk, tv in tol.items():
            if not (tk.startswith("max_") or tk.startswith("min_")) or len(tk) < 5:
                raise MarkcalError(f"tolerance '{tk}' in [{flow}.tolerance] must be max_<key> or min_<key>", path)
            if isinstance(tv, bool) or not isinstance(tv, (int, float)) or not math.isfinite(tv):
                raise MarkcalError(f"tolerance '{tk}' in [{flow}.tolerance] must be a finite number", path)
            cfg[flow]["tolerances"][tk] = float(tv)
        for k, v in sec.items():
            if k == "tolerance":
                continue
            if k not in cfg[flow]["options"]:
                raise MarkcalError(f"unknown option '{k}' in [{flow}] (known: {', '.join(flow_options[flow])}, "
                                   "tolerance)", path)
            default = flow_options[flow][k]
            if type(v) is not type(default) and not (isinstance(default, float) and isinstance(v, int)
                                                     and not isinstance(v, bool)):
                raise MarkcalError(f"option '{k}' in [{flow}] must be {type(default).__name__}", path)
            if isinstance(v, float) and not math.isfinite(v):
                raise MarkcalError(f"option '{k}' in [{flow}] must be a finite number (got {v!r})", path)
            cfg[flow]["options"][k] = type(default)(v)
    return cfg
