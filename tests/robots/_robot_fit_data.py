"""Test data for fits of URDF libraries, simulated with lagsindy's own regressor (no
pinocchio): smooth multi-sine joint trajectories, torques of the URDF's parameters
plus rotor inertia, friction, offsets and optionally a spring."""

from __future__ import annotations

import dataclasses

import numpy as np

from lagsindy import CandidateLibrary
from lagsindy.robots import example_urdf, multisine

EPS = 0.01  # the Coulomb kind's default smoothing velocity (tanh(qd / eps))


@dataclasses.dataclass
class ArmData:
    X: np.ndarray
    tau: np.ndarray
    t: np.ndarray
    truth: np.ndarray  # full parameters (link, then rotor)
    viscous: np.ndarray
    coulomb: np.ndarray
    offset: np.ndarray
    spring: tuple | None


def planar_data(
    duration=8.0,
    dt=0.002,
    armature=(0.02, 0.01),
    viscous=(0.6, 0.3),
    coulomb=(0.4, 0.2),
    offset=(0.1, -0.05),
    spring=None,
    seed=0,
):
    """The shipped two-link arm along multi-sines; ``spring=(joint, k, rest)``."""
    rng = np.random.default_rng(seed)
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    t = np.arange(0.0, duration, dt)
    q, qd, qdd = multisine(t, 2, random_state=rng)
    truth = lib.nominal_.copy()
    truth[-2:] = armature
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth
    viscous, coulomb, offset = (
        np.asarray(v, float) for v in (viscous, coulomb, offset)
    )
    tau += viscous * qd + coulomb * np.tanh(qd / EPS) + offset
    if spring is not None:
        j, k, rest = spring
        tau[:, j] += k * (q[:, j] - rest)
    return ArmData(
        np.hstack([q, qd, qdd]), tau, t, truth, viscous, coulomb, offset, spring
    )


def two_sines(duration, dt=0.002):
    """Times and ``(q, qd, qdd)`` of the two-link arm along two sines per joint
    (the motion of docs/robots.md's examples): ``t, q, qd, qdd``."""
    t = np.arange(0.0, duration, dt)
    w = np.array([[0.7, 1.9], [1.3, 3.1]])
    q = 0.4 * np.sin(np.outer(t, w[0])) + 0.2 * np.cos(np.outer(t, w[1]))
    qd = 0.4 * w[0] * np.cos(np.outer(t, w[0])) - 0.2 * w[1] * np.sin(np.outer(t, w[1]))
    qdd = -0.4 * w[0] ** 2 * np.sin(np.outer(t, w[0])) - 0.2 * w[1] ** 2 * np.cos(
        np.outer(t, w[1])
    )
    return t, q, qd, qdd
