"""The indents flow's AFM height maps: a channel levelled (from the far field where an imprint fills the map, then
to the surface beyond the corners), its imprints detected and measured, on both scan directions where the file holds
them (:func:`afm_map`). :mod:`markcal.pipeline.flows.indents` calls it for every AFM map.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from markcal.stages import indent as ind
from markcal.stages import indent_select as sel
from markcal.stages.errors import MarkcalError
from markcal.stages.image_io import Image
from markcal.stages.indent_level import corner_level, level_map, level_single
from markcal.stages.indent_single import facet_apex_nm, measure_single
from markcal.stages.indent_unflatten import detect_line_flatten, unflatten_lines
from markcal.stages.scan_lag import (FLOOR_MISSED_PX, SHIFT_MIN_PAIRS, floor_separations_px, imprints_shift_px,
                                     pair_directions, scan_lag, unlag)

__all__ = ["afm_map", "BOTH_DIRECTIONS_MAX_IMPRINTS", "BOTH_DIRECTIONS_MAX_PIXELS"]


def afm_map(img: Image, spec, say, info: dict) -> tuple:
    """Measure the imprints of an AFM map. Returns the imprints (None where a measurement failed), the depth an
    imprint must pass (nm, 8 noise levels, at least 5 nm) and the map to show (levelled, moved back by the z loop's
    lag); ``info`` takes the levelling's figures."""
    name = os.path.basename(img.source)
    px = img.pixel_um
    if img.meta.get("blank_rows"):
        say(f"{name}: {img.meta['blank_rows']} constant scan lines (not scanned) left out")
    say(f"{name}: levelling {img.shape[0]} x {img.shape[1]} AFM map")
    lv, imps = _afm_channel(img.data, px, spec, say, name, info)
    floor = max(5.0, 8 * lv.noise_nm)
    image = lv.z_nm
    if lag_px := _scan_lag_px(img, say, name, info):
        # every slope lies along the fast axis from the surface, the trace's one way and the retrace's the other:
        # the imprints measured on the retrace too and their corners averaged where that is done, else moved back
        # by the lag; the map shown moved back by the lag
        if (other := _other_direction(img, imps, floor, spec)) is not None:
            _floor_reached(imps, other, lag_px * px, px, say, name, info)
            imps, both = pair_directions(imps, other, lag_px * px, px)
            info["n_both_directions"] = both
            say(f"{name}: {both} of {sum(m is not None for m in imps)} imprint(s) measured on the retrace too: "
                "centres and corners the means of both scan directions")
        else:
            if (shift := _imprints_shift_px(img, imps, floor, lag_px)) is not None:
                info["imprint_shift_px"] = shift
                say(f"{name}: the imprints lie {shift:+.2f} px along the fast axis (trace against retrace, "
                    f"{IMPRINT_SHIFT_SAMPLE} or fewer of them): that taken out, not the ramp lag")
                lag_px = shift
            imps = [m if m is None else m.moved(-lag_px * px) for m in imps]
            say(f"{name}: positions moved back by the lag, {-lag_px:+.2f} px")
        image = unlag(image, lag_px)
    info.update(noise_nm=lv.noise_nm, tilt_deg=lv.tilt_deg, bow_nm=lv.bow_nm, n_scar_px=lv.n_scar_px)
    return imps, floor, image


def _floor_reached(trace, retrace, lag_um, px, say, name, info):
    """Whether both scan directions reached the imprints' floors (``info["floor_separation_px"]``, the largest of
    :func:`markcal.stages.scan_lag.floor_separations_px`; ``info["floor_missed"]``: it is
    :data:`~markcal.stages.scan_lag.FLOOR_MISSED_PX` or more, the depths are lower bounds)."""
    if not (seps := floor_separations_px(trace, retrace, lag_um, px)):
        return
    info["floor_separation_px"] = sep = max(seps)
    info["floor_missed"] = sep >= FLOOR_MISSED_PX
    if info["floor_missed"]:
        say(f"{name}: the trace's floor lies {sep:.1f} px right of the retrace's beyond the lag: the tip fell slower "
            "than the facets (scan too fast for the z loop) and reached the floor on neither, depths are lower "
            "bounds")


