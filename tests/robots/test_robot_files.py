"""Model files of URDF-library fits (schema version 2): self-contained, the fitted
base-parameter grouping kept, predictions equal to round-off, clear refusals."""

import json
import shutil
import warnings

import numpy as np
import pytest
from _robot_fit_data import planar_data
from sklearn.base import clone

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.io import model_file
from lagsindy.robots import FRICTION_KINDS, example_urdf
from lagsindy.robots import fitting as robot_fitting

ARM7_JOINTS = [f"joint{i}" for i in range(1, 8)]


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    """Embedded URDFs go to a folder of this test."""
    monkeypatch.setenv("LAGSINDY_CACHE_DIR", str(tmp_path / "urdf-cache"))


def _fit(path, data, kinds=(*FRICTION_KINDS, "spring"), **lib_kw):
    lib = CandidateLibrary.from_urdf(path, **lib_kw)
    est = LagrangianSINDy(lib, dissipation=DissipationLibrary(list(kinds)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return est.fit(data.X, data.tau)


@pytest.fixture(scope="module")
def planar():
    return planar_data(duration=3.0, spring=(1, 0.5, 0.1))


@pytest.fixture(scope="module")
def fitted(planar):
    return _fit(example_urdf("planar2"), planar)


def _states(n_dof, n=40, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.5, 1.5, (n, 3 * n_dof))


def _rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.abs(a - b).max() / np.abs(a).max()


def test_round_trip_predicts_equally(fitted, tmp_path):
    path = fitted.save(tmp_path / "arm.json")
    doc = json.loads(path.read_text())
    assert doc["schema_version"] == model_file.ROBOT_SCHEMA_VERSION
    assert doc["terms"] == fitted.library_.terms_
    assert "<robot" in doc["robot"]["urdf"]
    back = LagrangianSINDy.load(path)
    np.testing.assert_array_equal(back.coef_, fitted.coef_)
    np.testing.assert_array_equal(back.dissipation_coef_, fitted.dissipation_coef_)
    np.testing.assert_array_equal(
        back.library_.base_.matrix, fitted.library_.base_.matrix
    )
    assert back.library_.base_.labels == fitted.library_.base_.labels
    X = _states(2)
    assert _rel(fitted.predict(X), back.predict(X)) <= 1e-12  # measured 0
    tau = fitted.predict(X)
    assert (
        _rel(fitted.predict_acceleration(X, tau), back.predict_acceleration(X, tau))
        <= 1e-12
    )
    assert back.equation() == fitted.equation()
    assert back.library_.robot_.consistent and not back.library_.robot_.penalize


def test_round_trip_simulates_equally(tmp_path, planar):
    """Viscous friction only (a smooth right-hand side: a short integration)."""
    est = _fit(example_urdf("planar2"), planar, kinds=("viscous",))
    back = LagrangianSINDy.load(est.save(tmp_path / "arm.json"))
    t = np.linspace(0.0, 0.01, 3)
    x0 = np.array([0.3, -0.4, 0.5, 0.2])
    a, b = est.simulate(x0, t), back.simulate(x0, t)
    assert _rel(a, b) <= 1e-12


def test_file_is_self_contained_and_keeps_the_grouping(
    fitted, planar, tmp_path, monkeypatch
):
    """The URDF may be gone and a new reduction may choose other columns: the file
    still gives the fitted columns."""
    urdf = tmp_path / "copy.urdf"
    shutil.copy(example_urdf("planar2"), urdf)
    est = _fit(urdf, planar)
    path = est.save(tmp_path / "arm.json")
    urdf.unlink()

    def other_grouping(*args, **kwargs):
        raise AssertionError("a model file must not reduce the library again")

    monkeypatch.setattr(robot_fitting, "base_parameters", other_grouping)
    back = LagrangianSINDy.load(path)
    assert back.library_.terms_ == est.library_.terms_
    X = _states(2, seed=1)
    assert _rel(est.predict(X), back.predict(X)) <= 1e-12
    # a refit of the loaded model's configuration keeps the stored grouping
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        refit = clone(back).fit(planar.X, planar.tau)
    assert refit.library_.terms_ == est.library_.terms_


def test_seven_joint_round_trip(tmp_path):
    """The 7-joint arm with a locked joint order: the stored joints, gravity and
    armature setting rebuild the same columns."""
    lib = CandidateLibrary.from_urdf(
        example_urdf("arm7"), ARM7_JOINTS, armature=False, gravity=(0, 0, -9.8)
    )
    rng = np.random.default_rng(3)
    n = 400
    q = rng.uniform(-1, 1, (n, 7))
    qd, qdd = rng.uniform(-1, 1, (n, 7)), rng.uniform(-2, 2, (n, 7))
    truth = lib.nominal_
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth + 0.3 * qd
    est = LagrangianSINDy(lib, dissipation=DissipationLibrary(["viscous"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(np.hstack([q, qd, qdd]), tau)
    back = LagrangianSINDy.load(est.save(tmp_path / "arm7.json"))
    assert back.coordinates_ == ARM7_JOINTS
    assert back.library_.robot_.gravity == (0.0, 0.0, -9.8)
    assert back.library_.robot_.armature is False
    X = _states(7, seed=2)
    assert _rel(est.predict(X), back.predict(X)) <= 1e-12


def test_old_files_still_read(tmp_path):
    """A version 1 file (no robot field) reads as before."""
    from lagsindy.systems import make_dataset, single_pendulum

    system = single_pendulum()
    data = make_dataset(system, n_trajectories=2, duration=1.0, random_state=0)
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    est.fit(data.X, data.tau)
    path = est.save(tmp_path / "p.json")
    doc = json.loads(path.read_text())
    assert doc["schema_version"] == 1 and "robot" not in doc
    back = LagrangianSINDy.load(path)
    np.testing.assert_array_equal(back.coef_, est.coef_)


def _tampered(fitted, tmp_path, change):
    doc = model_file.model_to_dict(fitted)
    change(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: d.pop("robot"), "has a 'robot' object"),
        (lambda d: d.update(schema_version=1), "has a 'robot' object"),
        (lambda d: d["robot"].pop("matrix"), "exactly the fields"),
        (lambda d: d["robot"]["matrix"].pop(), "grouping does not fit"),
        (lambda d: d["robot"]["independent"].reverse(), "grouping does not fit"),
        (lambda d: d["robot"].update(gravity=[0, 0]), "3 numbers"),
        (lambda d: d["robot"].update(armature="yes"), "true or false"),
        (lambda d: d["terms"].reverse(), "not those of the robot"),
        (
            lambda d: d["robot"].update(
                urdf='<!DOCTYPE r [<!ENTITY a "b">]>' + d["robot"]["urdf"]
            ),
            "document type declaration",
        ),
        (lambda d: d["robot"].update(urdf="<robot"), "does not rebuild"),
        (lambda d: d.update(unpenalized=["cos(shoulder)"]), "not among its terms"),
    ],
)
def test_tampered_robot_files_are_refused(fitted, tmp_path, change, match):
    path = _tampered(fitted, tmp_path, change)
    with pytest.raises(ValueError, match=match):
        LagrangianSINDy.load(path)


def test_missing_urdf_at_save_is_a_clear_error(planar, tmp_path):
    urdf = tmp_path / "gone.urdf"
    shutil.copy(example_urdf("planar2"), urdf)
    est = _fit(urdf, planar, kinds=("viscous",))
    urdf.unlink()
    with pytest.raises(ValueError, match="cannot be read to embed"):
        est.save(tmp_path / "m.json")


def test_code_export_refuses_torch_terms(fitted, tmp_path):
    from lagsindy.export import export_model

    with pytest.raises(ValueError, match="torch term function.*to_urdf"):
        export_model(fitted, tmp_path / "arm.py")


def test_cli_reads_a_robot_model_file(fitted, planar, tmp_path, capsys):
    import pandas as pd

    from lagsindy.cli import main

    model = fitted.save(tmp_path / "arm.json")
    names = ["shoulder", "elbow"]
    cols = names + [f"{c}_dot" for c in names] + [f"{c}_ddot" for c in names]
    frame = pd.DataFrame(planar.X, columns=cols)
    frame.insert(0, "t", planar.t)
    for j, c in enumerate(names):
        frame[f"tau_{c}"] = planar.tau[:, j]
    data = tmp_path / "arm.csv"
    frame.to_csv(data, index=False)
    out = tmp_path / "pred.csv"
    assert main(["predict", str(model), str(data), "--out", str(out)]) == 0
    pred = pd.read_csv(out)
    want = fitted.predict(planar.X)
    got = pred[[f"tau_{c}" for c in names]].to_numpy()
    assert _rel(want, got) <= 1e-9  # (CSV text: 17 digits)
    code = main(["export", str(model), "--out", str(tmp_path / "arm.py")])
    assert code != 0
    assert "to_urdf" in capsys.readouterr().err


@pytest.mark.slow  # (~70 s: the torch terms' integration and diagnose's refits)
def test_cli_simulates_and_diagnoses_a_robot_model_file(planar, tmp_path):
    import pandas as pd

    from lagsindy.cli import main

    est = _fit(example_urdf("planar2"), planar, kinds=("viscous",))
    model = est.save(tmp_path / "arm.json")
    out = tmp_path / "sim.csv"
    args = ["--x0", "0.3,-0.4,0.5,0.2", "--duration", "0.01", "--rate", "200"]
    assert main(["simulate-model", str(model), *args, "--out", str(out)]) == 0
    sim = pd.read_csv(out)
    want = est.simulate(np.array([0.3, -0.4, 0.5, 0.2]), sim.t.to_numpy())
    assert _rel(want[:, :2], sim[["shoulder", "elbow"]].to_numpy()) <= 1e-9
    names = ["shoulder", "elbow"]
    cols = names + [f"{c}_dot" for c in names] + [f"{c}_ddot" for c in names]
    rows = slice(0, 900)  # (diagnose's cost)
    frame = pd.DataFrame(planar.X[rows], columns=cols)
    frame.insert(0, "t", planar.t[rows])
    for j, c in enumerate(names):
        frame[f"tau_{c}"] = planar.tau[rows, j]
    data = tmp_path / "arm.csv"
    frame.to_csv(data, index=False)
    final = tmp_path / "final.json"
    code = main(
        [
            "diagnose",
            str(data),
            "--model",
            str(model),
            "--catalogue",
            "spring",
            "--out-model",
            str(final),
            "--quiet",
        ]
    )
    assert code == 0
    back = LagrangianSINDy.load(final)  # a robot model file again
    assert back.library_.terms_ == est.library_.terms_
    assert json.loads(final.read_text())["schema_version"] == 2


def test_a_grouping_of_another_robot_is_refused(fitted):
    from lagsindy.robots import BaseParameterLibrary

    arm7 = CandidateLibrary.from_urdf(example_urdf("arm7"), ARM7_JOINTS)
    with pytest.raises(ValueError, match="another robot library"):
        BaseParameterLibrary(arm7, base=fitted.library_.base_).build()
