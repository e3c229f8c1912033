"""Development data for robot arms, simulated with pinocchio (``pip install -e ".[robots]"``).

Two data sets, both at 1 kHz:

* :func:`seven_joint_arm`: a 7-joint arm (``tests/robots/data/arm7.urdf``, the Panda's
  kinematic layout, or any URDF) driven along an exciting trajectory: a finite
  Fourier series per joint (Swevers et al. 1997) scaled into the joint limits (with a
  margin) and the velocity limits. Torques are pinocchio's inverse dynamics plus what
  the URDF does not declare: rotor (armature) inertia, viscous and Coulomb friction
  and a torque offset per joint, and one spring on one joint. Noise: 1e-4 rad on the
  positions, 1 % of each joint's torque RMS on the torques.
* :func:`planar_arm`: the two-link arm of ``tests/robots/data/planar2.urdf`` (its elbow
  angle relative to the upper arm, as an encoder reports it) with gear friction
  larger than its inertial torques.

Each returns a :class:`RobotData` with the noisy measurements and the truth.
This module is a library for the benchmark ``benchmarks/robots.py`` (no ``main``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1] / "tests" / "robots" / "data"
ARM7 = DATA / "arm7.urdf"
ARM7_JOINTS = [f"joint{i}" for i in range(1, 8)]
PLANAR = DATA / "planar2.urdf"


@dataclasses.dataclass
class RobotData:
    """Simulated measurements and the truth behind them.

    Attributes
    ----------
    urdf, joints, locked
        What :meth:`lagsindy.CandidateLibrary.from_urdf` needs.
    t : ndarray (n,)
    q, tau : ndarray (n, n_dof)
        Measured (noisy) positions and torques.
    q_true, qd_true, qdd_true, tau_true : ndarray (n, n_dof)
        Noise-free trajectory and torques.
    armature, viscous, coulomb, offset : ndarray (n_dof,)
        The undeclared joint effects.
    spring : tuple (joint index, stiffness, rest angle) or None
    noise_q : float
    noise_tau : ndarray (n_dof,)
        Torque noise standard deviations.
    """

    urdf: Path
    joints: list
    locked: dict
    t: np.ndarray
    q: np.ndarray
    tau: np.ndarray
    q_true: np.ndarray
    qd_true: np.ndarray
    qdd_true: np.ndarray
    tau_true: np.ndarray
    armature: np.ndarray
    viscous: np.ndarray
    coulomb: np.ndarray
    offset: np.ndarray
    spring: tuple | None
    noise_q: float
    noise_tau: np.ndarray


def fourier_trajectory(
    t, lower, upper, vmax, rng, harmonics=5, period=10.0, margin=0.1
):
    """An exciting finite Fourier series per joint within limits: (q, qd, qdd).

    ``q_j(t) = c_j + sum_l a_jl sin(l w t) + b_jl cos(l w t)`` with ``w = 2 pi / period``
    and coefficients decaying as ``1/l``, scaled so that ``q`` stays inside
    ``[lower + margin * range, upper - margin * range]`` and ``|qd| <= 0.8 vmax``.
    """
    n_dof = len(lower)
    w = 2 * np.pi / period
    q, qd, qdd = (np.zeros((len(t), n_dof)) for _ in range(3))
    for j in range(n_dof):
        lo, hi = lower[j], upper[j]
        if not np.isfinite(lo) or not np.isfinite(hi):
            lo, hi = -np.pi, np.pi
        span = (hi - lo) * (1 - 2 * margin)
        centre = 0.5 * (lo + hi)
        a = rng.normal(size=harmonics) / np.arange(1, harmonics + 1)
        b = rng.normal(size=harmonics) / np.arange(1, harmonics + 1)
        pos = sum(
            a[h] * np.sin((h + 1) * w * t) + b[h] * np.cos((h + 1) * w * t)
            for h in range(harmonics)
        )
        vel = sum(
            (h + 1)
            * w
            * (a[h] * np.cos((h + 1) * w * t) - b[h] * np.sin((h + 1) * w * t))
            for h in range(harmonics)
        )
        acc = sum(
            -(((h + 1) * w) ** 2)
            * (a[h] * np.sin((h + 1) * w * t) + b[h] * np.cos((h + 1) * w * t))
            for h in range(harmonics)
        )
        scale = 0.5 * span / np.abs(pos).max()
        if np.isfinite(vmax[j]):
            scale = min(scale, 0.8 * vmax[j] / np.abs(vel).max())
        q[:, j] = centre + scale * pos
        qd[:, j] = scale * vel
        qdd[:, j] = scale * acc
    return q, qd, qdd


def _velocity_limits(urdf, joints):
    import xml.etree.ElementTree as ET

    root = ET.parse(urdf).getroot()
    out = []
    for name in joints:
        el = root.find(f"joint[@name='{name}']/limit")
        out.append(float(el.get("velocity", np.inf)) if el is not None else np.inf)
    return np.array(out)


def simulate(
    urdf,
    joints,
    locked,
    *,
    duration,
    rate,
    armature,
    viscous,
    coulomb,
    offset,
    spring,
    noise_q,
    noise_tau_rel,
    random_state,
    period=10.0,
):
    """Torques along an exciting trajectory from pinocchio's inverse dynamics + extras."""
    import pinocchio as pin

    from lagsindy import CandidateLibrary

    rng = np.random.default_rng(random_state)
    lib = CandidateLibrary.from_urdf(urdf, joints, locked=locked)
    tree = lib.tree_
    model = pin.buildModelFromUrdf(str(urdf))
    if tree.locked:
        q0 = pin.neutral(model)
        for name, value in tree.locked.items():
            q0[model.joints[model.getJointId(name)].idx_q] = value
        model = pin.buildReducedModel(
            model, [model.getJointId(n) for n in tree.locked], q0
        )
    data = model.createData()
    idx = [model.joints[model.getJointId(c)].idx_v for c in tree.coordinates]
    t = np.arange(int(round(duration * rate))) / rate
    q, qd, qdd = fourier_trajectory(
        t,
        tree.lower,
        tree.upper,
        _velocity_limits(urdf, tree.coordinates),
        rng,
        period=period,
    )
    tau = np.empty_like(q)
    qp, vp, ap = np.zeros(model.nq), np.zeros(model.nv), np.zeros(model.nv)
    for s in range(len(t)):
        qp[idx], vp[idx], ap[idx] = q[s], qd[s], qdd[s]
        tau[s] = pin.rnea(model, data, qp, vp, ap)[idx]
    tau = tau + armature * qdd + viscous * qd + coulomb * np.sign(qd) + offset
    if spring is not None:
        j, k, rest = spring
        tau[:, j] += k * (q[:, j] - rest)
    noise_tau = noise_tau_rel * np.sqrt(np.mean(tau**2, axis=0))
    return RobotData(
        urdf=Path(urdf),
        joints=list(tree.coordinates),
        locked=dict(locked or {}),
        t=t,
        q=q + noise_q * rng.normal(size=q.shape),
        tau=tau + noise_tau * rng.normal(size=tau.shape),
        q_true=q,
        qd_true=qd,
        qdd_true=qdd,
        tau_true=tau,
        armature=np.asarray(armature, float),
        viscous=np.asarray(viscous, float),
        coulomb=np.asarray(coulomb, float),
        offset=np.asarray(offset, float),
        spring=spring,
        noise_q=noise_q,
        noise_tau=noise_tau,
    )


