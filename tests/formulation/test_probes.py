"""Fits with forces and no dissipation library report friction and damping they miss
(lagsindy.formulation.probes)."""

import dataclasses
import warnings

import numpy as np
import pytest

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.formulation import UnmodelledForceWarning
from lagsindy.formulation import probes as probes_module
from lagsindy.formulation.probes import (
    EXPLAINED_FLOOR,
    NAMED_SHARE,
    RESIDUAL_FLOOR,
    ROWS_PER_PROBE,
    UNMODELLED_SHARE,
    ProbeResult,
    enough_equations,
    named_enough,
    warn_unmodelled,
    without_probes,
)
from lagsindy.joint import conservative_fits
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
)


def _data(system):
    return make_dataset(
        system, n_trajectories=4, duration=3.0, excitation="sincos", noise=1e-3,
        protocol="sensor", random_state=0,
    )  # fmt: skip


@pytest.fixture(scope="module")
def damped():
    system = double_pendulum().with_damping(viscous={"theta1": 0.3})
    return system, _data(system)


def _fit(system, data, library=None, passive=False, **params):
    """The fit (without tau if ``passive``), its warnings, and the probe result it
    computed."""
    seen = []
    original = probes_module.probe_forces

    def spy(*args, **kwargs):
        seen.append(original(*args, **kwargs))
        return seen[-1]

    import lagsindy.pipeline as estimator_module

    # the conservative fit and its warning (a fit with forces that the probes find
    # dominated by damping is otherwise redone jointly: tests/test_joint.py)
    with pytest.MonkeyPatch.context() as mp, conservative_fits():
        mp.setattr(estimator_module, "probe_forces", spy)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            est = LagrangianSINDy(library or system.paper_library(), **params).fit(
                data.X, None if passive else data.tau, groups=data.groups
            )
    return est, caught, seen[-1] if seen else None


def _unmodelled(caught):
    return [str(w.message) for w in caught if w.category is UnmodelledForceWarning]


def test_missing_joint_damping_is_reported_with_its_coefficient(damped):
    """Viscous damping 0.3 at joint 1, fitted without a dissipation library: the
    conservative fit was 35-41 % low without a word; now the fit names the force."""
    est, caught, result = _fit(*damped)
    # measured: the kept terms' least-squares residual 0.134 -> 3.1e-4 with the
    # probes (share 0.998); viscous(theta1) alone named, refitted at 0.29977
    assert result.share == pytest.approx(0.998, abs=0.002)
    assert list(result.named) == ["viscous(theta1)"]
    assert result.named["viscous(theta1)"] == pytest.approx(0.3, rel=1e-3)
    (message,) = _unmodelled(caught)
    assert "viscous(theta1) = 0.3" in message
    assert "dissipation=DissipationLibrary" in message
    assert "adds energy" not in message
    # the general "not a model of these data" warning is not repeated
    assert not any("sum of squares unexplained" in str(w.message) for w in caught)


def test_missing_coulomb_friction_is_named():
    system = cart_pendulum().with_damping(coulomb={"x": 0.2})
    est, caught, result = _fit(system, _data(system))
    # measured: share 0.986, coulomb(x) refitted at 0.1994
    assert result.share == pytest.approx(0.986, abs=0.005)
    assert list(result.named) == ["coulomb(x)"]
    assert result.named["coulomb(x)"] == pytest.approx(0.2, rel=0.01)
    assert len(_unmodelled(caught)) == 1


def test_two_missing_forces_are_both_named():
    """Probes are named one at a time until they explain what every probe explains:
    the best one alone (viscous(theta1), residual 0.040) is not enough here."""
    system = double_pendulum().with_damping(
        viscous={"theta1": 0.3}, coulomb={"theta2": 0.2}
    )
    est, caught, result = _fit(system, _data(system))
    # measured: residual 0.158 -> 0.00484 with viscous(theta1) = 0.2933 and
    # coulomb(theta2) = 0.1989 (0.00475 with every probe)
    assert list(result.named) == ["viscous(theta1)", "coulomb(theta2)"]
    np.testing.assert_allclose(list(result.named.values()), [0.3, 0.2], rtol=0.03)
    assert result.named_residual == pytest.approx(0.00484, rel=0.02)
    (message,) = _unmodelled(caught)
    assert "viscous(theta1) = 0.293, coulomb(theta2) = 0.199" in message


