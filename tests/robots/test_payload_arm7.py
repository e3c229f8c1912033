"""The payload on the 7-joint arm (issue #42): simulated with pinocchio's inverse
dynamics of a copy of the URDF with a 1 kg point mass on the last link (the quick
benchmark's 10 s record, 1 kHz, 1e-4 rad and 1 % torque noise, filtered as the
benchmark filters), fitted with the URDF's link parameters held."""

from __future__ import annotations

import time
import warnings

import numpy as np
import pytest

pytest.importorskip("pinocchio")
pytest.importorskip("scipy.signal")

from benchmarks.robots import EDGE, filtered_states  # noqa: E402
from benchmarks.robots_data import ARM7, ARM7_JOINTS, simulate  # noqa: E402
from lagsindy import (  # noqa: E402
    CandidateLibrary,
    DissipationLibrary,
    LagrangianSINDy,
    diagnose,
)
from lagsindy.robots import FRICTION_KINDS, ROBOT_CATALOGUE  # noqa: E402

LOCKED = {"finger_joint1": 0.02}
CENTRE = (0.02, -0.03, 0.15)  # m in link7's frame


def arm_record(tmp_path, mass):
    text = ARM7.read_text()
    load = f"""<link name="load"><inertial><origin xyz="0 0 0"/><mass value="{mass}"/>
  <inertia ixx="0" ixy="0" ixz="0" iyy="0" iyz="0" izz="0"/></inertial></link>
  <joint name="load_mount" type="fixed"><parent link="link7"/><child link="load"/>
  <origin xyz="{CENTRE[0]} {CENTRE[1]} {CENTRE[2]}"/></joint></robot>"""
    path = tmp_path / "arm7_loaded.urdf"
    path.write_text(text.replace("</robot>", load) if mass else text)
    data = simulate(
        path, ARM7_JOINTS, LOCKED, duration=10.0, rate=1000.0,
        armature=np.array([0.30, 0.30, 0.25, 0.25, 0.10, 0.10, 0.05]),
        viscous=np.array([0.60, 0.80, 0.50, 0.60, 0.20, 0.25, 0.10]),
        coulomb=np.array([0.80, 1.00, 0.70, 0.80, 0.40, 0.35, 0.30]),
        offset=np.array([0.10, -0.20, 0.05, 0.15, -0.05, 0.02, 0.04]),
        spring=None, noise_q=1e-4, noise_tau_rel=0.01, random_state=0,
    )  # fmt: skip
    q, qd, qdd, tau = (x[EDGE:-EDGE] for x in filtered_states(data.t, data.q, data.tau))
    return np.hstack([q, qd, qdd]), tau


def held_fit(X, tau):
    lib = CandidateLibrary.from_urdf(ARM7, ARM7_JOINTS, locked=LOCKED, inertia="urdf")
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(list(FRICTION_KINDS)), formulation="strong"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return est.fit(X, tau)


CATALOGUE = [k for k in ROBOT_CATALOGUE if k != "joint_delay"]


@pytest.mark.slow  # 50 s CPU of diagnose (measured; 28 s without a payload)
@pytest.mark.parametrize("mass", [1.0, 0.0])
def test_arm7_payload(tmp_path, mass):
    X, tau = arm_record(tmp_path, mass)
    est = held_fit(X, tau)
    start = time.process_time()
    report = diagnose(est, X, tau, catalogue=CATALOGUE)
    print(f"diagnose: {time.process_time() - start:.1f} s CPU")
    if not mass:
        assert report.payload is None and report.effects == []
        return
    found = report.payload
    assert report.effects == ["payload(link7)"]
    # measured 0.9968 +- 0.0020 kg, centre (0.0192, -0.0304, 0.1489) m: all 10 of
    # the last link's parameters are identifiable on this arm
    assert found["mass"] == pytest.approx(mass, rel=0.02)
    assert np.allclose(found["com"], CENTRE, atol=5e-3)
    assert len(report.final.library_.payload_.kinds) == 10
