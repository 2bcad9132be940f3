"""Levelling an AFM map whose one imprint may fill most of the field (issue 20).

:func:`level_single`: a robust plane from the border ring (and the scanner's bow from it where the ring
is clearly bowed), then, iterated, the features masked, plane + quadratic bow fitted to the rest, each
row's offset from its far-field pixels, scars patched. Nothing is taken from inside the imprint.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .cv_filters import dilate_square, gaussian, grey_close
from .indent_geometry import robust_plane
from .level import Levelled, _remove_scars, _row_nanmedian, level_afm, noise_nm, poly_surface

__all__ = ["CornerLevel", "corner_level", "in_cracks", "level_map", "level_single"]

TRIM_SPREADS = 3.0          # a round's surface refitted without the far-field pixels this many spreads off it
RING_BOW_MIN_NM = 10.0      # the ring's robust spread about its plane above which its bow is fitted first
#: share of the map that the largest feature :func:`markcal.stages.level.level_afm` masks covers, above which an
#: imprint fills the field. Measured (session 27): maps of one imprint (feedback 1-40, ruled 1-20, ours 2000-2009)
#: 0.96-0.98; the real grating, circles and Bruker maps 1.00, 0.99 and 0.41; arrays 0.01, dense ones too (3 µm
#: imprints at a 4.5-8 µm pitch, 2 µm at 3.5 µm), though those mask 13-45 % of the field in all. Until session 27 the whole mask's
#: share decided, and the dense arrays over 0.3 were levelled as one imprint: centres 6-28 nm RMS, diameters 7-32 nm
#: RMS, against 1-4 nm for those under it
FILLED_SHARE = 0.3


def level_map(z_nm: np.ndarray, pixel_um: float) -> tuple[Levelled, bool]:
    """Level an AFM map: :func:`markcal.stages.level.level_afm`, or :func:`level_single` where an imprint fills
    the field (its feature, the largest ``level_afm`` masks, covers ``FILLED_SHARE`` of it). Returns the levelled
    map and whether it was filled.

    (Telling from the map binned 2 x 2 first was tried: 0.2 s less on a 1024 x 1024 map, but a dense array binned
    can be masked whole, 83 %, as a map of one imprint is.)
    """
    lv = level_afm(z_nm, pixel_um)
    if _largest_share(lv) > FILLED_SHARE:
        return level_single(z_nm, pixel_um), True
    return lv, False


def _largest_share(lv: Levelled) -> float:
    """Share of the map the largest connected feature of ``lv.mask`` covers (0 without features)."""
    lab, n = ndimage.label(lv.mask)
    return float(np.bincount(lab.ravel())[1:].max()) / lv.mask.size if n else 0.0


def level_single(z_nm: np.ndarray, pixel_um: float, n_iter: int = 4, fit_bow: bool = True) -> Levelled:
    """Level a map whose imprint may fill most of the field, from the far field only.

    The first plane comes from the border ring (robust: the corners of the imprint and pile-up are
    rejected), and the ring's bow where it is clearly bowed (:func:`_ring_bow`); then, iterated, the
    features (more than 5 noise levels off after smoothing, grown by 3 px) are masked, a plane +
    quadratic bow is fitted to the rest, each row's offset is the median of its far-field pixels (rows
    with under a tenth of their width as far field, or split by a scar, interpolated from their
    neighbours) and scars are patched.

    Parameters
    ----------
    z_nm : ndarray (rows, cols)
        Raw heights (nm), rows along the slow scan axis.
    pixel_um : float
        Pixel size (µm), for the tilt angle.
    fit_bow : bool
        Whether the scanner's bow is fitted (the ring's and each round's quadratic); without it, planes only.
        Where the far field lies on the pile-up's tails, a quadratic through them bends 20-50 nm under the
        imprint (:func:`corner_level`).
    """
    valid = np.isfinite(z_nm)
    z = np.where(valid, z_nm - np.nanmedian(z_nm), 0.0).astype(np.float64)
    ny, nx = z.shape
    rr, cc = np.mgrid[0:ny, 0:nx]
    ring = valid & ((rr < 3) | (rr >= ny - 3) | (cc < 3) | (cc >= nx - 3))
    coef = robust_plane(cc[ring].astype(float), rr[ring].astype(float), z[ring], n_iter=8)
    plane = coef[0] * cc + coef[1] * rr + coef[2]
    tilt_deg = float(np.degrees(np.arctan(np.hypot(coef[0], coef[1]) / (1000.0 * pixel_um))))
    z -= plane
    ring_bow = _ring_bow(z, ring) if fit_bow else np.zeros_like(z)
    z -= ring_bow
    keep = ring.copy()
    sigma, bow = 1.0, 0.0
    scars = np.zeros(z.shape, bool)
    # a row's offset needs a tenth of the row as far field: a few pixels at the row's end, on the tail of
    # a pile-up lobe below the mask's threshold, define their own zero and hide the lobe (13 nm on a
    # 1 µm imprint filling 80 % of the field); rows with less are interpolated from their neighbours
    min_row = max(3, nx // 10)
    # the bow (``surf_total``) accumulates over the rounds, the line offsets and the scars are found afresh
    # every round from the map with only the bow removed: offsets interpolated over rows without far field
    # in an early round (its mask still holding pile-up tails) would otherwise stay in those rows for
    # good, 6-8 nm under a 1 µm imprint filling 80 % of the field; and a row offset that a scar pulled
    # off in one round makes the rest of the row look like a scar, whose patch would replace the floor
    # of an imprint the row runs through with its neighbours' mean
    z0 = z.copy()
    surf_total = np.zeros_like(z)
    for it in range(n_iter):
        sigma = noise_nm(z, keep)
        if not np.isfinite(sigma) or sigma <= 0:
            sigma = 1.0
        if it == 0:
            feat, off0 = _first_features(z, keep, valid, sigma)
        else:
            zs = gaussian(z, 1.0)
            # grown by 3 px: a 7 x 7 square
            feat = dilate_square(np.abs(zs - np.median(zs[keep])) > 5 * sigma, 7)
        prev, keep = keep, valid & ~feat
        if keep.sum() < 0.02 * valid.sum():
            # nearly all masked: the first round's ring, later the last round's far field (a bow fitted to
            # the ring alone, lobes and imprint corners in it, had sent a 4 µm imprint 150 nm down)
            keep = valid & ring if it == 0 else prev
        # the first round's surface under the side strips' line offsets when they made its mask: offsets of
        # hundreds of nm (a scan flattened line by line, imprint and all) bent a quadratic 240 nm
        degree = _bow_degree(keep) if fit_bow else min(_bow_degree(keep), 1)
        surf = _trimmed_surface(z - off0[:, None] if it == 0 else z, keep, degree, sigma)
        if it == 0:
            bow = float(np.ptp((surf + ring_bow)[keep])) if keep.any() else 0.0
        surf_total += surf
        za = z0 - surf_total
        # line offsets from the far field of each row, the scars found so far left out
        use = keep & ~scars
        cnt = use.sum(axis=1)
        # (a sort per row: numpy's nanmedian along an axis goes row by row in Python, 0.17 s on a 1024 x 1024 map)
        off = _row_nanmedian(za, use) if cnt.max() >= min_row else np.full(ny, np.nan)
        off[cnt < min_row] = np.nan
        # a row whose far field splits into two levels, one of them its neighbours' (a scar over most of
        # it), has no single offset: the median would follow the scar and shift the rest of the row, the
        # imprint's floor included; such a row takes its neighbours' offset and the scar is patched below
        tol = max(4.0 * sigma, 2.0)
        padded = np.pad(off, 3, constant_values=np.nan)
        around = np.stack([padded[3 + k:3 + k + ny] for k in (-3, -2, -1, 1, 2, 3)], axis=1)
        has = np.isfinite(around)
        nb = np.where(has.any(axis=1), _row_nanmedian(np.where(has, around, 0.0), has), np.nan)   # NaN: none
        # two levels: pixels at the neighbours' level that are not at the row's own (a row only a little off its
        # neighbours is the lines' own jitter, 0.5-5 nm on the feedback renderer, its pixels at its own level; counted
        # within tol of the neighbours' alone, 0.05 nm more noise had moved its offset to theirs, 5-15 nm, on most seeds)
        at_nb = ((np.abs(za - nb[:, None]) <= tol) & (np.abs(za - off[:, None]) > tol) & use).sum(axis=1)
        split = (np.abs(off - nb) > tol) & (at_nb >= np.maximum(0.15 * cnt, 8))
        off[split] = np.nan
        good = np.isfinite(off)
        if good.sum() >= 2:
            off = np.interp(np.arange(ny), np.flatnonzero(good), off[good])
            za = za - off[:, None]
        z, scars = _remove_scars(za, keep, sigma)
    sigma = noise_nm(z, keep)
    z -= np.median(z[keep]) if keep.any() else 0.0
    z[~valid] = np.nan
    return Levelled(z_nm=z, mask=~keep, noise_nm=float(sigma), tilt_deg=tilt_deg, bow_nm=bow, scars=scars)


def _trimmed_surface(z, keep, degree, sigma, n_trim=3):
    """The far-field surface of one round, refitted (up to ``n_trim`` times) without the pixels of ``keep`` more
    than ``TRIM_SPREADS`` robust spreads (at least the pixel noise ``sigma``) off it.

    The first round's far field holds the pile-up's tails under its 20 nm threshold: a quadratic through them
    left the true far field of an imprint filling 84 % of the field 5-40 nm off, over 5 noise levels, so the
    next round masked 95 % of the field and levelled from what was left (feedback seed 6 without debris:
    d +52 %; +1.65 % with the refit). Stops when a refit would keep under half of ``keep``.
    """
    use = keep
    for _ in range(n_trim + 1):
        surf = poly_surface(z, use, degree, step=1 if use.sum() < 3000 else 2)
        res = (z - surf)[keep]
        med = np.median(res)
        spread = max(1.4826 * np.median(np.abs(res - med)), sigma)
        nxt = keep & (np.abs(z - surf - med) <= TRIM_SPREADS * spread)
        if nxt.sum() < 0.5 * keep.sum() or np.array_equal(nxt, use):
            break
        use = nxt
    return surf


def _bow_degree(keep):
    """Degree of the surface a round fits to the far field ``keep``: 2 where it surrounds the imprint.

    A quadratic through far field in a few corners of the map extrapolates under an imprint that fills
    most of it (100-150 nm on a 4 µm imprint at 85 % fill); a plane there, an offset where the far
    field lies in one part of the map only. Coverage: cells of a 4 x 4 grid holding 1 % far field.
    """
    ny, nx = keep.shape
    cells = keep[:ny // 4 * 4, :nx // 4 * 4].reshape(4, ny // 4, 4, nx // 4).mean(axis=(1, 3)) >= 0.01
    rows, cols = cells.any(axis=1).sum(), cells.any(axis=0).sum()
    if cells.sum() >= 10:
        return 2
    return 1 if rows >= 3 and cols >= 3 else 0


def _first_features(z, keep, valid, sigma):
    """The first round's feature mask: clear features only (line offsets are still in), grown by 3 px,
    and the line offsets (nm per row) it was found under.

    The rows' drift (tens of nm over a scan) can stand above the threshold over most of the field; the
    map with each row's side-strip median removed is then masked instead, when that leaves more of the
    field unmasked (where pile-up lobes reach the sides, removing the strips' level marks more).
    """
    thr = max(5 * sigma, 20.0)
    found = []
    for off in (np.zeros(z.shape[0]), _side_strip_offsets(z, valid)):
        zs = gaussian(z - off[:, None], 1.0)
        found.append((dilate_square(np.abs(zs - np.median(zs[keep])) > thr, 7), off))
    return min(found, key=lambda f: int(f[0].sum()))


def _side_strip_offsets(z, valid):
    """Each row's median over its two side strips (a tenth of the width each; nm), 0 where a row has none there.

    A first guess of the line offsets that needs no mask: the imprint rarely covers most of both ends
    of a row, and rows where it does are corrected by the far-field offsets of the later rounds.
    """
    w = max(3, z.shape[1] // 10)
    off = _row_nanmedian(np.concatenate([z[:, :w], z[:, -w:]], axis=1),
                         np.concatenate([valid[:, :w], valid[:, -w:]], axis=1))
    return off - np.median(off)


def _ring_bow(z, ring):
    """The scanner's bow (nm, everywhere) as a robust quadratic through the border ring ``ring``, or zeros.

    A strong bow (a few hundred nm), left in, stands above the first round's 20 nm feature threshold over
    most of the field, and the bow fitted to what is left (parts of the ring) extrapolates 30 nm wrong
    under the imprint. Taken only where the ring is clearly bowed (its robust spread about the plane over
    ``RING_BOW_MIN_NM``, halved by the quadratic): where the imprint and its pile-up cover much of the
    ring, a quadratic through it would follow them.
    """
    spread_plane = 1.4826 * np.median(np.abs(z[ring] - np.median(z[ring])))
    if not spread_plane > RING_BOW_MIN_NM:
        return np.zeros_like(z)
    use, fit, spread = ring.copy(), np.zeros_like(z), spread_plane
    for _ in range(4):
        fit = poly_surface(z, use, 2, step=1)
        res = z - fit
        med = np.median(res[use])
        spread = 1.4826 * np.median(np.abs(res[use] - med))
        nxt = ring & (np.abs(res - med) <= max(4.0 * spread, 3.0))
        if nxt.sum() < 0.5 * ring.sum() or np.array_equal(nxt, use):
            break
        use = nxt
    return fit if spread < 0.5 * spread_plane else np.zeros_like(z)


# ----------------------------------------------------------------------------- the level beyond the corners
CORNER_BAND_HALF_PX = 3.0   # half width of the strip along a diagonal beyond a corner (pixels)
CORNER_BAND_FROM_PX = 2.0   # the strip starts this far beyond the corner (pixels) ...
CORNER_BAND_TO_D = 0.2      # ... and ends this far beyond it (of the mean diagonal), or at the border
CORNER_BAND_MIN_PX = 10     # pixels a strip needs to count
CORNER_MIN_NM = 3.0         # ... lying this far (nm) under the map's zero at least
CORNER_MIN_STRIPS = 2       # strips needed to level to them
CORNER_RAMP = 0.3           # levelled in part from (1 - this) to (1 + this) times the threshold, in full beyond
CRACK_CLOSING_PX = 9       # a grey closing this wide fills a radial crack (2-4 px, smeared to 6 by the scan) ...
CRACK_NOISE = 4.0           # ... whose pixels lie more than this many noise levels ...
CRACK_MIN_NM = 5.0          # ... and this far (nm) under it


@dataclass(frozen=True)
class CornerLevel:
    """The original surface where pile-up vanishes: on the diagonals beyond the imprints' corners.

    Attributes
    ----------
    levels_nm : ndarray (m,)
        Each strip's level (nm, in the map's current frame).
    strips : ndarray of bool (rows, cols)
        The strips' pixels (those that count).
    """

    levels_nm: np.ndarray
    strips: np.ndarray

    @property
    def offset_nm(self) -> float:
        """The strips' median level (nm): how far the original surface lies off the map's zero."""
        return float(np.median(self.levels_nm)) if len(self.levels_nm) else 0.0

    def weight(self, noise_nm: float) -> float:
        """How far to level to the strips, 0-1: 0 where they lie less than ``1 - CORNER_RAMP`` times the threshold
        under the map's zero, 1 beyond ``1 + CORNER_RAMP`` times it, linear between; 0 on fewer than
        ``CORNER_MIN_STRIPS`` strips.

        The threshold: 2 noise levels, ``CORNER_MIN_NM`` and twice the strips' spread's standard error, the largest.
        Only below: pile-up's tails raise the far field. The strips scatter by a few nm where nothing does (what is
        left of cracks, the z loop's lag), and levelling to them costs the far field's line offsets: on
        feedback-renderer seeds drawn without the z loop, a 1-3 nm threshold levelled maps whose zero was right
        (seed 21: d +0.27 -> -1.10 %). A yes or no at the threshold moved one map's area by 4.8 % and its depth by
        2.4 % between draws of a whisper of noise (unseen feedback seed 79: two strips, -12 and -35 nm, their mean
        0.98-1.02 times the threshold)."""
        m = len(self.levels_nm)
        if m < CORNER_MIN_STRIPS:
            return 0.0
        spread = 1.4826 * float(np.median(np.abs(self.levels_nm - self.offset_nm)))
        threshold = max(2.0 * noise_nm, CORNER_MIN_NM, 2.0 * spread / np.sqrt(m))
        return float(np.clip((-self.offset_nm / threshold - 1.0 + CORNER_RAMP) / (2.0 * CORNER_RAMP), 0.0, 1.0))


def in_cracks(z_nm: np.ndarray, sigma_nm: float) -> np.ndarray:
    """Pixels of ``z_nm`` (a window of a levelled map, NaN where not measured) in a narrow groove, a radial crack:
    more than ``CRACK_NOISE`` noise levels and ``CRACK_MIN_NM`` under a grey closing ``CRACK_CLOSING_PX`` wide."""
    zf = np.where(np.isfinite(z_nm), z_nm, np.nanmedian(z_nm))
    closed = grey_close(zf, np.ones((CRACK_CLOSING_PX, CRACK_CLOSING_PX), bool))
    return closed - zf > max(CRACK_NOISE * sigma_nm, CRACK_MIN_NM)


def _strip_level(v: np.ndarray, sigma: float) -> float:
    """A strip's level, robust to what is left of a radial crack in it: the median of the pixels within 3 noise
    levels (at least 3 nm) of its upper quartile."""
    top = np.percentile(v, 75)
    tol = 3.0 * max(sigma, 1.0)
    near = v[np.abs(v - top) <= tol]
    return float(np.median(near)) if near.size else float(top)


def corner_level(z_nm: np.ndarray, corners_px, centres_px, diagonals_px, sigma_nm: float) -> CornerLevel:
    """The original surface from strips along each imprint's diagonals beyond its corners.

    Pile-up stands beside a Vickers imprint's edges and vanishes at its corners; where the imprint fills most
    of the field, the far field left lies on the pile-up's tails and the map's zero with it (7-38 nm on
    feedback-renderer seeds at 79-90 % fill, pushing every corner 2-4 px out). Each strip runs from
    ``CORNER_BAND_FROM_PX`` beyond a corner to ``CORNER_BAND_TO_D`` of the diagonal, ``CORNER_BAND_HALF_PX``
    either side of the line from the centre through the corner.

    Parameters
    ----------
    z_nm : ndarray (rows, cols)
        The levelled map (nm), NaN where not measured.
    corners_px : sequence of (4, 2) arrays
        Each imprint's corners (column, row).
    centres_px : sequence of (2,) arrays
        Each imprint's centre (column, row).
    diagonals_px : sequence of float
        Each imprint's mean diagonal (pixels).
    sigma_nm : float
        The map's noise (nm).
    """
    ny, nx = z_nm.shape
    levels = []
    strips = np.zeros(z_nm.shape, bool)
    for corners, centre, d in zip(corners_px, centres_px, diagonals_px):
        centre = np.asarray(centre, float)
        for q in np.asarray(corners, float):
            e = q - centre
            r = float(np.hypot(*e))
            if not np.isfinite(r) or r <= 0:
                continue
            e /= r
            reach = CORNER_BAND_FROM_PX + max(CORNER_BAND_TO_D * d, 4.0)
            lo, hi = q - reach - CORNER_BAND_HALF_PX, q + reach + CORNER_BAND_HALF_PX
            c0, r0 = max(int(np.floor(lo[0])), 0), max(int(np.floor(lo[1])), 0)
            c1, r1 = min(int(np.ceil(hi[0])) + 1, nx), min(int(np.ceil(hi[1])) + 1, ny)
            if c1 <= c0 or r1 <= r0:
                continue
            rr, cc = np.mgrid[r0:r1, c0:c1]
            t = (cc - q[0]) * e[0] + (rr - q[1]) * e[1]
            w = -(cc - centre[0]) * e[1] + (rr - centre[1]) * e[0]
            zz = z_nm[r0:r1, c0:c1]
            if not np.isfinite(zz).any():
                continue
            band = (t >= CORNER_BAND_FROM_PX) & (t <= reach) & (np.abs(w) <= CORNER_BAND_HALF_PX) & np.isfinite(zz)
            band &= ~in_cracks(zz, sigma_nm)
            if band.sum() < CORNER_BAND_MIN_PX:
                continue
            levels.append(_strip_level(zz[band], sigma_nm))
            strips[r0:r1, c0:c1] |= band
    return CornerLevel(levels_nm=np.asarray(levels, float), strips=strips)
