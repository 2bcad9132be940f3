"""Vickers micro-indentation stages (paper 000 sec. 4), one concern per module.

- :mod:`.indent_geometry`: circle fit, diagonals, robust plane, the ``Imprint`` record;
- :mod:`.indent_afm`: AFM pit detection and the four-facet model;
- :mod:`.indent_single`: single-imprint metrology (corners on bowed edges, area, floor depth,
  pile-up, hardness);
- :mod:`.indent_om`: OM micrographs (illumination, dot detection, diamond image model);
- :mod:`.indent_om_array`: the dots of one micrograph fitted with shared optics and material;
- :mod:`.indent_array`: array indexing, registration and per-size statistics.

This module re-exports their public names.
"""
from .indent_afm import detect_pits, measure_afm  # noqa: F401
from .indent_array import ArrayFit, index_array, size_stats  # noqa: F401
from .indent_geometry import IMPRINT_FIELDS, Imprint, circle_fit  # noqa: F401
from .indent_om import (RESOLUTION_RADII, airy_radius_um, airy_sigma_um, detect_dots, measure_om,  # noqa: F401
                        om_background)
from .indent_om_array import measure_om_array, om_halo_crease  # noqa: F401

__all__ = ["circle_fit", "Imprint", "detect_pits", "measure_afm", "detect_dots", "measure_om", "measure_om_array",
           "om_background", "ArrayFit", "index_array", "size_stats", "IMPRINT_FIELDS", "airy_radius_um",
           "RESOLUTION_RADII", "om_halo_crease"]
