"""Readings of paper 003's garbled or unit-less equations, and how well each reproduces Tables 1-2.

Paper 003 prints the identified plant (eq. 13), the PID law (eq. 16) and the
gains (sec. 5) without units, and eq. 13 is garbled in the source text
("G n ( s ) = 4683.3 s 2 + 18.85 s 2 + 61.68"). A :class:`Reading` fixes every
open choice; :func:`reading_params` turns it into the plant and gains in
markcal's internal units (positions mm, velocities mm/s, controller output V),
which is what the simulation runs on. :func:`baseline_rows` simulates the
paper's "without CCA" cases (Table 1: S-curve moves; Table 2: 10 mm sines) and
:func:`score_rows` measures the distance to the paper's rows.

The open choices:

* ``plant`` -- ``"a0"``: ``b0 / (s^2 + a1 s + a0)`` with a0 = 61.68 (eq. 12's
  form); ``"no_a0"``: ``b0 / (s^2 + a1 s)``, the trailing "2 + 61.68" read as
  typesetting debris (a linear motor on a guide has no spring to ground).
* ``b0_scale`` -- 1 (4683.3 as printed) or 0.1 (468.33: the numerator read with
  its decimal point one place left). Speculative; kept because it is the
  reading the tables ask for (see the README's readings table).
* ``plant_unit`` / ``ctrl_unit`` / ``ff_unit`` -- the length unit of the plant
  output (per V), of the error the PID gains multiply, and of the velocity the
  feed-forward Kf multiplies: ``"mm"`` or ``"um"``.
* ``integral`` -- ``"inv"``: ``(1/Ki) integral(e)`` as eq. 16 prints it;
  ``"gain"``: ``Ki integral(e)``.
* ``jerk_mm_s3`` -- jerk limit of the S-curve (``inf``: trapezoidal velocity).
* ``band`` -- settling band: ``"1um"``, ``"2um"``, ``"5um"``, ``"10um"`` or
  ``"2pct"`` (2 % of the stroke).
* ``origin`` -- settling time measured from the ``"end"`` of the reference
  move or from its ``"start"``.
* ``r0_unit`` -- the unit of the tracking differentiator's speed factor r0 =
  1,000,000: ``"um"`` (µm/s^2, i.e. 1 m/s^2: the TD reshapes the 10 m/s^2
  S-curve) or ``"mm"`` (1000 m/s^2: the TD passes the S-curve through).
  Only the composite controller uses it.
* ``cca_origin`` -- the composite controller's settling time counted from the
  end of its ``"own"`` reference (the TD output) or of the planned move ``"xd"``.
* ``sine_window`` -- MAE/STD over the ``"last"`` period of three (steady state)
  or over the ``"whole"`` record of ``sine_periods`` periods from rest.
* ``sine_phase`` -- the sine reference starts at 0 at full speed (``"sin"``,
  a velocity step for the stage at rest) or at its crest at rest (``"cos"``).
* ``pid_form`` -- ``"ts"``: ``integral(e dt)`` and ``de/dt`` (textbook);
  ``"sample"``: the discrete sum of e and the difference of e per sample, with
  no ``Ts`` (integral gain / Ts, derivative gain x Ts).
* ``d_filter_hz`` -- first-order low-pass on the derivative term (``inf``: none).
* ``u_max_v`` -- saturation of the plant input, V (``inf``: none; a dSPACE DAC
  gives +-10 V).
* ``feedforward`` -- what Kf multiplies: the reference ``"velocity"`` (paper),
  its ``"accel"`` (acceleration), or ``"none"``.
* ``ts_s`` -- controller sampling period, s (0: the plant's, i.e. the paper's 0.1 ms).
* ``cca_sine_periods`` -- when the composite controller's sine error is
  measured: 0 in the same window as the baseline's; N >= 2: over the N-th
  period from rest, after the repetitive controller has learnt for N - 1
  periods (the baseline row keeps its own window). Only the CCA uses it.

The encoder's 1 nm quantisation is not a choice: it changes MAE/STD by far less
than 0.01 µm at the paper's micrometre-scale errors.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from markcal.stages.errors import MarkcalError
from markcal.stages.servo_control import PIDGains
from markcal.stages.servo_plant import PlantParams, discretise
from markcal.stages.servo_profile import s_curve, sinusoid
from markcal.stages.servo_sim import BASELINE, simulate, tracking_metrics

__all__ = ["Reading", "BASE_READING", "DEFAULT_READING", "NAMED_READINGS", "reading_params", "settle_band_um",
           "settling_from", "reference_end_s", "sim_options", "sine_phase_deg", "baseline_rows", "baseline_rows_many", "score_rows", "PAPER_T1_BASE", "PAPER_T2_BASE", "UNIT_MM"]

#: length units (mm per unit)
UNIT_MM = {"mm": 1.0, "um": 1e-3}
#: paper Table 1 baseline ("without CCA"): stroke mm -> (overshoot µm, settling ms)
PAPER_T1_BASE = {10.0: (232.01, 85.13), 20.0: (232.33, 85.18), 30.0: (232.33, 85.23)}
#: paper Table 2 baseline, 10 mm amplitude: frequency Hz -> (MAE µm, STD µm)
PAPER_T2_BASE = {0.1: (2.4, 2.8), 0.2: (4.9, 5.6), 0.5: (13.1, 14.9), 1.0: (31.1, 35.2), 2.0: (91.3, 103.4)}
BANDS = ("1um", "2um", "5um", "10um", "2pct")


@dataclass(frozen=True)
class Reading:
    """One reading of the paper's open choices (see the module docstring)."""

    plant: str = "a0"
    b0_scale: float = 1.0
    plant_unit: str = "mm"
    ctrl_unit: str = "mm"
    ff_unit: str = "mm"
    integral: str = "inv"
    jerk_mm_s3: float = 1_000_000.0
    band: str = "1um"
    origin: str = "end"
    sine_window: str = "last"
    sine_periods: float = 3.0
    r0_unit: str = "um"
    cca_origin: str = "own"
    sine_phase: str = "sin"
    pid_form: str = "ts"
    d_filter_hz: float = math.inf
    u_max_v: float = math.inf
    feedforward: str = "velocity"
    ts_s: float = 0.0
    cca_sine_periods: float = 0.0

    def check(self) -> None:
        """Refuse an unknown choice, naming it."""
        allowed = {"plant": ("a0", "no_a0"), "plant_unit": tuple(UNIT_MM), "ctrl_unit": tuple(UNIT_MM),
                   "ff_unit": tuple(UNIT_MM), "integral": ("inv", "gain"), "band": BANDS,
                   "origin": ("end", "start"), "sine_window": ("last", "whole"), "r0_unit": tuple(UNIT_MM),
                   "cca_origin": ("own", "xd"), "sine_phase": ("sin", "cos"), "pid_form": ("ts", "sample"),
                   "feedforward": ("velocity", "accel", "none")}
        for k, ok in allowed.items():
            if getattr(self, k) not in ok:
                raise MarkcalError(f"reading {k} = {getattr(self, k)!r} unknown (one of {', '.join(ok)})")
        if not (self.b0_scale > 0 and math.isfinite(self.b0_scale)):
            raise MarkcalError(f"reading b0_scale must be positive (got {self.b0_scale})")
        if not self.jerk_mm_s3 > 0:
            raise MarkcalError(f"reading jerk_mm_s3 must be positive (got {self.jerk_mm_s3})")
        for k in ("d_filter_hz", "u_max_v"):
            if not getattr(self, k) > 0:
                raise MarkcalError(f"reading {k} must be positive (got {getattr(self, k)})")
        if not (0 <= self.ts_s <= 0.01):
            raise MarkcalError(f"reading ts_s must be in [0, 0.01] s (got {self.ts_s})")
        if not self.sine_periods >= 2:
            raise MarkcalError(f"reading sine_periods must be >= 2 (got {self.sine_periods})")
        if not (self.cca_sine_periods == 0 or (2 <= self.cca_sine_periods <= 100
                                               and self.cca_sine_periods == int(self.cca_sine_periods))):
            raise MarkcalError(f"reading cca_sine_periods must be 0 or a whole number in 2-100 "
                               f"(got {self.cca_sine_periods})")

    @property
    def label(self) -> str:
        """Short description for tables."""
        jerk = "trapezoid" if math.isinf(self.jerk_mm_s3) else f"jerk {self.jerk_mm_s3 / 1e3:g} m/s³"
        b0 = 4683.3 * self.b0_scale
        return (f"{'b0/(s²+a1·s+a0)' if self.plant == 'a0' else 'b0/(s²+a1·s)'}, b0 {b0:g}, plant "
                f"{self.plant_unit}/V, PID on {self.ctrl_unit}, Kf on {self.ff_unit}/s, "
                f"{'(1/Ki)∫e' if self.integral == 'inv' else 'Ki∫e'}, {jerk}, band {self.band} from the "
                f"{self.origin} of the move, sine MAE/STD over "
                f"{'the last of 3 periods' if self.sine_window == 'last' else f'{self.sine_periods:g} periods from rest'}"
                + self.extra_label)

    @property
    def extra_label(self) -> str:
        """The choices added in the second search, where they differ from the paper as printed."""
        out = []
        if self.sine_phase != "sin":
            out.append("sine from its crest at rest")
        if self.pid_form != "ts":
            out.append("PID per sample (no Ts)")
        if not math.isinf(self.d_filter_hz):
            out.append(f"D filtered at {self.d_filter_hz:g} Hz")
        if not math.isinf(self.u_max_v):
            out.append(f"input saturated at ±{self.u_max_v:g} V")
        if self.feedforward != "velocity":
            out.append(f"Kf on {'acceleration' if self.feedforward == 'accel' else 'nothing (no feed-forward)'}")
        if self.ts_s:
            out.append(f"Ts {self.ts_s * 1e3:g} ms")
        if self.cca_sine_periods:
            out.append(f"CCA sine error over period {self.cca_sine_periods:g} of {self.cca_sine_periods:g} "
                       "(after the repetitive controller has learnt)")
        return "".join(", " + o for o in out)


