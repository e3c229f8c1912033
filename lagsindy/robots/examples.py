"""URDF files shipped with lagsindy, for the documentation and first tries."""

from __future__ import annotations

from pathlib import Path

_DATA = Path(__file__).resolve().parent.parent / "data" / "robots"


def example_urdf(name: str = "planar2") -> Path:
    """The path of a URDF shipped with lagsindy.

    Parameters
    ----------
    name : {"planar2", "arm7"}, default="planar2"
        ``"planar2"``: a two-link planar arm in a vertical plane, the elbow angle
        relative to the upper arm; ``"arm7"``: a seven-joint spatial arm (revolute
        joints about alternating axes). Both were written for lagsindy's tests
        (BSD-3-Clause).

    Returns
    -------
    pathlib.Path

    Examples
    --------
    >>> from lagsindy.robots import example_urdf
    >>> example_urdf().name
    'planar2.urdf'
    """
    names = sorted(p.stem for p in _DATA.glob("*.urdf"))
    if name not in names:
        raise ValueError(f"no shipped URDF named {name!r}; choose one of {names}")
    return _DATA / f"{name}.urdf"
