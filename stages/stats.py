"""Small statistics shared by flows and reports."""
from __future__ import annotations

import numpy as np


def reduction_pct(before, after):
    """Reduction (%) from ``before`` to ``after``; NaN when either is missing or before <= 0."""
    if not (np.isfinite(before) and np.isfinite(after)) or before <= 0:
        return float("nan")
    return 100.0 * (1.0 - after / before)


def pct_less(new, old) -> float:
    """How much smaller ``new`` is than ``old``, in % (0 when ``old`` is 0)."""
    return float(100.0 * (1.0 - new / old)) if old > 0 else 0.0
