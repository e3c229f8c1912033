"""Friction the sparse solve dropped, re-admitted when least squares without the L1
penalty finds it significant (``lagsindy.robots.fitting._significant``).

Unpenalized base parameters can take the place of a friction candidate they are
nearly collinear with: on small swings of the two-link arm, hanging in a vertical
plane, the upper arm's centre of mass acts on the shoulder like a constant offset.
"""

import warnings

import numpy as np
import pytest
from _robot_fit_data import two_sines

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.robots import FRICTION_KINDS, example_urdf, multisine
from lagsindy.robots import fitting

OFFSETS = np.array([0.1, -0.05])  # added to the torques: bias = -offset


def _fit(q, qd, qdd, tau, verbose=0):
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    est = LagrangianSINDy(
        lib,
        dissipation=DissipationLibrary(list(FRICTION_KINDS)),
        formulation="strong",
        verbose=verbose,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(np.hstack([q, qd, qdd]), tau)
    return {t.name: c for t, c in zip(est.dissipation_terms_, est.dissipation_coef_)}


def _torques(q, qd, qdd, offsets, noise=0.0, seed=0):
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    truth = lib.nominal_.copy()
    truth[-2:] = [0.02, 0.01]
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth
    tau += [0.6, 0.3] * qd + [0.4, 0.2] * np.tanh(qd / 0.01) + offsets
    rng = np.random.default_rng(seed)
    return tau + noise * tau.std(0) * rng.standard_normal(tau.shape)


@pytest.fixture(scope="module")
def docs_record():
    """docs/robots.md's 8 s noise-free record (friction of all three kinds)."""
    _, q, qd, qdd = two_sines(8.0)
    return q, qd, qdd, _torques(q, qd, qdd, OFFSETS)


def test_an_offset_taken_by_a_centre_of_mass_is_readmitted(docs_record, capsys):
    """The sparse solve drops bias(shoulder) (-0.1): the upper arm's centre of mass
    takes its place. Least squares without the penalty explains 8.6e-7 of the
    torques' sum of squares more with it (measured): re-admitted, exact."""
    coef = _fit(*docs_record, verbose=1)
    assert abs(coef["bias(shoulder)"] + 0.1) < 1e-4  # measured -0.1 to 1e-6
    assert abs(coef["bias(elbow)"] - 0.05) < 2e-3  # measured 0.0488 -> 0.05
    assert "re-admitted ['bias(shoulder)']" in capsys.readouterr().out


def test_a_term_below_the_floor_stays_dropped(docs_record, monkeypatch):
    """The floor at its boundary: 8.6e-7 of the sum of squares is above 1e-8 (the
    default) and below 1e-6."""
    monkeypatch.setattr(fitting, "READMIT_FLOOR", 1e-6)
    assert _fit(*docs_record)["bias(shoulder)"] == 0.0


def test_noisy_offsets_are_readmitted_when_significant():
    """6 s of multi-sine motion, 3 % torque noise: both offsets dropped, t^2 = 60
    and 121 against the 25 required, 1.0 % and 2.0 % of the residual against 0.5 %
    (measured): re-admitted near the true 0.1 and -0.05."""
    t = np.arange(0.0, 6.0, 0.002)
    q, qd, qdd = multisine(t, 2, random_state=0)
    coef = _fit(q, qd, qdd, _torques(q, qd, qdd, -OFFSETS, noise=0.03, seed=100))
    assert 0.07 < coef["bias(shoulder)"] < 0.12  # measured 0.088
    assert -0.07 < coef["bias(elbow)"] < -0.035  # measured -0.055


@pytest.mark.parametrize("seed, noise", [(3, 0.01), (0, 0.0)])
def test_no_offset_is_readmitted_where_there_is_none(seed, noise):
    """Records without offsets (1 % noise; none, with the library's data-driven
    Coulomb smoothing against 0.01 in the simulation): nothing re-admitted."""
    t = np.arange(0.0, 6.0, 0.002)
    q, qd, qdd = multisine(t, 2, random_state=seed)
    coef = _fit(q, qd, qdd, _torques(q, qd, qdd, 0.0, noise=noise, seed=seed))
    assert coef["bias(shoulder)"] == 0.0 and coef["bias(elbow)"] == 0.0


@pytest.mark.parametrize("sign, dissipative, kept", [(1, True, [0]), (-1, True, []),
                                                     (-1, False, [0])])  # fmt: skip
def test_a_dissipative_candidate_needs_a_physical_sign(sign, dissipative, kept):
    """A dissipative kind (viscous, Coulomb) only removes energy: a candidate whose
    least-squares coefficient is negative is not re-admitted however significant;
    an offset may take either sign."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((400, 2))  # one base parameter, one friction column
    y = a @ [1.0, 0.5 * sign] + 1e-3 * rng.standard_normal(400)
    m = np.column_stack([a, y])
    gram = m.T @ m
    coef = np.array([1.0, 0.0])  # the sparse solve dropped the friction column
    assert fitting._significant(gram, coef, 1, 400, [dissipative]) == kept


def test_a_significant_but_immaterial_candidate_stays_dropped(monkeypatch):
    """The share of the residual at its boundary: the shoulder's offset on the 6 s
    noisy record explains 1.0 % of the residual (measured), re-admitted at the
    default 0.5 %, not at 1.5 %."""
    t = np.arange(0.0, 6.0, 0.002)
    q, qd, qdd = multisine(t, 2, random_state=0)
    tau = _torques(q, qd, qdd, -OFFSETS, noise=0.03, seed=100)
    monkeypatch.setattr(fitting, "READMIT_SHARE", 0.015)
    coef = _fit(q, qd, qdd, tau)
    assert coef["bias(shoulder)"] == 0.0
    assert coef["bias(elbow)"] != 0.0  # 2.0 % of the residual: still re-admitted
