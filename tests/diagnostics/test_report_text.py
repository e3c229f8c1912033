"""The diagnosis report explains itself (#44 item 3): one legend for the force
scale, every effect of the final model in the table, notes where the criteria
disagree, and the user's units in the text and the figure."""

import warnings

import re

import numpy as np
import pytest

from lagsindy import LagrangianSINDy, diagnose
from lagsindy.diagnostics import report as report_module
from lagsindy.diagnostics.report import Candidate, DiagnosisReport, Step
from lagsindy.dissipation import DissipationLibrary
from lagsindy.systems import make_dataset, single_pendulum

TOL = report_module.CRITERIA_TOLERANCE


class _Model:
    def equation(self, precision):
        return "L = theta_dot**2"


def _report(h=(1.0, 0.5), p=(1.0, 1.0), before=(65.0, 10.0), after=(60.0, 5.0),
            steps=(), units=None):  # fmt: skip
    return DiagnosisReport(
        initial=_Model(),
        final=_Model(),
        residual_rms_before=np.array(before),
        residual_rms_after=np.array(after),
        force_rms=np.array([100.0, 100.0]),
        heldout_error_before=h[0],
        heldout_error_after=h[1],
        pointwise_before=p[0],
        pointwise_after=p[1],
        steps=list(steps),
        rankings=[],
        coordinates=["x", "theta"],
        passive=False,
        settings={"n_splits": 3, "units": units},
    )


def test_one_legend_for_the_force_scale():
    text = str(_report(units={"x": ("px", "V"), "theta": ("rad", "V")}))
    assert text.count("force scale") == 2  # the heading's mark and its legend
    assert "measured force, or the model's forces" not in text
    assert "  before: x 65 V (65.0%), theta 10 V (10.0%)" in text
    assert "of the measured force on the coordinate, or of the model's" in text
    # no units given: none invented
    assert "  before: x 65 (65.0%), theta 10 (10.0%)" in str(_report())


@pytest.mark.parametrize(
    "pointwise_after, notes",
    [(1.0 - TOL * 1.05, 0), (1.0 - TOL * 0.95, 1), (1.0, 1), (1.2, 1)],
)
def test_says_when_held_out_and_pointwise_disagree(pointwise_after, notes):
    report = _report(p=(1.0, pointwise_after), after=(60.0, 5.0))
    said = [t for t in report.disagreements() if "criteria disagree" in t]
    assert len(said) == notes
    if notes:
        assert "held-out trajectory error fell 50.0%" in said[0]
        assert f"note: {said[0]}" in str(report)


@pytest.mark.parametrize("factor, notes", [(1 + TOL * 0.95, 0), (1 + TOL * 1.05, 1)])
def test_says_when_a_coordinate_residual_rose(factor, notes):
    report = _report(p=(1.0, 0.5), after=(65.0 * factor, 5.0), units={"x": ("px", "V")})
    said = [t for t in report.disagreements() if "rose" in t]
    assert len(said) == notes
    if notes:
        assert (
            said[0].startswith("the residual on x rose (65 -> 65.") and " V)" in said[0]
        )


def test_no_note_when_nothing_changed():
    assert _report(h=(1.0, 1.0), p=(1.0, 1.0), after=(70.0, 10.0)).disagreements() == []


def test_the_issue_case_held_out_better_pointwise_equal_one_coordinate_worse():
    # issue 44: held-out improved, pointwise stayed equal, one residual 65 -> 102
    report = _report(
        h=(0.2, 0.1), p=(0.3, 0.3), before=(65.0, 40.0), after=(102.0, 20.0)
    )
    text = str(report)
    assert "pointwise error stayed within 1%" in text
    assert "the residual on x rose (65 -> 102)" in text


def _step(name, how):
    return Step(
        candidate=Candidate("viscous", name, ("theta",), None),
        coefficient=0.2,
        units="per unit of theta_dot",
        explained=0.5,
        fold_explained=[],
        residual_rms=np.zeros(2),
        heldout_error=0.1,
        equation="",
        ranking=None,
        how=how,
    )


def test_step_table_legend_names_how_each_effect_came():
    report = _report(
        steps=[_step("viscous(theta)", "added"), _step("coulomb(x)", "refit")]
    )
    text = str(report)
    assert "kept by a refit of the model's own dissipation terms" in text
    assert "added = added alone (step 2)" in text
    rows = [line for line in text.splitlines() if "per unit of theta_dot" in line]
    assert rows[0].lstrip().startswith("1 ") and rows[0].endswith("added")
    assert rows[1].lstrip().startswith("2 ") and rows[1].endswith("refit")
    assert report.effects == ["viscous(theta)", "coulomb(x)"]


@pytest.fixture(scope="module")
def damped():
    system = single_pendulum().with_damping(
        viscous={"theta": 0.2}, coulomb={"theta": 0.1}
    )
    data = make_dataset(
        system, n_trajectories=9, duration=3.0, excitation="sincos", random_state=0
    )
    return system, data


def test_step_table_lists_the_effects_of_a_starting_model_with_damping(damped):
    """Issue 44: a final model with D and a Coulomb force printed no table."""
    system, data = damped
    est = LagrangianSINDy(
        system.paper_library(),
        dissipation=DissipationLibrary(["viscous", "coulomb"]),
        formulation="strong",
    ).fit(data.X, data.tau, groups=data.groups)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = diagnose(est, data.X, data.tau, groups=data.groups)
    text = str(report)
    assert "D = " in text and "tanh" in text  # the final model: D and Coulomb
    rows = {
        line.split()[3]: line for line in text.splitlines() if line.endswith("start")
    }
    assert set(rows) == {"viscous(theta)", "coulomb(theta)"}
    assert "start = in the starting model already" in text
    assert report.effects == []  # found nothing new
    assert "no effect improves the held-out criterion" in text
    frame = report.to_frame()
    assert list(frame.how) == ["start", "start"]
    assert frame.coefficient.to_numpy() == pytest.approx([0.2, 0.1], rel=1e-9)


def test_diagnosis_figure_units_and_before_after(damped, tmp_path):
    pytest.importorskip("matplotlib")
    from lagsindy.joint import conservative_fits

    system, data = damped
    with conservative_fits():  # diagnose finds the damping (not the fit)
        est = LagrangianSINDy(system.paper_library(), formulation="strong").fit(
            data.X, data.tau, groups=data.groups
        )
    report = diagnose(
        est, data.X, data.tau, groups=data.groups, units={"theta": ("rad", "N*m")}
    )
    # measured 0.34 N*m before, 3.4 % of the force scale (3.5 % with the paper's
    # threshold rule, whose final model's forces differ slightly)
    assert re.search(r"theta 0\.34 N\*m \(3\.[45]%\)", str(report))
    fig = report.plot(tmp_path / "d.png")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "theta_dot (rad/s)"
    assert ax.get_ylabel() == "force residual on theta (N*m)"
    before, after = ax.collections[:2]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "before (starting model)",
        "after (final model)",
    ]
    assert not np.allclose(before.get_facecolor()[0], after.get_facecolor()[0])
    dot, cross = before.get_paths()[0], after.get_paths()[0]
    assert len(dot.vertices) != len(cross.vertices)  # dot vs cross markers
    styles = sorted(line.get_linestyle() for line in ax.get_lines()[:2])
    assert styles == ["-", "--"]  # binned means: after solid, before dashed
    # no units given: none invented
    plain = diagnose(est, data.X, data.tau, groups=data.groups).plot()
    assert plain.axes[0].get_ylabel() == "force residual on theta"