def seven_joint_arm(
    duration=40.0, rate=1000.0, urdf=ARM7, joints=None, locked=None, random_state=0
):
    """The 7-joint arm data set (see the module docstring); spring on joint 4."""
    joints = ARM7_JOINTS if joints is None and Path(urdf) == ARM7 else joints
    locked = (
        {"finger_joint1": 0.02} if locked is None and Path(urdf) == ARM7 else locked
    )
    return simulate(
        urdf,
        joints,
        locked,
        duration=duration,
        rate=rate,
        armature=np.array([0.30, 0.30, 0.25, 0.25, 0.10, 0.10, 0.05]),
        viscous=np.array([0.60, 0.80, 0.50, 0.60, 0.20, 0.25, 0.10]),
        coulomb=np.array([0.80, 1.00, 0.70, 0.80, 0.40, 0.35, 0.30]),
        offset=np.array([0.10, -0.20, 0.05, 0.15, -0.05, 0.02, 0.04]),
        spring=(3, 4.0, -1.5),  # joint 4: 4 N m/rad about -1.5 rad (a cable)
        noise_q=1e-4,
        noise_tau_rel=0.01,
        random_state=random_state,
    )


def planar_arm(duration=40.0, rate=1000.0, random_state=0):
    """The two-link arm with a relative elbow and gear friction above its inertia."""
    return simulate(
        PLANAR,
        None,
        None,
        duration=duration,
        rate=rate,
        armature=np.array([0.05, 0.03]),
        viscous=np.array([4.0, 3.0]),
        coulomb=np.array([3.0, 2.0]),
        offset=np.array([0.2, -0.1]),
        spring=None,
        noise_q=1e-4,
        noise_tau_rel=0.01,
        random_state=random_state,
        period=5.0,
    )