#: the reading that scores best against Tables 1-2 (benchmarks/servo_readings.py)
#: (ties within 0.002 broken towards the paper as printed: (1/Ki), mm throughout); the composite
#: controller's sine error is taken over the 8th period, after the repetitive controller has learnt
#: (``servo_readings.py --cca``: 5 of 5 STD reductions within a third of Table 2's; baseline rows unchanged)
BASE_READING = Reading(plant="no_a0", b0_scale=0.1, integral="inv", band="2um", origin="end",
                       sine_window="whole", sine_periods=2.0)
DEFAULT_READING = replace(BASE_READING, cca_sine_periods=8.0)

#: readings offered by name (``--reading NAME`` / ``[model] reading``)
NAMED_READINGS = {
    "best": DEFAULT_READING,
    "printed": Reading(),                                    # everything as printed, mm throughout
    "printed_ff_um": Reading(ff_unit="um"),                  # the best reading with b0 as printed
    "no_a0": Reading(plant="no_a0"),
    "plant_um": Reading(plant_unit="um"),
    "b0_468": Reading(b0_scale=0.1, band="2um"),
    # the best score of the second search (0.194; 15 of 16 numbers): the default with the plant input
    # clipped at +-20 V -- only the start-up of the sines clips, so its 2 Hz error is a spike, not a sine
    "sat20": replace(BASE_READING, u_max_v=20.0),
    # sines started at rest from their crest and measured over the last of 3 periods: baseline rows farther
    # from Table 2 (6/10), but the composite controller's STD reductions come within a third at 0.1-1 Hz
    "crest_steady": replace(BASE_READING, sine_phase="cos", sine_window="last"),
    # the previous default: the composite controller measured over the same 2 periods from rest as the baseline
    "rc_2periods": BASE_READING,
}