def _afm_imprint(lv, px, r, c, rad, local_level=True, plateau=None):
    """One AFM imprint: the model-free measurement, and the facet model where it is used.

    A large imprint (``LARGE_IMPRINT_PX``) takes everything from the model-free measurement;
    its ``apex_depth_nm`` comes from closed-form plane fits per facet instead of the (slow)
    facet model. ``local_level``: corners on the surface just beyond them; ``plateau``: the pixels of a floor
    clipped by the scanner's Z range (``measure_single``).
    """
    single = measure_single(lv.z_nm, px, lv.noise_nm, r, c, rad, local_level=local_level, plateau=plateau)
    if single is not None and single.d_um / px >= sel.LARGE_IMPRINT_PX:
        m = sel.merge_afm(None, single, px)
        return dataclasses.replace(m, apex_depth_nm=facet_apex_nm(lv.z_nm, px, single))
    return sel.merge_afm(ind.measure_afm(lv.z_nm, px, r, c, rad, lv.noise_nm, lv.mask, lv.scars), single, px)


def _afm_imprints(lv, px, local_level=True, plateau=None, at=None) -> list:
    """Every pit of a levelled map, measured (None where the measurement failed); ``at``: imprints measured
    before, only the pits whose centres lie within one of them measured (the same imprints measured again)."""
    pits = ind.detect_pits(lv.z_nm, lv.noise_nm, px)
    if at is not None:
        pits = [(r, c, rad) for r, c, rad in pits
                if any(np.hypot(c - m.x_um / px, r - m.y_um / px) <= 0.5 * m.d_um / px for m in at)]
    return [_afm_imprint(lv, px, r, c, rad, local_level, plateau) for r, c, rad in pits]


def _level_at_corners(heights, lv, px, imps, floor, say, name, info, plateau=None) -> tuple:
    """Where the surface beyond the imprints' corners lies clearly below the far field's level (pile-up's tails
    under the far field, :func:`markcal.stages.indent_level.corner_level`): the map levelled again with planes
    only, its zero put on that surface, and its imprints measured again. Returns the levelled map and the
    imprints, measured again in any case with the corners on the surface just beyond them (the first
    measurement, whose corners place the strips, takes them at 0). Only the pits within the imprints found are
    measured again: the others were no imprints, and a level a few nm off does not make them one (feedback seeds
    1-180, ruled 1-140: the same imprints), while measuring them again took 0.2 s on a 1024 x 1024 map."""
    found = sel.accept_imprints(imps, px, floor)
    if not found:
        return lv, imps
    corners, centres = [m.corners_um / px for m in found], [(m.x_um / px, m.y_um / px) for m in found]
    diagonals = [m.d_um / px for m in found]
    lev = corner_level(lv.z_nm, corners, centres, diagonals, lv.noise_nm)
    w = lev.weight(lv.noise_nm)
    info["corner_level_nm"] = lev.offset_nm
    info["levelled_to_corners"] = w > 0
    info["corner_level_weight"] = w
    if w == 0:
        return lv, _afm_imprints(lv, px, plateau=plateau, at=found)
    say(f"{name}: the surface beyond the corners lies {lev.offset_nm:+.1f} nm under the far field's level "
        "(pile-up's tails): levelled to it" + ("" if w == 1 else f" by {w:.0%} (the strips scatter nearly as much)"))
    # planes only (a bow through the tails bends under the imprint), then the strips' level taken as zero; where
    # the strips tell it less clearly, part way between that and the far field's level
    lv_far = lv
    lv = level_single(heights, px, fit_bow=False)
    lev = corner_level(lv.z_nm, corners, centres, diagonals, lv.noise_nm)
    lv = dataclasses.replace(lv, z_nm=w * (lv.z_nm - lev.offset_nm) + (1.0 - w) * lv_far.z_nm)
    return lv, _afm_imprints(lv, px, plateau=plateau, at=found)