def test_a_conservative_system_is_not_reported():
    system = double_pendulum()
    est, caught, result = _fit(system, _data(system))
    # measured: share 0.0037 (over 58 fits of right models up to noise 0.1: <= 0.40)
    assert result.share < 0.02
    assert not _unmodelled(caught)


def test_probes_leave_the_fit_unchanged(damped):
    """The Lagrangian is fitted on the same columns as without probes: the weak
    form's Gram blocks are the same numbers, so the coefficients are equal."""
    system, data = damped
    est, _, result = _fit(system, data)
    with without_probes():
        plain, caught, none = _fit(system, data)
    assert none is None and not _unmodelled(caught)
    np.testing.assert_array_equal(est.coef_, plain.coef_)
    assert est.residual_ == plain.residual_


def test_a_dissipation_library_turns_the_probes_off(damped):
    system, data = damped
    est, caught, result = _fit(system, data, dissipation=DissipationLibrary())
    assert result is None and not _unmodelled(caught)
    # with the library the damping is fitted (measured 0.2998)
    assert est.dissipation_coef_[0] == pytest.approx(0.3, rel=1e-3)


def _passive(system, seed=0):
    return make_dataset(
        system, n_trajectories=4, duration=3.0, excitation=None, noise=1e-3,
        protocol="sensor", random_state=seed,
    )  # fmt: skip


def _fit_passive(system, data):
    return _fit(system, data, passive=True)


def test_passive_damping_is_reported_in_the_fits_scale():
    """Case III: the fixed term's column is the target, and the coefficient is in
    the scale where it is 1 (theta_dot**2 = 1 is twice the physical 0.5)."""
    system = single_pendulum().with_damping(viscous={"theta": 0.05})
    est, caught, result = _fit_passive(system, _passive(system))
    assert est.case_ == "fixed" and result.passive
    # measured: share 0.9929; viscous(theta) = 0.1002 in the scale theta_dot**2 = 1
    assert result.share == pytest.approx(0.993, abs=0.003)
    assert est.coef_table().set_index("term")["coefficient"]["theta_dot**2"] == 1.0
    assert result.named == pytest.approx({"viscous(theta)": 0.1}, rel=0.01)
    (message,) = _unmodelled(caught)
    assert "relative to the column of the term whose coefficient is 1" in message
    assert "does not lose energy" in message and "tau" not in message


def test_small_dissipative_damping_is_reported_below_the_floor():
    """Viscous damping 0.01 on a passive pendulum explains 1.3e-5 of the fixed
    term's column, under EXPLAINED_FLOOR: reported because the force is dissipative
    against the fitted (positive) kinetic energy."""
    system = single_pendulum().with_damping(viscous={"theta": 0.01})
    est, caught, result = _fit_passive(system, _passive(system))
    # measured: 1.51e-5 -> 2.18e-6 (share 0.856), viscous(theta) = 0.0202 (0.02 in
    # the scale theta_dot**2 = 1)
    assert result.residual - result.probed < EXPLAINED_FLOOR
    assert result.share == pytest.approx(0.856, abs=0.01)
    assert result.named == pytest.approx({"viscous(theta)": 0.02}, rel=0.03)
    assert est.mass_check_.negative == 0.0
    assert len(_unmodelled(caught)) == 1


def test_a_conservative_passive_system_is_not_reported():
    system = double_pendulum()
    est, caught, result = _fit_passive(system, _passive(system))
    # measured: share 0.0099 (right passive models up to noise 0.1: <= 0.37)
    assert result.share < 0.02
    assert not _unmodelled(caught)


def test_too_few_equations_are_not_probed():
    """3 weak-form windows of a pendulum and a 2-term model: two probes fitted its
    residual exactly (3e-15) and the fit warned of a friction force it cannot see."""
    data = make_dataset(single_pendulum(), n_trajectories=3, duration=1.0,
                        random_state=0)  # fmt: skip
    library = CandidateLibrary.from_terms(["theta"], ["theta_dot**2", "theta**2"])
    est, caught, result = _fit(single_pendulum(), data, library=library)
    assert est.formulation_ == "weak" and result is None
    assert not _unmodelled(caught)