def reading_params(reading: Reading, gains: PIDGains = PIDGains(),
                   plant: PlantParams = PlantParams()) -> tuple[PlantParams, PIDGains]:
    """The plant and gains of ``reading`` in markcal's units (mm, mm/s, V).

    ``gains`` and ``plant`` hold the paper's numbers as printed; they are
    converted: plant gain times the plant unit, PID gains divided by the
    controller unit, Kf divided by the feed-forward unit, the integral taken
    as printed (``1/Ki``) or as a gain, ``phi`` in the controller unit, ``r0``
    in ``r0_unit``.
    """
    reading.check()
    up, uc, uf = (UNIT_MM[u] for u in (reading.plant_unit, reading.ctrl_unit, reading.ff_unit))
    p = replace(plant, b0=plant.b0 * reading.b0_scale * up, a0=plant.a0 if reading.plant == "a0" else 0.0,
                ts_s=reading.ts_s or plant.ts_s)
    ki_inv = (1.0 / gains.ki if reading.integral == "inv" else gains.ki) / uc
    kd = gains.kd / uc
    if reading.pid_form == "sample":          # sum of e and difference of e per sample: no Ts
        ki_inv, kd = ki_inv / p.ts_s, kd * p.ts_s
    kf = 0.0 if reading.feedforward == "none" else gains.kf / uf
    g = replace(gains, kf=kf, kp=gains.kp / uc, kd=kd,
                ki=(1.0 / ki_inv) if ki_inv > 0 else math.inf, phi_mm=gains.phi_mm * uc, r0=gains.r0 * UNIT_MM[reading.r0_unit])
    return p, g


