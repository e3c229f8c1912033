"""The unit check before ``derivatives(..., angles=)`` unwraps angles by 2 pi.

:func:`numpy.unwrap` reads a step larger than pi between consecutive samples as a
wrap from pi to -pi and adds a multiple of 2 pi. That is right for angles in radians
reduced to one turn, and silently wrong for angles in degrees (a wrap from 180 to
-180, or a fast swing of more than 3.14 degrees per sample, becomes a staircase of
6.28). Angles reduced to one turn in radians span at most 2 pi on a trajectory; so a
step that ``numpy.unwrap`` would change on a trajectory whose values span more than
a turn (``WRAP_SPAN`` turns) is not a radian wrap: the check warns and says what to
do.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

# Span (in turns of 2 pi) of a trajectory's values above which a step of more than pi
# is not a wrap in radians. Angles wrapped to (-pi, pi] or [0, 2 pi) span at most one
# turn; the margin lets noise carry a sample a little past the wrap.
WRAP_SPAN = 1.05


def unwrap_unit_check(q, segments, mask, stacklevel: int = 2) -> list:
    """Warn when unwrapping the ``mask`` columns of ``q`` by 2 pi would change a
    trajectory whose values span more than ``WRAP_SPAN`` turns (angles in degrees,
    or angles already continuous). Returns the columns found."""
    found = {}
    for j in np.flatnonzero(mask):
        for _, sl in segments:
            col = q[sl, j]
            if col.size < 2 or np.ptp(col) <= WRAP_SPAN * 2 * math.pi:
                continue
            steps = np.abs(np.diff(col))
            if np.any(steps > math.pi):
                found[int(j)] = max(found.get(int(j), 0.0), float(steps.max()))
    if found:
        shown = ", ".join(f"{j} (steps up to {s:.3g})" for j, s in found.items())
        warnings.warn(
            f"angles {shown} step by more than pi between consecutive samples on a "
            f"trajectory whose values span more than a turn in radians, so the "
            "steps are not wraps of radian angles, and unwrapping adds multiples of "
            "2 pi there. Angles in degrees do this: convert them to radians first "
            "(numpy.deg2rad, or numpy.unwrap(q, period=360) then numpy.deg2rad for "
            "degrees wrapped at +-180). Angles that are already continuous need no "
            "angles=; otherwise sample faster than half a turn per sample.",
            UserWarning,
            stacklevel=stacklevel + 1,
        )
    return sorted(found)
