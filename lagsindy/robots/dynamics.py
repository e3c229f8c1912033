r"""A robot's forward dynamics on a few states at a time: rigid-body algorithms, NumPy.

Simulating a fitted robot model evaluates its mass matrix ``M(q)`` and bias
``h(q, qd)`` on one state (or a few) per right-hand-side call. The torch term
functions (:class:`~lagsindy.robots.RobotTerms`: the Newton-Euler regressor or
autograd) pay torch's per-operation overhead on every call (measured: about 15 ms per
call of a 2-link model). The Lagrangian ``sum_k c_k phi_k`` of the robot's terms is
that of a rigid-body tree whose link parameters are the coefficients (a term's
coefficient is its link parameter; terms left out are zero), so this module
evaluates it by the spatial-vector algorithms instead, in float64 NumPy:

* the poses of all bodies by composing each joint's homogeneous transform with its
  parent's (the only loop over bodies);
* everything else at once over all bodies, in the base frame: joint screws
  ``S_j``, body velocities ``v_i = sum_{j <= i} S_j qd_j`` (ancestor mask),
  velocity-product accelerations ``a_i = -g + sum_{j <= i} (v_j x S_j) qd_j``,
  inertias in the base frame, body wrenches
  ``f_i = I_i a_i + v_i x* I_i v_i`` and the torques ``tau_j = S_j . sum_{i >= j}
  f_i`` (the recursive Newton-Euler algorithm's bias ``h`` with ``qdd = 0``);
* the mass matrix from the composite inertias ``Ic_j = sum_{i >= j} I_i``:
  ``M_jk = S_j . Ic_k S_k`` for ``j`` an ancestor of (or equal to) ``k`` (the
  composite rigid body algorithm), plus the rotor inertias on the diagonal.

Spatial vectors are ordered (angular, linear), Featherstone's convention. A body's
10 parameters are pinocchio's ``m, m c_x, m c_y, m c_z, Ixx, Ixy, Iyy, Ixz, Iyz,
Izz`` (inertia about the body frame's origin), as in :mod:`.energy`. Every array
carries the states as a leading dimension, so a batch of trajectories costs one call.
"""

from __future__ import annotations

import numpy as np

CHUNK = 2048  # states per evaluation of RigidBodyDynamics (memory, not speed)

# Levi-Civita: cross(a, b)_i = sum_jk EPS[i, j, k] a_j b_k; skew(a) = a @ SKEW
_EPS = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _EPS[_i, _j, _k], _EPS[_i, _k, _j] = 1.0, -1.0
_SKEW = _EPS.transpose(1, 0, 2).reshape(3, 9)  # skew(a).ravel() = a @ _SKEW
# crm(v).ravel() = v @ _CRM for the spatial motion cross product v x m = crm(v) m
_CRM = np.zeros((6, 6, 6))
for _a in range(3):
    _s = _SKEW[_a].reshape(3, 3)
    _CRM[_a, :3, :3] = _s  # w x
    _CRM[_a, 3:, 3:] = _s
    _CRM[3 + _a, 3:, :3] = _s  # v0 x (angular part)
_CRM = _CRM.reshape(6, 36)
# Y.ravel() = [E.ravel(), (E [p]x).ravel()] @ _Y_MAP for the motion transform from
# the base frame to a body's, Y = [[E, 0], [-E [p]x, E]]
_Y_MAP = np.zeros((18, 6, 6))
for _r in range(3):
    for _c in range(3):
        _Y_MAP[3 * _r + _c, _r, _c] = _Y_MAP[3 * _r + _c, 3 + _r, 3 + _c] = 1.0
        _Y_MAP[9 + 3 * _r + _c, 3 + _r, _c] = -1.0
_Y_MAP = _Y_MAP.reshape(18, 36)


def _skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def spatial_inertia(parameters) -> np.ndarray:
    """The 6 x 6 spatial inertia (about the body origin) of 10 inertial parameters.

    ``[[I_o, [h]x], [-[h]x, m 1]]`` with ``h = m c`` and ``I_o`` the rotational inertia
    about the origin; linear in the parameters, so any values (physically consistent
    or not) give the Lagrangian ``sum_k pi_k phi_k`` of :mod:`.energy`.
    """
    m, hx, hy, hz, ixx, ixy, iyy, ixz, iyz, izz = (float(v) for v in parameters)
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    hs = _skew([hx, hy, hz])
    out = np.zeros((6, 6))
    out[:3, :3], out[:3, 3:], out[3:, :3] = inertia, hs, -hs
    out[3:, 3:] = m * np.eye(3)
    return out


