"""pinocchio as the oracle of the robot regressor (tests skip without it)."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parent / "data"
PANDA_JOINTS = [f"panda_joint{i}" for i in range(1, 8)]
ARM7_JOINTS = [f"joint{i}" for i in range(1, 8)]


def example_robot(relative: str) -> str:
    """Path of a URDF shipped by the ``example-robot-data`` package, or skip."""
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("example-robot-data is not installed (pip install -e '.[robots]')")
    path = (
        Path(dist.locate_file("cmeel.prefix/share/example-robot-data/robots"))
        / relative
    )
    if not path.exists():
        pytest.skip(f"example-robot-data has no {relative}")
    return str(path)


def pinocchio_model(pin, tree):
    """pinocchio's model of the URDF with the tree's locked joints locked alike."""
    model = pin.buildModelFromUrdf(str(tree.path))
    if tree.locked:
        q0 = pin.neutral(model)
        for name, value in tree.locked.items():
            q0[model.joints[model.getJointId(name)].idx_q] = value
        model = pin.buildReducedModel(
            model, [model.getJointId(n) for n in tree.locked], q0
        )
    return model


def pinocchio_regressor(pin, model, tree, q, qd, qdd):
    """``computeJointTorqueRegressor`` in the tree's coordinate and body order.

    Returns (n_samples, n_dof, 10 * n_bodies) and the stacked dynamic parameters.
    """
    data = model.createData()
    joints = [model.joints[model.getJointId(c)] for c in tree.coordinates]
    cols = np.concatenate(
        [10 * (model.getJointId(b.joint) - 1) + np.arange(10) for b in tree.bodies]
    )
    rows = [j.idx_v for j in joints]
    out = []
    for s in range(q.shape[0]):
        qp, vp, ap = np.zeros(model.nq), np.zeros(model.nv), np.zeros(model.nv)
        for k, j in enumerate(joints):
            if j.nq == 2:  # continuous joint: (cos, sin)
                qp[j.idx_q : j.idx_q + 2] = np.cos(q[s, k]), np.sin(q[s, k])
            else:
                qp[j.idx_q] = q[s, k]
            vp[j.idx_v], ap[j.idx_v] = qd[s, k], qdd[s, k]
        y = pin.computeJointTorqueRegressor(model, data, qp, vp, ap)
        out.append(y[rows][:, cols])
    params = np.concatenate(
        [
            model.inertias[model.getJointId(b.joint)].toDynamicParameters()
            for b in tree.bodies
        ]
    )
    return np.stack(out), params
