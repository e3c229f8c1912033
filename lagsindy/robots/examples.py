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


def multisine(t, n_joints, frequencies=(0.7, 1.9, 3.1), amplitude=(0.2, 0.5), *,
              random_state=None):  # fmt: skip
    """An exciting joint trajectory: per joint, a sum of sines of the given
    ``frequencies`` (rad/s) with random phases and amplitudes drawn from
    ``amplitude`` (rad) divided by the square root of the frequency.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Times (s).
    n_joints : int
    frequencies : sequence of float, default=(0.7, 1.9, 3.1)
    amplitude : (low, high), default=(0.2, 0.5)
    random_state : int, Generator or None, default=None
        Drawn per joint and frequency: amplitude, then phase.

    Returns
    -------
    q, qd, qdd : ndarray of shape (n_samples, n_joints)
        Positions and their exact derivatives.

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.robots import multisine
    >>> q, qd, qdd = multisine(np.linspace(0, 1, 5), 2, random_state=0)
    >>> q.shape
    (5, 2)
    """
    import numpy as np

    rng = np.random.default_rng(random_state)
    t = np.asarray(t, dtype=float)
    q, qd, qdd = (np.zeros((len(t), n_joints)) for _ in range(3))
    for j in range(n_joints):
        for w in frequencies:
            a = rng.uniform(*amplitude) / w**0.5
            ph = rng.uniform(0, 2 * np.pi)
            q[:, j] += a * np.sin(w * t + ph)
            qd[:, j] += a * w * np.cos(w * t + ph)
            qdd[:, j] -= a * w**2 * np.sin(w * t + ph)
    return q, qd, qdd