def _scan_lag_px(img: Image, say, name, info) -> float:
    """The z loop's lag along the fast axis (px), where the file holds the channel's other scan direction too
    (half the two directions' offset; ``stages/scan_lag``); 0 without it or where the two do not match."""
    if img.other_direction is None:
        return 0.0
    lag = scan_lag(img.data, img.other_direction)
    if not lag.usable:
        say(f"{name}: the channel's two scan directions do not match (slopes' correlation {lag.correlation:.2f}, "
            f"offset {2 * lag.lag_px:+.2f} px): positions keep the z loop's lag")
        return 0.0
    info["scan_lag_px"] = lag.lag_px
    say(f"{name}: trace and retrace {abs(2 * lag.lag_px):.2f} px apart along the fast axis (the z loop's lag, "
        f"{lag.lag_px:+.2f} px)")
    return lag.lag_px


def _refuse_inverted(lv, px):
    """Raise when a levelled map's heights look inverted: more stands up than lies down, and most of what stands
    up is imprints turned over (pile-up lobes turned over are pits, which had been reported as imprints). The
    imprints of the ruled renderer's maps negated (seeds 1-12) hold 100-104 % of what stands up; on the real
    map of raised circles (circles.nid) three circles turned over pass for imprints and hold 2.2 %."""
    up, down = sel.raised_and_sunk_um3(lv.z_nm, lv.noise_nm, px)
    if up <= down:
        return
    turned = sel.accept_imprints(_afm_imprints(dataclasses.replace(lv, z_nm=-lv.z_nm), px), px,
                                 max(5.0, 8 * lv.noise_nm))
    # a pyramid's volume: a third of its base times its height
    if sum(np.nan_to_num(m.area_um2) * m.depth_nm * 1e-3 / 3 for m in turned) >= 0.5 * up:
        n = len(turned)
        raise MarkcalError(f"the map holds {n} imprint{'s' if n > 1 else ''} standing up ({up:.3g} µm³ above its "
                           f"surface, {down:.3g} µm³ below): are its heights inverted (the channel's sign)?")


#: the most imprints, and pixels, a map without an array spec may hold for its other scan direction to be measured
#: too. Each direction costs as much: a 512 x 512 map of 25 imprints took 0.66 s with both (goal 0.5 s), a
#: 1024 x 1024 map of one imprint 2.1 s (goal 2 s; 1.2 s one way; 3.7-4.0 s and 1.9 s before session 27)
BOTH_DIRECTIONS_MAX_IMPRINTS = 4
BOTH_DIRECTIONS_MAX_PIXELS = 512 * 512


#: imprints (the nearest the map's middle) measured on the retrace too, where the retrace is not measured whole, to
#: tell how far the imprints themselves lie along the fast axis; 0: the ramp lag is taken out
IMPRINT_SHIFT_SAMPLE = 5


def _imprints_shift_px(img: Image, imps: list, floor: float, lag_px: float) -> float | None:
    """How far the trace's imprints lie along the fast axis (px), where the retrace is not measured whole: up to
    :data:`IMPRINT_SHIFT_SAMPLE` imprints nearest the map's middle measured on the retrace too (the part of it round
    them levelled as the trace is, only those pits measured), :func:`markcal.stages.scan_lag.imprints_shift_px`;
    None where that cannot be told."""
    px = img.pixel_um
    found = sel.accept_imprints(imps, px, floor, size_window_um=(0.0, np.inf))     # an array's shallow ones too
    if IMPRINT_SHIFT_SAMPLE == 0 or len(found) < SHIFT_MIN_PAIRS:
        return None
    mid = np.array(img.shape[::-1]) * px / 2
    pick = sorted(found, key=lambda m: float(np.hypot(m.x_um - mid[0], m.y_um - mid[1])))[:IMPRINT_SHIFT_SAMPLE]
    # only the part of the retrace round them, with two of their diagonals of surface beyond their corners
    corners = np.vstack([np.asarray(m.corners_um, float) for m in pick]) / px
    margin = 2.0 * max(m.d_um for m in pick) / px + abs(2 * lag_px) + 8
    (c0, r0), (c1, r1) = np.floor(corners.min(axis=0) - margin), np.ceil(corners.max(axis=0) + margin)
    r0, c0 = int(max(r0, 0)), int(max(c0, 0))
    r1, c1 = int(min(r1, img.shape[0])), int(min(c1, img.shape[1]))
    try:
        _heights, lv, _filled, _plateau = _levelled(img.other_direction[r0:r1, c0:c1], px, lambda m: None, "", {})
    except MarkcalError:
        return None
    here = [m.moved(-c0 * px, -r0 * px) for m in pick]
    return imprints_shift_px(here, _afm_imprints(lv, px, at=here), lag_px * px, px)