def sim_options(reading: Reading, u_max_v: float = math.inf) -> dict:
    """Keyword arguments of :func:`simulate` that ``reading`` fixes (``u_max_v``: a config's own limit)."""
    return {"u_max_v": min(u_max_v, reading.u_max_v), "d_filter_hz": reading.d_filter_hz,
            "ff_order": {"velocity": 1, "accel": 2, "none": 0}[reading.feedforward]}


def sine_phase_deg(reading: Reading) -> float:
    """Phase of the sine reference under ``reading``, degrees."""
    return 0.0 if reading.sine_phase == "sin" else 90.0


def settle_band_um(band: str, stroke_mm: float) -> float:
    """Half width of the settling band, µm."""
    return 0.02 * abs(stroke_mm) * 1e3 if band == "2pct" else float(band[:-2])


def reference_end_s(t_s, ref_mm, tol_mm: float = 1e-7) -> float:
    """Time (s) from which ``ref_mm`` stays within ``tol_mm`` of its final value."""
    off = np.flatnonzero(np.abs(np.asarray(ref_mm) - ref_mm[-1]) > tol_mm)
    return float(t_s[0]) if off.size == 0 else float(t_s[min(off[-1] + 1, len(t_s) - 1)])


def settling_from(t_s, pos_mm, target_mm, t0_s, band_um) -> float:
    """Time from ``t0_s`` until ``|pos - target|`` stays within ``band_um`` (s); NaN if never.

    Only samples at or after ``t0_s`` count; ``t_s`` increasing (s), positions mm.
    """
    dev = np.abs(np.asarray(pos_mm) - target_mm) * 1e3
    after = np.asarray(t_s) >= t0_s - 1e-12
    outside = np.flatnonzero(after & (dev > band_um))
    if outside.size == 0:
        return 0.0
    if outside[-1] == len(t_s) - 1:
        return float("nan")
    return float(t_s[outside[-1] + 1] - t0_s)


def baseline_rows(reading: Reading, strokes_mm=(10.0, 20.0, 30.0), freqs_hz=(0.1, 0.2, 0.5, 1.0, 2.0),
                  amplitude_mm: float = 10.0, dwell_s: float = 0.4, gains: PIDGains = PIDGains(),
                  plant: PlantParams = PlantParams()) -> dict:
    """Simulate the paper's baseline ("without CCA") cases under ``reading``.

    Returns
    -------
    dict
        ``{"t1": {stroke: (overshoot µm, settling ms)}, "t2": {freq: (MAE µm, STD µm)}}``;
        NaN where the loop does not settle or diverges.
    """
    return baseline_rows_many(reading, [reading], strokes_mm, freqs_hz, amplitude_mm, dwell_s, gains, plant)[0]