def test_the_warning_needs_a_share_and_an_amount():
    big = ProbeResult(0.1, 0.01, {"viscous(q)": -0.5}, 0.01)
    assert big.reported() and big.reported(-1.0)  # above the floor: any sign
    assert not ProbeResult(0.1, 0.06, {"viscous(q)": 0.5}, 0.06).missing
    # below EXPLAINED_FLOOR: only dissipative forces (against the kinetic sign)
    small = ProbeResult(1.6 * EXPLAINED_FLOOR, 0.7 * EXPLAINED_FLOOR, {}, 0.0)
    assert small.missing and not small.reported()
    damping = dataclasses.replace(small, named={"viscous(q)": 0.1, "coulomb(q)": 0.2})
    assert damping.reported() and not damping.reported(-1.0)
    mixed = dataclasses.replace(small, named={"viscous(q)": -0.1, "coulomb(q)": 0.2})
    assert not mixed.reported()
    rounding = ProbeResult(
        1.8 * RESIDUAL_FLOOR, 0.9 * RESIDUAL_FLOOR, {"viscous(q)": 0.1}, 0.0
    )
    assert not rounding.missing
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_unmodelled(mixed) is False
        assert warn_unmodelled(rounding) is False
        assert warn_unmodelled(None) is False


def test_probes_weight_the_equations_as_the_fit_did(damped):
    """The check reuses the fit's row scales instead of balancing again (the
    balance iterations were 1 of its 1.6 ms)."""
    import torch

    from lagsindy.formulation.scaling import BalancedGram

    gram = torch.tensor(np.diag([1.0, 4.0, 9.0])).repeat(2, 1, 1)
    gram[1] *= 100.0
    fresh = BalancedGram(gram, 10, 2)
    given = BalancedGram(gram, 10, 2, row_scale=fresh.row_scale)
    torch.testing.assert_close(given.gram, fresh.gram, rtol=0, atol=0)
    other = BalancedGram(gram, 10, 2, row_scale=torch.ones(2, dtype=gram.dtype))
    assert not torch.allclose(other.gram, fresh.gram)

    seen = []
    original = probes_module.probe_forces

    def spy(stats, coef, normalize=True, fixed=None, row_scale=None):
        seen.append(row_scale)
        return original(stats, coef, normalize, fixed, row_scale)

    import lagsindy.pipeline as estimator_module

    system, data = damped
    with pytest.MonkeyPatch.context() as mp, conservative_fits():
        mp.setattr(estimator_module, "probe_forces", spy)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            LagrangianSINDy(system.paper_library()).fit(
                data.X, data.tau, groups=data.groups
            )
    (rows,) = seen
    assert rows is not None and rows.shape == (2,) and bool((rows > 0).all())


def test_the_warning_class_is_public():
    import lagsindy

    assert lagsindy.UnmodelledForceWarning is UnmodelledForceWarning
    assert issubclass(UnmodelledForceWarning, UserWarning)


def test_negative_damping_points_at_sign_and_delay():
    result = ProbeResult(0.1, 0.01, {"viscous(q)": -0.5}, 0.01)
    with pytest.warns(UnmodelledForceWarning, match="adds energy") as record:
        assert warn_unmodelled(result) is True
    assert "estimate_delay" in str(record[0].message)


def test_case_ii_reports_missing_damping_in_its_own_scale():
    """Case II (``case="acceleration"``) is probed as case III is, against its unit
    term's column; before, a damped pendulum fitted by case II warned of nothing.
    A unit term of coefficient -1 reports the coefficients in the fit's scale."""
    system = single_pendulum().with_damping(viscous={"theta": 0.05})
    data = _passive(system)
    calls = []
    original = probes_module.probe_forces
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(
            probes_module, "probe_forces", lambda *a: calls.append(a) or original(*a)
        )
        est, caught, result = _fit(system, data, passive=True, case="acceleration")
    assert est.case_ == "acceleration" and result.passive
    coef = est.coef_table().set_index("term")["coefficient"]
    assert coef["theta_dot**2"] == 1.0  # the unit term: the probes' target
    # measured: share 0.615 (case II's strong form keeps the accelerations' noise;
    # case III's weak form 0.993); viscous(theta) = 0.1034 where theta_dot**2 = 1
    assert result.share == pytest.approx(0.615, abs=0.02)
    assert result.named == pytest.approx({"viscous(theta)": 0.1}, rel=0.05)
    (message,) = _unmodelled(caught)
    assert "relative to the column of the term whose coefficient is 1" in message

    # The same model with the opposite sign (unit term -1): the force flips with it.
    from lagsindy.formulation.probes import probe_term

    (stats, coef, normalize, fixed, row_scale) = calls[-1]
    assert fixed == probe_term("acceleration", coef, None)
    flipped = original(stats, -coef, normalize, fixed, row_scale)
    assert flipped.named == pytest.approx({"viscous(theta)": -0.1}, rel=0.05)
    assert flipped.share == result.share


