"""Plausible mutants of the indents stages (issue 21): each must make the indents tests fail.

``MUTANTS_INDENTS`` is a list of dicts {name, file, old, new, tests}: one text edit of a stage
(``old`` occurs exactly once in ``file``) and the pytest selection that must catch it. They run
through the harness of ``benchmarks/mutants.py`` (the mutated module is swapped in at import in a
fresh pytest process; the source tree is never written)::

    python benchmarks/mutants.py --areas [-k NAME] [--jobs 2]

A mutant is killed when its tests fail (exit 1), survives when they pass.
"""


_MICRO = "tests/test_indent_micrograph.py::test_single_micrograph_against_truth"

_SINGLE = "tests/test_indent_single.py"

MUTANTS_INDENTS = [
    {   # a blurred corner as the sum over wedges (half the contrast at its tip): corners pulled in
        "name": "micrograph-inside-as-sum",
        "file": "stages/indent_micrograph_kernel.py",
        "old": "        out = min(max(1.0 - inside, 0.0), 1.0)\n",
        "new": "        inside = min(wsum, 1.0)\n        out = min(max(1.0 - inside, 0.0), 1.0)\n",
        "tests": ["tests/test_indent_micrograph.py::test_small_om_imprint_not_short"],
    },
    {   # block centres of the coarse levels half a block off
        "name": "micrograph-block-half-pixel",
        "file": "stages/indent_micrograph.py",
        "old": "X, Y = np.meshgrid(cols * f + (f - 1) / 2, rows * f + (f - 1) / 2)",
        "new": "X, Y = np.meshgrid(cols * f + f / 2, rows * f + f / 2)",
        "tests": [_MICRO],
    },
    {   # the dark edge lines left out of the model
        "name": "micrograph-no-edge-lines",
        "file": "stages/indent_micrograph_kernel.py",
        "old": "        a[i, 15] = edge_line * out\n        a[i, 16] = edge_line * inside\n",
        "new": "        a[i, 15] = 0.0\n        a[i, 16] = 0.0\n",
        "tests": [_MICRO],
    },
    {   # the ridge-end correction moves the corner by delta * tan instead of delta / tan
        "name": "micrograph-ridge-tan",
        "file": "stages/indent_micrograph.py",
        "old": "t_c = t_half + delta_px / np.tan(alpha / 2)",
        "new": "t_c = t_half + delta_px * np.tan(alpha / 2) + 3.0",
        "tests": [_MICRO, "tests/test_indent_micrograph.py::test_two_imprints_in_one_micrograph"],
    },
    {   # the edges' bows left out of the micrograph model (straight edges: corners where the edges' average
        # lines cross, bow and area of the bowed outline wrong)
        "name": "micrograph-straight-edges",
        "file": "stages/indent_micrograph_kernel.py",
        "old": "                e[k] += bow[k] * 4.0 * t * (1.0 - t)\n",
        "new": "                e[k] += 0.0 * t\n",
        "tests": ["tests/test_micrograph_independent.py::test_bowed_edges_bow_and_area"],
    },
    {   # HV with the load in mN instead of N
        "name": "single-hv-load-units",
        "file": "stages/indent_single.py",
        "old": "return indenter.hv_factor * (load_mN * 1e-3) / (d_mm * d_mm)",
        "new": "return indenter.hv_factor * load_mN / (d_mm * d_mm)",
        "tests": [_SINGLE + "::test_hardness_formula"],
    },
    {   # edge bow measured with the normal pointing inwards (sink-in reported as pile-up)
        "name": "single-bow-sign",
        "file": "stages/indent_single.py",
        "old": "        if nrm @ (mid - [cx, cy]) < 0:\n            nrm = -nrm\n",
        "new": "        if nrm @ (mid - [cx, cy]) > 0:\n            nrm = -nrm\n",
        "tests": [_SINGLE + "::test_edge_bow_signs_against_truth"],
    },
    {   # a corner outside the field not flagged
        "name": "single-border-not-flagged",
        "file": "stages/indent_single.py",
        "old": "    cut = bool(cut or outside)\n",
        "new": "    cut = bool(outside)\n",
        "tests": [_SINGLE + "::test_cut_by_border_flagged", _SINGLE + "::test_edge_across_the_border_flagged_with_corners_inside"],
    },
    {   # the corner refined on the ray ignores the straight-line zero crossing (coarse corner kept)
        "name": "single-corner-not-refined",
        "file": "stages/indent_single.py",
        "old": "    s0 = -k[1] / k[0]\n",
        "new": "    s0 = length - 1.0\n",
        "tests": [_SINGLE + "::test_single_imprint_against_truth", _SINGLE + "::test_profile_crossing_where_the_valley_fit_fails"],
    },
    {   # pile-up volume in µm² nm taken as µm³ (the 1e-3 dropped)
        "name": "single-pileup-volume-units",
        "file": "stages/indent_single.py",
        "old": "vol = float(zr[outer].sum() * pixel_um * pixel_um * 1e-3)",
        "new": "vol = float(zr[outer].sum() * pixel_um * pixel_um)",
        "tests": [_SINGLE + "::test_single_imprint_against_truth"],
    },
    {   # the full-resolution level skipped on the coarse outline's size (a halo inflates it)
        "name": "micrograph-levels-on-coarse-size",
        "file": "stages/indent_micrograph.py",
        "old": "if i > 0 and _mean_diagonal(p[2:10].reshape(4, 2)) / f > FINEST_PX:",
        "new": "if i > 0 and d_px / f > FINEST_PX:",
        "tests": ["tests/test_indent_micrograph.py::test_halo_does_not_skip_full_resolution_level"],
    },
    {   # pit candidates at the deepest point within the component's bounding box, not in the map
        "name": "afm-pit-position-in-box",
        "file": "stages/indent_afm.py",
        "old": "out.append((float(pos_k[0] + sl[0].start), float(pos_k[1] + sl[1].start), float(r_px)))",
        "new": "out.append((float(pos_k[0]), float(pos_k[1]), float(r_px)))",
        "tests": ["tests/test_indents.py", _SINGLE],
    },
    {   # the facet fit's robust loss dropped (plain least squares): dust and scars pull the facets
        "name": "lm-soft-l1-unweighted",
        "file": "stages/indent_geometry.py",
        "old": "        w = 1.0 / np.sqrt(1 + (r / f_scale) ** 2)\n",
        "new": "        w = np.ones_like(r)\n",
        "tests": ["tests/test_indents.py", _MICRO],
    },
    {   # the OM model's fine grid cut off inside the rim's tail (the far-cell shortcut too near the dot)
        "name": "om-far-cut-inside-rim",
        "file": "stages/indent_om_kernel.py",
        "old": "    far = max(RIM_TAIL_T * rw,",
        "new": "    far = max(1.0 * rw,",
        "tests": ["tests/test_indents.py"],
    },
    {   # the extended OM model (edge and ridge lines, one-sided shading) never switched on
        "name": "om-extended-never",
        "file": "stages/indent_om_array.py",
        "old": "    if gain <= 1.0:\n",
        "new": "    if gain <= 1e9:\n",
        "tests": ["tests/test_indents.py::test_om_array_with_lines_and_one_sided_shading"],
    },
    {   # radial cracks left in: the level contour runs out along them (session 12)
        "name": "single-cracks-not-filled",
        "file": "stages/indent_single.py",
        "old": "    zr, groove = _fill_cracks(zr, noise, slope_px, depth)\n",
        "new": "    groove = np.zeros(zr.shape, bool)\n",
        "tests": [_SINGLE + "::test_radial_cracks_do_not_lengthen_the_diagonals"],
    },
    {   # row offsets from rows with 3 far-field pixels (lobe tails set their zero; session 12)
        "name": "level-row-offsets-from-3-pixels",
        "file": "stages/indent_level.py",
        "old": "    min_row = max(3, nx // 10)\n",
        "new": "    min_row = 3\n",
        "tests": ["tests/test_independent_renders.py::test_single_ruled_imprint_against_truth"],
    },
    {   # the ring's bow never fitted first (a 300 nm scanner bow; session 12)
        "name": "level-ring-bow-never",
        "file": "stages/indent_level.py",
        "old": "    if not spread_plane > RING_BOW_MIN_NM:\n",
        "new": "    if True:\n",
        "tests": [_SINGLE + "::test_strong_scanner_bow_levelled_from_the_ring"],
    },
    {   # the first mask from the raw map only: a drifting scan masks 95 % of the field (session 13)
        "name": "level-first-mask-without-side-strips",
        "file": "stages/indent_level.py",
        "old": "    return min(masks, key=lambda m: int(m.sum()))\n",
        "new": "    return masks[0]\n",
        "tests": [_SINGLE + "::test_drifting_scan_lines_within_goals"],
    },
    {   # no square search when the outline finds nothing (BSE grain; session 13)
        "name": "micrograph-no-square-search",
        "file": "pipeline/flows/indents.py",
        "old": "    if not imps and not squares:\n",
        "new": "    if False:\n",
        "tests": ["tests/test_micrograph_independent.py::test_grain_spots_of_one_imprint_refused_by_their_sizes"],
    },
    {   # grain spots of every size go to the dots' slow shared fit first (session 14)
        "name": "flow-dots-fit-before-four-edges",
        "file": "pipeline/flows/indents.py",
        "old": "    squares = spec is None and sel.mixed_spots([c[2] for c in cands])\n",
        "new": "    squares = False\n",
        "tests": ["tests/test_micrograph_independent.py::test_bse_grain_contrast_square_search"],
    },
    {   # dots of every size after the fit taken as imprints (session 14)
        "name": "select-one-size-always",
        "file": "stages/indent_select.py",
        "old": "    if len(imps) < 5:\n        return True\n",
        "new": "    if True:\n        return True\n",
        "tests": ["tests/test_micrograph_independent.py::test_grain_without_an_imprint_is_no_imprint"],
    },
    {   # the first round's surface fitted through the line offsets of a row-flattened scan (session 14)
        "name": "level-first-surface-through-offsets",
        "file": "stages/indent_level.py",
        "old": "        surf = poly_surface(z - off0[:, None] if it == 0 else z, keep, _bow_degree(keep),\n",
        "new": "        surf = poly_surface(z, keep, _bow_degree(keep),\n",
        "tests": ["tests/test_independent_renders.py::test_flattened_scan_cropped_afterwards"],
    },
    {   # a map of non-square pixels read as square: every length along the long side shrunk (session 15)
        "name": "io-non-square-read-as-square",
        "file": "stages/image_io.py",
        "old": "        data, px, meta = _square_pixels(data, *px, meta, path)\n",
        "new": "        px = px[0]\n",
        "tests": ["tests/test_afm_readers.py::test_non_square_pixels_resampled_to_square",
                  "tests/test_independent_renders.py::test_single_ruled_imprint_scanned_with_every_second_line"],
    },
    {   # the resampled rows half a new pixel off the lines they come from (session 15)
        "name": "io-resample-half-pixel-off",
        "file": "stages/image_io.py",
        "old": "    pos = np.clip(np.arange(n_new) * short / long_, 0.0, n_old - 1.0)\n",
        "new": "    pos = np.clip((np.arange(n_new) + 0.5) * short / long_ - 0.5, 0.0, n_old - 1.0)\n",
        "tests": ["tests/test_afm_readers.py::test_non_square_pixels_resampled_to_square"],
    },
    {   # a line-flattened scan measured as it is, the lines' fits not taken again from the far field (session 15)
        "name": "flow-line-flatten-left-in",
        "file": "pipeline/flows/indents.py",
        "old": "            heights = unflatten_lines(heights, flat)\n",
        "new": "            pass\n",
        "tests": ["tests/test_independent_renders.py::test_single_ruled_imprint_flattened_line_by_line"],
    },
    {   # the signature's tolerance at half the noise: plain noisy scans taken for flattened (session 15)
        "name": "unflatten-loose-signature",
        "file": "stages/indent_unflatten.py",
        "old": "AGREE_NOISE = 0.02\n",
        "new": "AGREE_NOISE = 0.5\n",
        "tests": ["tests/test_indent_unflatten.py"],
    },
    {   # each line fitted on its own, not started from the lines before it (session 15)
        "name": "unflatten-lines-not-followed",
        "file": "stages/indent_unflatten.py",
        "old": "        start = None if not hist else (hist[-1] if len(hist) < 2 else 2 * hist[-1] - hist[-2])\n",
        "new": "        start = None\n",
        "tests": ["tests/test_indent_unflatten.py",
                  "tests/test_independent_renders.py::test_single_ruled_imprint_flattened_line_by_line"],
    },
    {   # the scan's slope and bow along the lines left in every line of an order-0/1 flatten (session 15)
        "name": "unflatten-no-common-profile",
        "file": "stages/indent_unflatten.py",
        "old": "    y = zz - _common_profile(zz, valid, order, scale)[None, :]\n",
        "new": "    y = zz\n",
        "tests": ["tests/test_indent_unflatten.py",
                  "tests/test_independent_renders.py::test_single_ruled_imprint_flattened_line_by_line"],
    },
    {   # the polynomial orders not told apart: a line flatten read as a mean flatten (session 15)
        "name": "unflatten-order-zero-only",
        "file": "stages/indent_unflatten.py",
        "old": "            for order in (3, 2, 1):\n",
        "new": "            for order in ():\n",
        "tests": ["tests/test_indent_unflatten.py"],
    },
    {   # pits whose contact area is no quadrilateral's between their corners taken as imprints (session 14)
        "name": "select-any-area-ratio",
        "file": "stages/indent_select.py",
        "old": "AREA_RATIO_RANGE = (0.6, 1.4)\n",
        "new": "AREA_RATIO_RANGE = (0.0, float(\"inf\"))\n",
        "tests": ["tests/test_independent_renders.py::test_pits_beside_lobes_are_no_imprints"],
    },
    {   # a map whose features stand up measured as if its heights were right (session 14)
        "name": "flow-inverted-heights-measured",
        "file": "pipeline/flows/indents.py",
        "old": "    if up <= down:\n        return\n",
        "new": "    if True:\n        return\n",
        "tests": ["tests/test_independent_renders.py::test_inverted_heights_are_refused"],
    },
    {   # imprints drawn red against a size that was only inferred, nothing judged (session 14)
        "name": "report-red-without-spec",
        "file": "reports/indents_report.py",
        "old": "    return [1] * n if f.nominal_inferred else f.table.get(\"in_tolerance\", [1] * n)\n",
        "new": "    return f.table.get(\"in_tolerance\", [1] * n)\n",
        "tests": ["tests/test_cli_indents_summary_line.py::test_report_without_spec_marks_nothing_out_of_tolerance"],
    },
    {   # a collapsed mask falls back to the border ring in every round (session 13)
        "name": "level-collapse-to-ring",
        "file": "stages/indent_level.py",
        "old": "            keep = valid & ring if it == 0 else prev\n",
        "new": "            keep = valid & ring\n",
        "tests": ["tests/test_independent_renders.py::test_feedback_render_noise_free_and_far_field_in_corners"],
    },
    {   # a quadratic whatever the far field's spread (session 13)
        "name": "level-always-quadratic",
        "file": "stages/indent_level.py",
        "old": "    if cells.sum() >= 10:\n",
        "new": "    if True:\n",
        "tests": ["tests/test_independent_renders.py::test_feedback_render_far_field_in_slivers"],
    },
    {   # the diagonals' direction from the boundary's far points again (session 13)
        "name": "single-diagonals-from-outline",
        "file": "stages/indent_single.py",
        "old": "    theta = _diagonal_angle(zs, pit, depth, nc)\n",
        "new": "    theta = None\n",
        "tests": ["tests/test_independent_renders.py::test_feedback_render_chip_beside_a_corner"],
    },
    {   # flat-bottomed or unfittable small pits taken for imprints without a spec (session 13)
        "name": "select-pits-not-pyramids",
        "file": "stages/indent_select.py",
        "old": "                                          or m.floor_share > MAX_FLOOR_SHARE or _no_pyramid(m, pixel_um))]\n",
        "new": "                                          )]\n",
        "tests": ["tests/test_afm_readers.py::test_real_maps_keep_every_line_and_hold_no_imprint"],
    },
    {   # the corner's sector the whole quadrant again: a chip's tip 25 deg off the diagonal (session 13)
        "name": "single-corner-sector-quadrant",
        "file": "stages/indent_single.py",
        "old": "        sec = np.abs(dphi) < np.pi / (3 * nc)\n",
        "new": "        sec = np.abs(dphi) < np.pi / nc\n",
        "tests": ["tests/test_independent_renders.py::test_feedback_render_chip_beside_a_corner"],
    },
    {   # squares under the minimum diagonal scored again: a dust blob wins on the real SEM image (session 13)
        "name": "squares-under-minimum-size",
        "file": "stages/indent_square_search.py",
        "old": "    sides = np.unique(np.ceil(side_min * SIZE_STEP ** np.arange(200)).astype(int))\n",
        "new": "    sides = np.unique(np.round(side_min * SIZE_STEP ** np.arange(200)).astype(int))\n",
        "tests": ["tests/test_indent_micrograph.py::test_real_sem_square_search_lands_on_the_imprint"],
    },
    {   # the squares ranked by the weakest edge's plain mean gradient (session 13)
        "name": "squares-plain-mean-score",
        "file": "stages/indent_square_search.py",
        "old": "        found.append(((float(score[r, c]) - mu) * np.sqrt(L) / sd, c, r, L))\n",
        "new": "        found.append((float(score[r, c]), c, r, L))\n",
        "tests": ["tests/test_indent_micrograph.py::test_real_sem_square_search_lands_on_the_imprint",
                  "tests/test_micrograph_independent.py::test_bse_grain_contrast_square_search"],
    },
]
