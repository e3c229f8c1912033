"""lagsindy.plotting: figures are built, saved as PNG, and fail clearly (#7)."""

import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib")
import matplotlib  # noqa: E402

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402

from lagsindy import LagrangianSINDy  # noqa: E402
from lagsindy.plotting import (  # noqa: E402
    plot_coefficient_path,
    plot_residuals,
    plot_trajectories,
)
from lagsindy.systems import make_dataset, single_pendulum  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def fitted():
    system = single_pendulum()
    data = make_dataset(
        system,
        n_trajectories=6,
        excitation="paper",
        noise=0.01,
        protocol="paper",
        random_state=0,
    )
    return system, data, LagrangianSINDy(system.paper_library()).fit(data.X, data.tau)


def test_trajectories_figure_and_png(fitted, tmp_path):
    system, _, est = fitted
    t = np.linspace(0, 3, 301)
    true = system.simulate([1.0, 0.0], t)
    learned = est.simulate([1.0, 0.0], t)
    fig = plot_trajectories(
        t,
        true,
        learned,
        system.coordinates,
        velocities=True,
        title="pendulum",
        path=tmp_path / "traj.png",
    )
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 2  # one coordinate x (position, velocity)
    lines = fig.axes[0].get_lines()
    # issue 44: the legend says measured and model, not "true"
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert legend == ["measured", "model"]
    np.testing.assert_array_equal(lines[0].get_ydata(), true[:, 0])
    np.testing.assert_array_equal(lines[1].get_ydata(), learned[:, 0])
    assert (tmp_path / "traj.png").read_bytes()[:8] == PNG


def test_trajectories_accept_a_failed_learned_model():
    t = np.linspace(0, 1, 11)
    states = np.column_stack([np.sin(t), np.cos(t), t, t])
    fig = plot_trajectories(t, states, None, ["a", "b"])
    assert len(fig.axes) == 2 and "could not be integrated" in fig.axes[0].get_title()
    fig = plot_trajectories(t, states, states[:5], ["a", "b"])  # stopped early
    assert len(fig.axes[0].get_lines()[1].get_xdata()) == 5


@pytest.mark.parametrize(
    "true, learned, names",
    [
        (np.zeros((11, 3)), None, None),  # odd number of state columns
        (np.zeros((10, 2)), None, None),  # wrong length
        (np.zeros((11, 2)), np.zeros((11, 4)), None),
        (np.zeros((11, 2)), None, ["a", "b"]),
    ],
)
def test_trajectories_reject_bad_shapes(true, learned, names):
    with pytest.raises(ValueError):
        plot_trajectories(np.linspace(0, 1, 11), true, learned, names)


def test_coefficient_path_has_one_line_per_surviving_term(fitted, tmp_path):
    _, _, est = fitted
    fig = plot_coefficient_path(est, path=tmp_path / "path.png")
    ax = fig.axes[0]
    labels = [
        line.get_label()
        for line in ax.get_lines()
        if not line.get_label().startswith("_")
    ]
    ever = np.any(np.vstack([s.coef for s in est.stages_] + [est.coef_]) != 0, axis=0)
    assert len(labels) == min(int(ever.sum()), 12)
    assert set(labels) >= {"theta_dot**2", "cos(theta)"}
    # the last point of each line is the final coefficient
    k = list(est.term_names_).index("cos(theta)")
    line = next(ln for ln in ax.get_lines() if ln.get_label() == "cos(theta)")
    assert line.get_ydata()[-1] == est.coef_[k]
    assert len(line.get_xdata()) == len(est.stages_) + 1
    assert (tmp_path / "path.png").read_bytes()[:8] == PNG


def test_coefficient_path_needs_stages(fitted, tmp_path):
    _, _, est = fitted
    loaded = LagrangianSINDy.load(est.save(tmp_path / "m.json"))
    with pytest.raises(ValueError, match="no stages"):
        plot_coefficient_path(loaded)