def test_probe_term_picks_the_passive_fits_unit_term():
    from lagsindy.formulation.probes import probe_term

    # raw coefficients may exceed 1: the gauge sets the largest *scaled* one
    coef = np.array([0.0, 4.0, -1.0, 1.0, 0.2])
    assert probe_term("acceleration", coef, None) == 2  # the first of +-1
    assert probe_term("fixed", coef, 4) == 4  # case III: its fixed term
    assert probe_term("forces", coef, None) is None
    assert probe_term("acceleration", np.zeros(3), None) is None
    assert probe_term("acceleration", np.array([0.5, -0.7]), None) == 1  # no unit


# ------------------------------------------------------- thresholds at their boundary
@pytest.mark.parametrize(
    "probed, missing",
    [
        (1 - UNMODELLED_SHARE, True),  # the probes explain exactly the share
        (1 - UNMODELLED_SHARE + 1e-9, False),
        (1 - 0.75 * UNMODELLED_SHARE, False),
    ],
)
def test_the_probes_must_explain_the_unmodelled_share(probed, missing):
    result = ProbeResult(1.0, probed, {"viscous(q)": 0.1}, probed)
    assert result.missing is missing
    assert result.reported() is missing


@pytest.mark.parametrize(
    "gain, missing", [(RESIDUAL_FLOOR, True), (RESIDUAL_FLOOR * (1 - 1e-6), False)]
)
def test_what_the_probes_explain_must_reach_the_rounding_floor(gain, missing):
    result = ProbeResult(2 * gain, gain, {"viscous(q)": 0.1}, gain)  # share 1/2
    assert result.gain == gain and result.share == 0.5
    assert result.missing is missing


@pytest.mark.parametrize(
    "gain, reported",
    [(EXPLAINED_FLOOR, True), (EXPLAINED_FLOOR * (1 - 1e-6), False)],
)
def test_forces_of_either_sign_are_reported_from_the_explained_floor(gain, reported):
    """A force that adds energy (negative against a positive kinetic energy) is
    reported when the probes explain at least EXPLAINED_FLOOR; a dissipative one
    below it too."""
    feeding = ProbeResult(2 * gain, gain, {"viscous(q)": -0.1}, gain)
    assert feeding.missing
    assert feeding.reported() is reported
    assert feeding.reported(-1.0)  # dissipative against a negative kinetic energy
    dissipative = dataclasses.replace(feeding, named={"viscous(q)": 0.1})
    assert dissipative.reported()


@pytest.mark.parametrize(
    "current, enough",
    [
        (NAMED_SHARE, True),  # what is left is exactly the named share
        (NAMED_SHARE * (1 + 1e-9), False),
        (0.0, True),
    ],
)
def test_probes_are_named_until_all_but_the_named_share_is_explained(current, enough):
    # every probe together: residual 0 (probed), explaining 1 (gain)
    assert named_enough(current, 0.0, 1.0) is enough
    assert named_enough(4 * current, 0.0, 4.0) is enough  # scaled by a power of 2


@pytest.mark.parametrize("spare, enough", [(0.0, True), (-1e-9, False)])
def test_each_probe_needs_its_rows_beyond_the_kept_terms(spare, enough):
    for n_support, n_probes in ((2, 2), (6, 4)):
        independent = n_support + ROWS_PER_PROBE * n_probes + spare
        assert enough_equations(independent, n_support, n_probes) is enough