def _other_direction(img: Image, imps: list, floor: float, spec) -> list | None:
    """The imprints of the channel's other scan direction (:func:`_afm_channel`), measured where the file holds
    it, no array spec is given (an array's positions are registered to its lattice, which takes a shift of the
    whole map) and the map holds one to :data:`BOTH_DIRECTIONS_MAX_IMPRINTS` imprints and at most
    :data:`BOTH_DIRECTIONS_MAX_PIXELS` pixels; None otherwise, or where its measurement fails."""
    if (spec is not None or img.other_direction is None or img.data.size > BOTH_DIRECTIONS_MAX_PIXELS
            or not 1 <= len(sel.accept_imprints(imps, img.pixel_um, floor)) <= BOTH_DIRECTIONS_MAX_IMPRINTS):
        return None
    try:
        return _afm_channel(img.other_direction, img.pixel_um, spec, lambda m: None, "", {})[1]
    except MarkcalError:
        return None


def _afm_channel(raw, px, spec, say, name, info) -> tuple:
    """One AFM height channel levelled (:func:`_levelled`, then to the surface beyond the corners where an imprint
    fills the map) and its imprints measured. Returns the levelled map and the imprints (None where the
    measurement failed)."""
    heights, lv, filled, plateau = _levelled(raw, px, say, name, info)
    _refuse_inverted(lv, px)
    say(f"{name}: detecting and fitting imprints")
    # where the level beyond the corners may follow, the corners that place its strips are taken at 0
    imps = _afm_imprints(lv, px, local_level=not (spec is None and filled), plateau=plateau)
    if spec is None and filled:
        lv, imps = _level_at_corners(heights, lv, px, imps, max(5.0, 8 * lv.noise_nm), say, name, info, plateau)
    return lv, imps


def _levelled(raw, px, say, name, info) -> tuple:
    """One AFM height channel levelled: the line flatten undone, the clipped floor found, the map levelled (from
    the far field only where an imprint fills it). Returns the heights (flatten undone),
    the levelled map, whether an imprint fills it and the clipped floor's pixels (None: not clipped)."""
    heights = raw
    if (flat := detect_line_flatten(heights)) is not None:
        # flattened line by line before export, imprint and all: each line's fit taken from its far field
        say(f"{name}: flattened line by line ({flat.describe()}): lines' fits taken again from the far field")
        undone = unflatten_lines(heights, flat)
        heights = undone.z_nm
        info["line_flatten"] = flat.describe()
        info["line_flatten_short_lines"] = undone.n_short_lines
        # 5 % of the lines or more: every flattened ruled seed that misses a goal, one of the nine that meet them
        info["line_flatten_uncertain"] = undone.n_short_lines >= 0.05 * undone.n_lines
        if info["line_flatten_uncertain"]:
            say(f"{name}: {undone.n_short_lines} of {undone.n_lines} lines have under 15 % of their length on "
                "the far field (pile-up or the imprint reaches their ends): their level is uncertain, so are "
                "the depth and area")
    plateau = sel.clipped_floor(raw)             # the cut: flat in the raw heights only, tilted once levelled
    if n_clip := 0 if plateau is None else int(plateau.sum()):
        # the Z range's end: the floor is cut flat, the depth a lower bound
        say(f"{name}: {n_clip} pixels hold the map's lowest height exactly: its floor is clipped (the scanner's "
            "Z range), depths are lower bounds")
    info["floor_clipped_px"] = n_clip
    lv, filled = level_map(heights, px)         # an imprint filling much of the field: from the far field only
    return heights, lv, filled, plateau