def baseline_rows_many(reading: Reading, variants, strokes_mm=(10.0, 20.0, 30.0),
                       freqs_hz=(0.1, 0.2, 0.5, 1.0, 2.0), amplitude_mm: float = 10.0, dwell_s: float = 0.4,
                       gains: PIDGains = PIDGains(), plant: PlantParams = PlantParams()) -> list:
    """:func:`baseline_rows` for readings that differ from ``reading`` only in how they measure.

    ``variants`` are readings whose ``band``, ``origin``, ``sine_window`` and
    ``sine_periods`` may differ from ``reading``'s (everything else is taken
    from ``reading``): each case is simulated once, over the longest record any
    variant needs (a shorter record from rest is a prefix of a longer one), and
    measured for every variant. Returns one rows dict per variant.
    """
    p, g = reading_params(reading, gains, plant)
    dp = discretise(p)
    opts = sim_options(reading)
    out = [{"t1": {}, "t2": {}} for _ in variants]
    with np.errstate(all="ignore"):
        for stroke in strokes_mm:
            prof = s_curve(stroke, 100.0, 10_000.0, reading.jerk_mm_s3, p.ts_s, dwell_s)
            r = simulate(dp, g, prof, BASELINE, **opts)
            dev_um = (r.pos_mm - prof.x_mm[-1]) * 1e3 * np.sign(stroke)
            over = float(max(0.0, np.max(dev_um))) if np.all(np.isfinite(dev_um)) else float("nan")
            for v, rows in zip(variants, out):
                t0 = prof.t_end_s if v.origin == "end" else 0.0
                band = settle_band_um(v.band, stroke)
                st = settling_from(prof.t_s, r.pos_mm, prof.x_mm[-1], t0, band) if np.isfinite(over) else float("nan")
                rows["t1"][float(stroke)] = (over, st * 1e3)
        longest = max(3.0 if v.sine_window == "last" else v.sine_periods for v in variants) if variants else 3.0
        for f in freqs_hz:
            prof = sinusoid(amplitude_mm, f, longest, p.ts_s, sine_phase_deg(reading))
            r = simulate(dp, g, prof, BASELINE, **opts)
            n1 = int(round(1.0 / f / p.ts_s))
            for v, rows in zip(variants, out):
                n = int(round((3.0 if v.sine_window == "last" else v.sine_periods) / f / p.ts_s)) + 1
                err = r.err_mm[n - n1:n] if v.sine_window == "last" else r.err_mm[:n]
                mae, std = tracking_metrics(err) if np.all(np.isfinite(err)) else (float("nan"), float("nan"))
                rows["t2"][float(f)] = (mae, std)
    return out


def score_rows(rows: dict) -> dict:
    """Distance of simulated baseline rows to the paper's Tables 1-2.

    ``score`` is the RMS of ``ln(ours / paper)`` with the two tables weighted
    equally (0 is perfect, 0.18 ~ 20 % off everywhere); ``t1_within`` counts
    Table 1 numbers within 20 %, ``t2_within`` Table 2 numbers within 30 %
    (the issue's goals). A missing number (no settling, divergence) counts as
    a factor e^3 off.
    """
    def logs(ours: dict, paper: dict):
        lg, rel = [], []
        for k, pv in paper.items():
            ov = ours.get(k, (float("nan"),) * len(pv))
            for o, q in zip(ov, pv):
                good = bool(np.isfinite(o) and o > 0)
                lg.append(abs(math.log(o / q)) if good else 3.0)
                rel.append(abs(o / q - 1.0) if good else math.inf)
        return np.array(lg), np.array(rel)
    l1, r1 = logs(rows["t1"], PAPER_T1_BASE)
    l2, r2 = logs(rows["t2"], PAPER_T2_BASE)
    score = math.sqrt(0.5 * float(np.mean(l1 ** 2)) + 0.5 * float(np.mean(l2 ** 2)))
    return {"score": score, "t1_within": int(np.sum(r1 <= 0.2)), "t1_n": len(r1),
            "t2_within": int(np.sum(r2 <= 0.3)), "t2_n": len(r2)}