def test_residual_figure_forces_and_accelerations(fitted, tmp_path):
    _, data, est = fitted
    fig = plot_residuals(est, data.X, data.tau, t=data.t, path=tmp_path / "res.png")
    assert len(fig.axes) == 2 and "force residual" in fig.axes[0].get_ylabel()
    resid = fig.axes[0].get_lines()[0].get_ydata()
    np.testing.assert_allclose(resid, data.tau[:, 0] - est.predict(data.X)[:, 0])
    fig = plot_residuals(est, data.X, data.tau, kind="acceleration")
    resid = fig.axes[0].get_lines()[0].get_ydata()
    np.testing.assert_allclose(
        resid, data.X[:, 2] - est.predict_acceleration(data.X, data.tau)[:, 0]
    )
    assert (tmp_path / "res.png").read_bytes()[:8] == PNG
    with pytest.raises(ValueError, match="tau"):
        plot_residuals(est, data.X, kind="forces")
    with pytest.raises(ValueError, match="kind"):
        plot_residuals(est, data.X, kind="other")


def test_missing_matplotlib_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(ImportError, match=r"lagsindy\[plot\]"):
        plot_trajectories([0.0, 1.0], np.zeros((2, 2)), None)


def test_axes_carry_units_and_time(fitted):
    system, data, est = fitted
    t = np.arange(101) / 100.0
    states = system.simulate([1.0, 0.0], t)
    fig = plot_trajectories(
        t, states, states, ["theta"], velocities=True, units=["rad"]
    )
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert labels == ["theta (rad)", "theta_dot (rad/s)"]
    assert [ax.get_xlabel() for ax in fig.axes] == ["t (s)", "t (s)"]
    with pytest.raises(ValueError, match="units"):
        plot_trajectories(t, states, states, ["theta"], units=["rad", "m"])
    # issue 44: no force unit guessed from the coordinate's (a voltage input)
    fig = plot_residuals(est, data.X, data.tau, t=data.t, units=["rad"])
    assert fig.axes[0].get_ylabel() == "theta\nforce residual (units of tau)"
    assert fig.axes[1].get_xlabel() == "residual (units of tau)"
    fig = plot_residuals(
        est, data.X, data.tau, t=data.t, units=["rad"], force_units=["V"]
    )
    assert fig.axes[0].get_ylabel() == "theta\nforce residual (V)"
    assert fig.axes[1].get_xlabel() == "residual (V)"
    with pytest.raises(ValueError, match="units"):
        plot_residuals(est, data.X, data.tau, force_units=["V", "N"])
    assert fig.axes[0].get_xlabel() == "t (s)"
    fig = plot_residuals(est, data.X, data.tau, kind="acceleration", units=["rad"])
    assert fig.axes[0].get_ylabel() == "theta\nacceleration residual (rad/s^2)"
    fig = plot_residuals(est, data.X, data.tau, dt=0.01)
    assert fig.axes[0].get_xlabel().startswith("t (s)")
    np.testing.assert_allclose(
        fig.axes[0].get_lines()[0].get_xdata()[:3], [0.0, 0.01, 0.02]
    )


def test_residual_share_is_of_the_measured_force(fitted):
    # The title's share is RMS(tau - predicted) / RMS(tau), as diagnose reports it.
    _, data, est = fitted
    fig = plot_residuals(est, data.X, data.tau)
    resid = data.tau[:, 0] - est.predict(data.X)[:, 0]
    share = np.sqrt(np.mean(resid**2)) / np.sqrt(np.mean(data.tau[:, 0] ** 2))
    title = fig.axes[0].get_title()
    assert title.endswith(f"{share:.2%} of the measured force"), title


def test_diagnosis_figure_with_nothing_found_shows_every_coordinate():
    from lagsindy import diagnose
    from lagsindy.systems import cart_pendulum

    system = cart_pendulum()
    data = make_dataset(
        system, n_trajectories=6, duration=2.0, excitation="sincos", random_state=0
    )
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    est.fit(data.X, data.tau, groups=data.groups)
    report = diagnose(est, data.X, data.tau, groups=data.groups)
    assert report.steps == []  # noise-free, complete model: nothing to add
    fig = report.plot()
    assert [ax.get_ylabel() for ax in fig.axes] == [
        "force residual on x",
        "force residual on theta",
    ]
    assert [ax.get_xlabel() for ax in fig.axes] == ["x_dot", "theta_dot"]