class RigidBodyDynamics:
    """Mass matrix and bias of a robot tree with given link parameters, in NumPy.

    Parameters
    ----------
    tree : RobotTree
        The kinematic tree (:func:`lagsindy.robots.build_tree`).
    parameters : array-like of shape (10 * n_bodies,)
        Every body's 10 inertial parameters (:meth:`RobotTree.parameters`' layout).
    armature : array-like of shape (n_dof,), optional
        Rotor inertias, added to the mass matrix's diagonal (default 0).
    gravity : sequence of 3 float, default=(0, 0, -9.81)
        Gravity in the base frame.

    Attributes
    ----------
    calls : int
        How many times the dynamics was evaluated (one per call, whatever the number
        of states): what tells a test that a simulation took this path.

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.robots import build_tree, example_urdf
    >>> from lagsindy.robots.dynamics import RigidBodyDynamics
    >>> tree = build_tree(example_urdf("planar2"))
    >>> dyn = RigidBodyDynamics(tree, tree.parameters())
    >>> mass, bias = dyn(np.zeros((1, 2)), np.zeros((1, 2)))
    >>> mass.shape, bias.shape
    ((1, 2, 2), (1, 2))
    """

    def __init__(self, tree, parameters, armature=None, gravity=(0.0, 0.0, -9.81)):
        bodies = tree.bodies
        nb, d = len(bodies), tree.n_dof
        parameters = np.asarray(parameters, dtype=float).reshape(nb, 10)
        self.n_dof, self.n_bodies = d, nb
        self.calls = 0
        self.parent = [b.parent for b in bodies]
        self.coordinate = np.array([b.coordinate for b in bodies], dtype=int)
        # Local transform of body i (child frame in parent frame, homogeneous 4 x 4)
        # T_i = C0 + sin(q) C1 + (1 - cos(q)) C2 + q C3: linear in those, so all
        # bodies' are one product with a (n, nb, 1, 4) array of [1, s, 1-c, q].
        local = np.zeros((nb, 4, 16))
        axes = np.zeros((nb, 3))
        revolute = np.zeros(nb)
        for i, b in enumerate(bodies):
            r0 = np.asarray(b.rotation, float)
            p0 = np.asarray(b.translation, float)
            axis = np.asarray(b.axis, float)
            k = _skew(axis)
            base = np.eye(4)
            base[:3, :3], base[:3, 3] = r0, p0
            local[i, 0] = base.ravel()
            if b.type == "revolute":
                revolute[i] = 1.0
                for row, gen in ((1, r0 @ k), (2, r0 @ k @ k)):
                    t = np.zeros((4, 4))
                    t[:3, :3] = gen
                    local[i, row] = t.ravel()
            else:
                t = np.zeros((4, 4))
                t[:3, 3] = r0 @ axis
                local[i, 3] = t.ravel()
            axes[i] = axis
        self._local = local
        self._axes = axes  # joint axes in the body frames
        # a joint's screw in the base frame from its axis u = R a and the outer
        # product p u^T: revolute [u; p x u], prismatic [0; u]
        screw_map = np.zeros((nb, 12, 6))
        for i in range(nb):
            if revolute[i]:
                screw_map[i, np.arange(3), np.arange(3)] = 1.0
                screw_map[i, 3:, 3:] = _EPS.transpose(1, 2, 0).reshape(9, 3)
            else:
                screw_map[i, np.arange(3), 3 + np.arange(3)] = 1.0
        self._screw_map = screw_map
        self._inertia = np.stack([spatial_inertia(p) for p in parameters])
        # ancestor[i, j]: body j is body i or one of its ancestors
        ancestor = np.eye(nb)
        for i, b in enumerate(bodies):
            if b.parent >= 0:
                ancestor[i] += ancestor[b.parent]
        self._ancestor = ancestor
        self._descendant = np.ascontiguousarray(ancestor.T)
        # M_jk = S_j . Ic_k S_k when j <= k in the tree; the other triangle by symmetry
        # [j, k]: body j is body k or one of its ancestors
        self._upper = np.ascontiguousarray(ancestor.T)
        self._strict = self._upper - np.eye(nb)
        arm = np.zeros(d) if armature is None else np.asarray(armature, float)
        self._armature = np.diag(arm.reshape(d))
        g = np.asarray(gravity, dtype=float).reshape(3)
        self._gravity_acc = np.concatenate([np.zeros(3), -g])  # base accelerates at -g
        order = self.coordinate
        self._identity_order = bool(np.array_equal(order, np.arange(d)))
        self._order = np.argsort(order)  # body of each coordinate

    def kinematics(self, q):
        """Rotations ``R`` (n, nb, 3, 3) and positions ``p`` (n, nb, 3) of the bodies
        in the base frame."""
        n = q.shape[0]
        qb = q[:, self.coordinate]  # (n, nb)
        weights = np.stack([np.ones_like(qb), np.sin(qb), 1.0 - np.cos(qb), qb], -1)
        local = (weights[:, :, None, :] @ self._local)[:, :, 0].reshape(n, -1, 4, 4)
        world = np.empty((n, self.n_bodies, 4, 4))
        for i, parent in enumerate(self.parent):
            if parent < 0:
                world[:, i] = local[:, i]
            else:
                np.matmul(world[:, parent], local[:, i], out=world[:, i])
        return world[..., :3, :3], world[..., :3, 3]

    def __call__(self, q, qd):
        """``M`` (n, n_dof, n_dof) and ``h`` (n, n_dof) at the states ``q``, ``qd``
        (n, n_dof), so that ``M qdd + h`` are the joint torques (gravity included)."""
        self.calls += 1
        q = np.asarray(q, dtype=float)
        qd = np.asarray(qd, dtype=float)
        if q.shape[0] > CHUNK:  # bounded temporaries (a few 6 x 6 per body and state)
            parts = [
                self._evaluate(q[s : s + CHUNK], qd[s : s + CHUNK])
                for s in range(0, q.shape[0], CHUNK)
            ]
            return tuple(np.concatenate(p) for p in zip(*parts))
        return self._evaluate(q, qd)

    def _evaluate(self, q, qd):
        n, nb = q.shape[0], self.n_bodies
        rot, pos = self.kinematics(q)
        # joint screws in the base frame: revolute [R a; p x R a], prismatic [0; R a]
        axis = (rot @ self._axes[:, :, None])[..., 0]  # (n, nb, 3)
        outer = (pos[..., :, None] * axis[..., None, :]).reshape(n, nb, 9)
        screw = (np.concatenate([axis, outer], -1)[..., None, :] @ self._screw_map)[
            ..., 0, :
        ]  # (n, nb, 6)
        # inertias in the base frame: I_w = Y^T I Y, Y = X_(i <- 0)
        rt = np.swapaxes(rot, -1, -2)
        rpx = rt @ (pos @ _SKEW).reshape(n, nb, 3, 3)
        y = np.concatenate([rt.reshape(n, nb, 9), rpx.reshape(n, nb, 9)], -1) @ _Y_MAP
        y = y.reshape(n, nb, 6, 6)
        inertia = np.swapaxes(y, -1, -2) @ self._inertia @ y  # (n, nb, 6, 6)
        # composite inertias and the mass matrix (bodies' order)
        composite = (self._descendant @ inertia.reshape(n, nb, 36)).reshape(n, nb, 6, 6)
        ics = (composite @ screw[..., None])[..., 0]  # (n, nb, 6): Ic_k S_k
        pair = screw @ np.swapaxes(ics, -1, -2)  # [j, k] = S_j . Ic_k S_k
        upper = pair * self._upper
        mass = upper + np.swapaxes(pair * self._strict, -1, -2)
        # velocities, velocity-product accelerations, wrenches, torques
        rate = qd[:, self.coordinate]  # (n, nb)
        vj = screw * rate[..., None]
        vel = self._ancestor @ vj  # (n, nb, 6)
        crm = (vel @ _CRM).reshape(n, nb, 6, 6)
        acc = self._ancestor @ (crm @ vj[..., None])[..., 0] + self._gravity_acc
        momentum = (inertia @ vel[..., None])[..., 0]
        wrench = (inertia @ acc[..., None])[..., 0] - (
            np.swapaxes(crm, -1, -2) @ momentum[..., None]
        )[..., 0]
        total = self._descendant @ wrench
        bias = (screw * total).sum(-1)
        if not self._identity_order:
            o = self._order
            mass, bias = mass[:, o][:, :, o], bias[:, o]
        return mass + self._armature, bias
