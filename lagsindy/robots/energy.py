r"""The energy regressor of a robot arm as torch term functions.

The Lagrangian of a tree of rigid bodies is linear in each body's 10 inertial
parameters :math:`\pi_b = [m, h, I]` (mass, first moment :math:`h = m c`, rotational
inertia about the body frame's origin) and in a rotor (armature) inertia
:math:`I_{a,j}` per joint:

.. math::

    L = \sum_b \Big(\tfrac12 m\, v_b^\top v_b + h^\top (v_b \times \omega_b)
        + \tfrac12 \omega_b^\top I \omega_b + g^\top (m\, p_b + R_b h)\Big)
        + \sum_j \tfrac12 I_{a,j} \dot q_j^2,

with :math:`v_b, \omega_b` the linear velocity of the body frame's origin and the
angular velocity, both in the body frame, :math:`(R_b, p_b)` the body's pose in the
base frame and :math:`g` the gravity vector in the base frame. The terms
:math:`\phi_j = \partial L / \partial \pi_j` are this library's candidate functions,
so ``L = sum_j pi_j * phi_j(q, qd)`` and the Euler-Lagrange columns of the terms are
the columns of the classical joint torque regressor.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from torch.func import jacfwd, jvp, vmap

from .regressor import _cross
from .urdf import PARAMETER_KINDS, RobotTree

GRAVITY = (0.0, 0.0, -9.81)
COLUMN_CHUNK = 1024  # samples per chunk of RobotTerms.columns


class _one_thread:
    """One torch thread on the CPU for the recursion's many small operations: with
    two threads on a loaded 2-core machine the same columns cost 10 times the CPU
    time (measured: 0.41 s vs 4.5 s for 9000 samples of a 7-joint arm)."""

    def __init__(self, like):
        self.cpu = like.device.type == "cpu"

    def __enter__(self):
        if self.cpu:
            self.threads = torch.get_num_threads()
            torch.set_num_threads(1)
        return self

    def __exit__(self, *exc):
        if self.cpu:
            torch.set_num_threads(self.threads)


def _rotate_t(rot, v):
    """``rot^T @ v`` over leading batch dimensions."""
    return torch.einsum("...ji,...j->...i", rot, v)


def _rotate(rot, v):
    return torch.einsum("...ij,...j->...i", rot, v)


def parameter_names(tree: RobotTree, armature: bool = True) -> list[str]:
    """Term names: ``"<kind>_<link>"`` per body parameter, then ``"Ia_<joint>"``."""
    names = [f"{k}_{b.name}" for b in tree.bodies for k in PARAMETER_KINDS]
    if armature:
        names += [f"Ia_{j}" for j in tree.coordinates]
    return names


class RobotTerms:
    """Torch term function of a robot's energy regressor.

    ``fn(q, qd)`` gives the ``n_terms`` values :math:`\\phi_j` for one sample
    (``q``, ``qd`` of shape ``(n_dof,)``), and ``fn_batch`` for many (shape
    ``(n_samples, n_dof)``); both are the same code over leading batch dimensions,
    written without in-place operations, value-dependent branches or ``.item()``, so
    ``torch.func`` (``jacfwd``, ``jvp``, ``vmap``) differentiates them. The tensors
    follow the input's dtype and device.

    Parameters
    ----------
    tree : RobotTree
        The reduced kinematic tree (:func:`lagsindy.robots.urdf.build_tree`).
    armature : bool, default=True
        Add a rotor inertia term ``0.5 * qd_j**2`` per joint, after the link terms.
    gravity : sequence of 3 float, default=(0, 0, -9.81)
        Gravity in the URDF's base (root link) frame.

    Attributes
    ----------
    names : list of str
        One name per term: ``m_<link>, mx_<link>, ..., Izz_<link>`` per moving body
        (pinocchio's order of the inertial parameters), then ``Ia_<joint>``.
    """

    def __init__(self, tree: RobotTree, armature: bool = True, gravity=GRAVITY):
        self.tree = tree
        self.armature = bool(armature)
        self.gravity = np.asarray(gravity, dtype=float).reshape(3)
        self.names = parameter_names(tree, self.armature)

    @property
    def n_terms(self) -> int:
        return len(self.names)

    def _packed(self):
        """Per-body constants as one array (n_bodies + 1, 36); the last row: gravity."""
        rows = []
        for b in self.tree.bodies:
            k = np.array(
                [
                    [0.0, -b.axis[2], b.axis[1]],
                    [b.axis[2], 0.0, -b.axis[0]],
                    [-b.axis[1], b.axis[0], 0.0],
                ]
            )
            rows.append(
                np.concatenate(
                    [
                        b.rotation.ravel(),
                        b.translation,
                        b.axis,
                        k.ravel(),
                        (k @ k).ravel(),
                        b.rotation @ b.axis,
                    ]
                )
            )
        rows.append(np.concatenate([self.gravity, np.eye(3).ravel(), np.zeros(24)]))
        return np.stack(rows)

    def _consts(self, like):
        # Fresh tensors at every call: a constant tensor cached across calls breaks
        # torch.func when a jvp and a jacfwd of the function run in one vmap (torch
        # 2.13 raised "INTERNAL ASSERT FAILED ... escaped?").
        if not hasattr(self, "_packed_np"):
            self._packed_np = self._packed()
        a = torch.as_tensor(self._packed_np, dtype=like.dtype, device=like.device)
        per_body = [
            dict(
                r0=row[0:9].reshape(3, 3),
                p0=row[9:12],
                axis=row[12:15],
                k=row[15:24].reshape(3, 3),
                k2=row[24:33].reshape(3, 3),
                r0_axis=row[33:36],
            )
            for row in a[:-1]
        ]
        return per_body, a[-1, 0:3], a[-1, 3:12].reshape(3, 3)

    def kinematics(self, q, qd):
        """Poses and body velocities: lists of ``(R, p, v, w)`` per body, in tree order.

        ``R``, ``p``: the body frame in the base frame; ``v``, ``w``: the linear
        velocity of its origin and its angular velocity, in the body frame.
        """
        per_body, _, eye = self._consts(q)
        out = []
        for b, c in zip(self.tree.bodies, per_body):
            qc, qdc = q[..., b.coordinate], qd[..., b.coordinate]
            if b.type == "revolute":
                s, co = torch.sin(qc)[..., None, None], torch.cos(qc)[..., None, None]
                r_pc = c["r0"] @ (eye + s * c["k"] + (1.0 - co) * c["k2"])
                p_pc = c["p0"].expand(*qc.shape, 3)
            else:
                r_pc = c["r0"].expand(*qc.shape, 3, 3)
                p_pc = c["p0"] + c["r0_axis"] * qc[..., None]
            joint_rate = c["axis"] * qdc[..., None]
            if b.parent < 0:
                rot, pos = r_pc, p_pc
                w = joint_rate if b.type == "revolute" else torch.zeros_like(joint_rate)
                v = (
                    joint_rate
                    if b.type == "prismatic"
                    else torch.zeros_like(joint_rate)
                )
            else:
                r_p, p_p, v_p, w_p = out[b.parent]
                rot = r_p @ r_pc
                w = _rotate_t(r_pc, w_p)
                v = _rotate_t(r_pc, v_p + _cross(w_p, p_pc))
                pos = p_p + _rotate(r_p, p_pc)
                if b.type == "revolute":
                    w = w + joint_rate
                else:
                    v = v + joint_rate
            out.append((rot, pos, v, w))
        return out

    def fn_batch(self, q, qd):
        """Term values for many samples: (n_samples, n_dof) -> (n_samples, n_terms).

        Works over any leading batch shape (``()`` for one sample).
        """
        _, g, _ = self._consts(q)
        parts = []
        for rot, pos, v, w in self.kinematics(q, qd):
            g_body = _rotate_t(rot, g)
            m_term = 0.5 * (v * v).sum(-1) + (pos * g).sum(-1)
            h_terms = _cross(v, w) + g_body
            wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
            i_terms = torch.stack(
                [
                    0.5 * wx * wx,
                    wx * wy,
                    0.5 * wy * wy,
                    wx * wz,
                    wy * wz,
                    0.5 * wz * wz,
                ],
                dim=-1,
            )
            parts += [m_term[..., None], h_terms, i_terms]
        if self.armature:
            parts.append(0.5 * qd * qd)
        return torch.cat(parts, dim=-1)

    def columns(self, q, qd, qdd):
        """Euler-Lagrange columns of the terms, (n_samples, n_dof, n_terms), fast.

        The joint torque regressor by the Newton-Euler recursion
        (:func:`lagsindy.robots.regressor.joint_torque_regressor`): equal to the
        ``torch.func`` columns of :meth:`fn` to round-off, without differentiating.
        """
        from .regressor import joint_torque_regressor

        n = q.shape[0] if q.ndim > 1 else 0
        with _one_thread(q):
            if n <= COLUMN_CHUNK:
                return joint_torque_regressor(self, q, qd, qdd)
            # chunks keep the recursion's temporaries in the processor's cache
            return torch.cat(
                [
                    joint_torque_regressor(
                        self,
                        q[s : s + COLUMN_CHUNK],
                        qd[s : s + COLUMN_CHUNK],
                        qdd[s : s + COLUMN_CHUNK],
                    )
                    for s in range(0, n, COLUMN_CHUNK)
                ]
            )

    def numpy_dynamics(self, coef, indices=None):
        """The model ``L = sum_k coef[k] phi_k`` as a NumPy function of the states.

        Its Lagrangian is a rigid-body tree's whose link parameters (and rotor
        inertias) are the coefficients, so the rigid-body algorithms evaluate it
        (:class:`~lagsindy.robots.dynamics.RigidBodyDynamics`): the same mass matrix
        and bias as the torch terms to round-off, at a fraction of the cost per call
        on one or a few states (what simulation needs).

        Parameters
        ----------
        coef : array-like of shape (n_terms,) or (len(indices),)
        indices : sequence of int, optional
            The terms ``coef`` belongs to (a subset's, :class:`BaseTerms`); the
            other terms' coefficients are 0.

        Returns
        -------
        RigidBodyDynamics
            ``f(q, qd) -> (M, h)`` with ``M`` (n, n_dof, n_dof) and ``h`` (n, n_dof).
        """
        from .dynamics import RigidBodyDynamics

        coef = np.asarray(coef, dtype=float).ravel()
        idx = np.arange(self.n_terms) if indices is None else np.asarray(indices, int)
        if coef.shape != idx.shape:
            raise ValueError(
                f"coef must have one entry per term ({idx.size}), got {coef.shape}"
            )
        full = np.zeros(self.n_terms)
        np.add.at(full, idx, coef)
        k = 10 * len(self.tree.bodies)
        rotor = full[k:] if self.armature else None
        return RigidBodyDynamics(self.tree, full[:k], rotor, self.gravity)

    def fn(self, q, qd):
        """Term values for one sample: (n_dof,), (n_dof,) -> (n_terms,)."""
        return self.fn_batch(q, qd)

    __call__ = fn

    def energies(self, q, qd, parameters):
        """Kinetic and potential energy for given parameters, (n_samples,) each.

        ``parameters`` has one value per term (``len(names)``).
        """
        p = torch.as_tensor(
            np.asarray(parameters, float), dtype=q.dtype, device=q.device
        )
        kin_only = self.fn_batch(q, qd) - self.fn_batch(q, torch.zeros_like(qd))
        kinetic = kin_only @ p
        potential = -(self.fn_batch(q, torch.zeros_like(qd)) @ p)
        return kinetic, potential


def euler_lagrange_columns(fn, q, qd, qdd, chunk_size: int = 8192) -> torch.Tensor:
    """Euler-Lagrange columns of a term function: (n_samples, n_dof, n_terms).

    ``d/dt (d phi / d qd) - d phi / d q`` by ``torch.func``: one forward Jacobian over
    ``qd`` differentiated along ``(qd, qdd)`` by a Jacobian-vector product (the
    Hessians are never formed), vmapped over samples.
    """
    grad_qd = jacfwd(fn, argnums=1)

    def one(q1, qd1, qdd1):
        _, total = jvp(grad_qd, (q1, qd1), (qd1, qdd1))
        return (total - jacfwd(fn, argnums=0)(q1, qd1)).transpose(0, 1)

    batched = vmap(one)
    n = q.shape[0]
    with warnings.catch_warnings():
        # torch's own notice when forward AD first loads, not the caller's concern
        warnings.filterwarnings("ignore", message=".*torch.jit.script.*is deprecated")
        parts = [
            batched(
                q[s : s + chunk_size], qd[s : s + chunk_size], qdd[s : s + chunk_size]
            )
            for s in range(0, n, chunk_size)
        ]
    return torch.cat(parts, dim=0)
