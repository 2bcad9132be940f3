"""Mutants of the scan flow's speed-critical stages (issue 21 for issue 22's area): the RBF selection,
the plane, the ring refinement and the plate-image path.

Each mutant is one text edit; the harness of benchmarks/mutants.py swaps the mutated module in at
import (the source tree is never written) and runs the listed tests with ``pytest -x``. A mutant is
killed when they fail.

    python benchmarks/mutants.py --areas [-k NAME] [--jobs 2]

Measured (2 cores, load 13-19): 9 of 9 killed, 5-25 s each. Written and dropped: the fine ring fit's
window left on the starting centre instead of the capture pass's (``_gather(raster, uv0, ...)``)
survived every test, because with starts 0.2-0.3 mm off the fine window still holds both rings; it
was replaced by the capture pass cut to one iteration. Huber off survived tests/test_ring_refinement.py
alone; it and the one-iteration capture pass are killed by tests/test_scan_image_refine.py.
"""


RBF_TESTS = ["tests/test_rbf_select.py", "tests/test_detect_rbf.py", "-k", "ols or rbf or select or chosen or batched"]

PLANE_TESTS = ["tests/test_plane.py", "tests/test_geometry.py", "-k", "plane or projection"]

DETECT_TESTS = ["tests/test_scan_image_refine.py", "tests/test_ring_refinement.py"]

IMAGE_TESTS = ["tests/test_plate_image.py", "-k", "1200_dpi or pixel_size_option"]

MUTANTS_SCANSPEED = [
    {"name": "rbf-err-not-normalised", "file": "stages/rbf.py",
     "old": "                e /= norms[i]", "new": "                e /= 1.0",
     "tests": RBF_TESTS},
    {"name": "rbf-coefficient-unscaled", "file": "stages/rbf.py",
     "old": "coef = s / nj", "new": "coef = s", "tests": RBF_TESTS},
    {"name": "plane-rotation-transposed", "file": "stages/plane.py",
     "old": 'np.einsum("ij,kj->ik", xyz_mm - plane.origin_mm, plane.rotation)',
     "new": 'np.einsum("ij,jk->ik", xyz_mm - plane.origin_mm, plane.rotation)', "tests": PLANE_TESTS},
    {"name": "projection-rotation-transposed", "file": "stages/project.py",
     "old": "            u = dx * rot[0, 0] + dy * rot[0, 1] + dz * rot[0, 2]",
     "new": "            u = dx * rot[0, 0] + dy * rot[1, 0] + dz * rot[2, 0]", "tests": PLANE_TESTS},
    {"name": "plane-normal-side", "file": "stages/plane.py",
     "old": "    if n[2] < 0:\n        n = -n", "new": "    if n[2] > 0:\n        n = -n", "tests": PLANE_TESTS},
    {"name": "detect-no-huber", "file": "stages/detect.py",
     "old": "radii, n_iter, free, huber_k=2.0):", "new": "radii, n_iter, free, huber_k=1e9):",
     "tests": DETECT_TESTS},
    {"name": "detect-capture-pass-one-iteration", "file": "stages/detect.py",
     "old": "p, _ = _gauss_newton(p, u, v, y, mask, radii, 6, free_a)",
     "new": "p, _ = _gauss_newton(p, u, v, y, mask, radii, 1, free_a)", "tests": DETECT_TESTS},
    {"name": "image-coarse-pixel-size", "file": "stages/plate_image.py",
     "old": "pixel_mm=raster.pixel_mm * f)", "new": "pixel_mm=raster.pixel_mm * (f + 1))", "tests": IMAGE_TESTS},
]

