"""The estimator's settings objects and the deprecated flat parameters
(lagsindy.settings): warnings that name the replacement, the same fit either way,
conflicts refused, model files with flat values loaded into objects."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from lagsindy import LagrangianSINDy, pipeline, settings
from lagsindy.formulation import AutoForm, StrongForm, WeakForm
from lagsindy.solvers import StagedFISTA
from lagsindy.systems import make_dataset, single_pendulum

_V010 = Path(__file__).resolve().parents[1] / "data" / "models_0_1"


@pytest.fixture(scope="module")
def pend():
    return make_dataset(
        single_pendulum(), n_trajectories=4, duration=2.0, excitation="paper",
        random_state=0,
    )  # fmt: skip


def _fit(est, data):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return est.fit(data.X, data.tau, groups=data.groups)


def test_flat_parameters_warn_naming_the_object_and_give_the_same_fit(pend):
    lib = single_pendulum().paper_library()
    flat = LagrangianSINDy(lib, threshold=0.1, max_iter=7, window=41, dt=0.01)
    with pytest.warns(FutureWarning) as caught:
        _fit(flat, pend)
    messages = [str(w.message) for w in caught if w.category is FutureWarning]
    assert len(messages) == 2
    assert "pass solver=StagedFISTA(max_iter=7, threshold=0.1)" in messages[0]
    assert "pass formulation=AutoForm(dt=0.01, window=41)" in messages[1]
    objects = LagrangianSINDy(
        lib,
        solver=StagedFISTA(threshold=0.1, max_iter=7),
        formulation=AutoForm(window=41, dt=0.01),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)  # the objects do not warn
        _fit(objects, pend)
    np.testing.assert_array_equal(flat.coef_, objects.coef_)
    assert flat.window_ == objects.window_ == 41
    # the flat value did reach the solve: the default runs more iterations
    default = _fit(LagrangianSINDy(lib, formulation=AutoForm(window=41, dt=0.01)), pend)
    assert flat.n_iter_ == objects.n_iter_ < default.n_iter_


def test_a_weak_formulation_name_is_named_in_the_warning():
    with pytest.warns(FutureWarning, match=r"formulation=WeakForm\(noise_cov=None\)"):
        settings.warn_deprecated({"formulation": "weak", "noise_cov": None})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        settings.warn_deprecated(LagrangianSINDy().get_params())  # nothing set


def test_an_object_and_its_flat_parameters_together_are_refused(pend):
    both = LagrangianSINDy(solver=StagedFISTA(), threshold=0.1)
    with pytest.raises(ValueError, match=r"solver= is given and so are \['thr"):
        _fit(both, pend)
    form = LagrangianSINDy(formulation=WeakForm(), window=81)
    with pytest.raises(ValueError, match=r"set them on the formulation object"):
        settings.formulation_settings(form.get_params())


def test_as_objects_folds_flat_values_and_drops_defaults():
    est = LagrangianSINDy(threshold=0.05, window="auto")  # the defaults, set
    out = settings.as_objects(est.get_params())
    assert out["solver"] is None and out["formulation"] == "auto"
    assert out["threshold"] == out["window"] == settings.DEPRECATED
    out = settings.as_objects(
        LagrangianSINDy(formulation="weak", max_iter=500, dt=0.02).get_params()
    )
    assert out["solver"].get_params() == StagedFISTA(max_iter=500).get_params()
    assert isinstance(out["formulation"], WeakForm)
    assert out["formulation"].get_params()["dt"] == 0.02
    # the strong form holds no weak-form settings: they are dropped
    out = settings.as_objects({"formulation": "strong", "window": 81})
    assert isinstance(out["formulation"], StrongForm)


@pytest.mark.parametrize("name", ["forces", "fixed_mass", "cart_dissipation"])
def test_files_with_flat_values_load_into_objects_without_a_warning(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        est = LagrangianSINDy.load(_V010 / f"{name}.json")
    params = est.get_params(deep=False)
    assert all(params[k] == settings.DEPRECATED for k in settings.DEPRECATED_FLAT)
    assert all(params[k] == settings.DEPRECATED for k in settings.FORMULATION_PARAMS)
    # 0.1 files store the defaults and formulation "strong" with window 81
    assert params["solver"] is None and isinstance(params["formulation"], StrongForm)


def test_saved_settings_objects_are_flat_in_the_file_and_come_back(tmp_path, pend):
    lib = single_pendulum().paper_library()
    est = LagrangianSINDy(
        lib, solver=StagedFISTA(threshold=0.02), formulation=WeakForm(dt=0.01)
    )
    _fit(est, pend)
    path = est.save(tmp_path / "m.json")
    hyper = json.loads(Path(path).read_text())["hyperparameters"]
    assert hyper["threshold"] == 0.02 and hyper["formulation"] == "weak"
    assert hyper["dt"] == 0.01 and hyper["window"] == "auto" and "solver" not in hyper
    back = LagrangianSINDy.load(path)
    assert back.solver.get_params() == est.solver.get_params()
    assert back.formulation.get_params() == est.formulation.get_params()
    bad = dict(hyper, threshold=2.0)
    with pytest.raises(ValueError, match="threshold"):
        settings.checked_params(bad)
    with pytest.raises(ValueError, match="unknown hyperparameters"):
        settings.checked_params(dict(hyper, shrinkage=1.0))


def test_lam_and_alpha_stay_flat_and_reach_the_solve(pend):
    """``alpha`` (the first stage's step) and ``lam`` are not solver settings: the
    setup passes them to the staged solve beside ``solver``."""
    lib = single_pendulum().paper_library()
    solver = StagedFISTA(max_iter=50, step_growth=3.0)
    est = _fit(
        LagrangianSINDy(lib, formulation="strong", alpha=1e-3, solver=solver), pend
    )
    assert est.stages_[0].step == 1e-3 and est.stages_[0].lam == 1e-3
    if len(est.stages_) > 1:
        assert est.stages_[1].step == pytest.approx(3e-3)  # step_growth, exactly
    auto = _fit(LagrangianSINDy(lib, formulation="strong", lam=2e-3), pend)
    # measured: 1/L = 0.19 here, far from the given step
    assert auto.stages_[0].step > 0.1 and auto.stages_[0].lam == 2e-3


@pytest.mark.parametrize("form", ["auto", AutoForm(window=161), "strong", StrongForm()])
def test_case_II_runs_the_strong_form(form):
    got = pipeline.formulation_of({"formulation": form}, "acceleration")
    assert type(got) is StrongForm


@pytest.mark.parametrize("form", ["weak", WeakForm()])
def test_case_II_refuses_the_weak_form(form):
    with pytest.raises(ValueError, match="needs the strong form"):
        pipeline.formulation_of({"formulation": form}, "acceleration")
