"""Where a warning raised deep inside the package should point: the user's line."""

from __future__ import annotations

import os
import sys

_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep


def outside_stacklevel() -> int:
    """The ``stacklevel`` that makes a warning issued by the calling function point
    at the first frame outside this package (the user's line), however deep in the
    package the warning is raised."""
    frame, level = sys._getframe(1), 1
    while frame is not None and _inside(frame.f_code):
        frame, level = frame.f_back, level + 1
    return level


def _inside(code) -> bool:
    # this package's frames, and scikit-learn's wrapper around every ``fit``
    # (``_fit_context``), which stands between the user's line and the method
    return code.co_filename.startswith(_PACKAGE_DIR) or (
        code.co_name == "wrapper" and f"{os.sep}sklearn{os.sep}" in code.co_filename
    )
