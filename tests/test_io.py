"""Saved models: JSON round trips, exact predictions, and tampered files (#7, #8)."""

import builtins
import json
import pickle
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import sympy as sp
from sklearn.base import clone

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy import io as lio
from lagsindy.io import model_file as lmf
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum

_VISCOUS = {
    "name": "viscous(x)",
    "kind": "viscous",
    "coordinates": ["x"],
    "forces": ["-x_dot", "0"],
    "rayleigh": "x_dot**2/2",
    "coefficient": 0.1,
}


@pytest.fixture(scope="module")
def cart_data():
    return make_dataset(
        cart_pendulum(),
        n_trajectories=8,
        excitation="sincos",
        noise=0.01,
        protocol="paper",
        random_state=3,
    )


@pytest.fixture(scope="module")
def cart_model(cart_data):
    return LagrangianSINDy(cart_pendulum().paper_library()).fit(
        cart_data.X, cart_data.tau
    )


@pytest.fixture(scope="module")
def passive_data():
    return make_dataset(
        single_pendulum(),
        n_trajectories=8,
        excitation=None,
        noise=0.001,
        protocol="paper",
        random_state=4,
    )


@pytest.fixture(scope="module")
def passive_model(passive_data):
    return LagrangianSINDy(
        single_pendulum().paper_library(), fixed_term="theta_dot**2"
    ).fit(passive_data.X)


@pytest.fixture(scope="module")
def saved(cart_model, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "cart.json"
    cart_model.save(path)
    return path


def _doc(path):
    return json.loads(path.read_text())


def _write(tmp_path, doc, name="m.json"):
    p = tmp_path / name
    p.write_text(json.dumps(doc))
    return p


# ---------------------------------------- round trips
def test_active_round_trip_predicts_to_1e12(cart_model, cart_data, saved):
    loaded = LagrangianSINDy.load(saved)
    X, tau = cart_data.X, cart_data.tau
    np.testing.assert_allclose(
        loaded.predict(X), cart_model.predict(X), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(
        loaded.predict_acceleration(X, tau),
        cart_model.predict_acceleration(X, tau),
        rtol=0,
        atol=1e-12,
    )
    assert loaded.score(X, tau) == pytest.approx(cart_model.score(X, tau), abs=1e-12)
    np.testing.assert_array_equal(loaded.coef_, cart_model.coef_)
    assert loaded.equation() == cart_model.equation()
    assert loaded.case_ == "forces" and loaded.fixed_term_ is None
    assert list(loaded.term_names_) == list(cart_model.term_names_)
    pd.testing.assert_frame_equal(loaded.coef_table(), cart_model.coef_table())


def test_loaded_model_simulates_like_the_original(cart_model, saved):
    loaded = lio.load_model(saved)
    t = np.linspace(0, 2, 201)
    x0 = [0.1, 0.8, 0.0, 0.0]
    np.testing.assert_allclose(
        loaded.simulate(x0, t), cart_model.simulate(x0, t), atol=1e-10
    )


def test_passive_round_trip_keeps_case_and_fixed_term(
    passive_model, passive_data, tmp_path
):
    path = lio.save_model(passive_model, tmp_path / "passive.json")
    loaded = lio.load_model(path)
    assert loaded.case_ == "fixed"
    assert loaded.fixed_term_ == passive_model.fixed_term_ == "theta_dot**2"
    X = passive_data.X
    np.testing.assert_allclose(
        loaded.predict_acceleration(X),
        passive_model.predict_acceleration(X),
        rtol=0,
        atol=1e-12,
    )
    assert loaded.score(X) == pytest.approx(passive_model.score(X), abs=1e-12)
    assert loaded.get_params()["fixed_term"] == "theta_dot**2"


def test_mass_normalized_round_trip(passive_data, tmp_path):
    est = LagrangianSINDy(single_pendulum().paper_library(), fixed_term="mass")
    est.fit(passive_data.X)
    loaded = lio.load_model(lio.save_model(est, tmp_path / "mass.json"))
    assert loaded.normalization_ == est.normalization_ == "mass"
    assert loaded.get_params()["fixed_term"] == "mass"
    assert loaded.fixed_term_ == est.fixed_term_
    np.testing.assert_allclose(
        loaded.predict_acceleration(passive_data.X),
        est.predict_acceleration(passive_data.X),
        rtol=0,
        atol=1e-12,
    )


def test_files_without_normalization_field_still_load(saved, tmp_path):
    doc = json.loads(open(saved).read())
    del doc["normalization"]
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    assert lio.load_model(path).normalization_ is None


def test_dataframe_fitted_round_trip(cart_data, tmp_path):
    df = pd.DataFrame(cart_data.X, columns=cart_data.feature_names)
    est = LagrangianSINDy(cart_pendulum().paper_library()).fit(df, cart_data.tau)
    loaded = LagrangianSINDy.load(est.save(tmp_path / "df.json"))
    assert list(loaded.feature_names_in_) == cart_data.feature_names
    frame = df.iloc[::-1].set_index(df.index[::-1] + 1000)  # any index comes back
    a, b = est.predict(frame), loaded.predict(frame)
    assert isinstance(b, pd.DataFrame) and list(b.columns) == ["tau_x", "tau_theta"]
    assert b.index.equals(frame.index)
    np.testing.assert_allclose(b.to_numpy(), a.to_numpy(), rtol=0, atol=1e-12)


def test_one_dimensional_tau_round_trip(tmp_path):
    data = make_dataset(
        single_pendulum(), n_trajectories=5, excitation="paper", random_state=5
    )
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(data.X, data.tau[:, 0])
    loaded = LagrangianSINDy.load(est.save(tmp_path / "m.json"))
    assert loaded.predict(data.X).shape == (len(data.X),)
    np.testing.assert_allclose(loaded.predict(data.X), est.predict(data.X), atol=1e-12)


def test_float_inside_a_term_round_trips_exactly(tmp_path):
    x, xd = sp.symbols("x x_dot", real=True)
    odd = sp.Float(1 / 3) * x**2 + sp.cos(sp.Float(0.1) * x)
    library = CandidateLibrary.from_terms(["x"], [xd**2, odd, x**4])
    rng = np.random.default_rng(0)
    X = rng.normal(size=(400, 3))
    tau = 2 * X[:, 2:3] + 0.9 * (2 / 3 * X[:, :1] - 0.1 * np.sin(0.1 * X[:, :1]))
    est = LagrangianSINDy(library).fit(X, tau)
    loaded = LagrangianSINDy.load(est.save(tmp_path / "m.json"))
    np.testing.assert_array_equal(loaded.predict(X), est.predict(X))
    assert "0.3333333333333333" in (tmp_path / "m.json").read_text()


def test_document_has_documented_fields(saved, cart_model):
    doc = _doc(saved)
    assert doc["format"] == "lagsindy-model" and doc["schema_version"] == 1
    assert doc["coordinates"] == ["x", "theta"]
    assert len(doc["terms"]) == len(doc["coefficients"]) == len(cart_model.coef_)
    assert doc["terms"] == [str(t) for t in cart_model.library_.terms_]
    assert "library" not in doc["hyperparameters"]
    assert doc["hyperparameters"]["lam"] == cart_model.lam
    assert doc["dissipation"] == [] and doc["tau_1d"] is False
    # exact floats: the text parses back to the very same doubles
    assert [float(c) for c in doc["coefficients"]] == list(cart_model.coef_)


def test_dissipation_field_round_trips(tmp_path):
    from lagsindy import DissipationLibrary
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum().with_damping(coulomb={"x": 0.2}, viscous={"theta": 0.05})
    data = make_dataset(system, n_trajectories=6, excitation="sincos", random_state=0)
    est = LagrangianSINDy(
        system.paper_library(), dissipation=DissipationLibrary(["viscous", "coulomb"])
    ).fit(data.X, data.tau)
    path = est.save(tmp_path / "d.json")
    entries = _doc(path)["dissipation"]
    assert [e["name"] for e in entries] == [
        "viscous(x)",
        "viscous(theta)",
        "coulomb(x)",
        "coulomb(theta)",
    ]
    assert entries[2]["forces"] == ["-tanh(100.0*x_dot)", "0"]
    loaded = LagrangianSINDy.load(path)
    np.testing.assert_array_equal(loaded.dissipation_coef_, est.dissipation_coef_)
    np.testing.assert_array_equal(loaded.predict(data.X), est.predict(data.X))
    np.testing.assert_array_equal(
        loaded.predict_acceleration(data.X, data.tau),
        est.predict_acceleration(data.X, data.tau),
    )
    assert loaded.equation() == est.equation()
    again = LagrangianSINDy.load(loaded.save(tmp_path / "again.json"))
    np.testing.assert_array_equal(again.dissipation_coef_, est.dissipation_coef_)


def test_loaded_model_pickles_and_refits(saved, cart_data):
    loaded = LagrangianSINDy.load(saved)
    again = pickle.loads(pickle.dumps(loaded))
    np.testing.assert_array_equal(
        again.predict(cart_data.X[:50]), loaded.predict(cart_data.X[:50])
    )
    refit = clone(loaded).fit(cart_data.X, cart_data.tau)
    np.testing.assert_allclose(refit.coef_, loaded.coef_, rtol=1e-6, atol=1e-9)


def test_loading_evaluates_no_code(saved, monkeypatch):
    """No eval/exec/pickle and no sympify of a string while loading."""

    def forbidden(*args, **kwargs):
        raise AssertionError("code evaluation during load")

    real_sympify = sp.sympify

    def guarded_sympify(a, *args, **kwargs):
        if isinstance(a, str):
            raise AssertionError(f"sympify of a string during load: {a!r}")
        return real_sympify(a, *args, **kwargs)

    monkeypatch.setattr(builtins, "eval", forbidden)
    monkeypatch.setattr(builtins, "exec", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(sp, "sympify", guarded_sympify)
    monkeypatch.setattr("sympy.parsing.sympy_parser.parse_expr", forbidden)
    est = lio.load_model(saved)
    assert est.coef_.shape == (len(_doc(saved)["terms"]),)


# ---------------------------------------- tampering
MARKER = "lagsindy_pwned"


EVIL_TERMS = [
    "__import__('os').system('touch {marker}')",
    '__import__("os").system("touch {marker}")',
    "x.__class__.__bases__",
    "lambda: 0",
    "exec('1')",
    "x_dot**2; import os",
    "eval",
    "y_dot**2",
    "x_ddot",
    "(((2**64)**64)**64)*x",
    "(" * 3000 + "x" + ")" * 3000,
    "-" * 5000 + "x",
    "x" * 20_000,
    "x**99",
    "2",
    "",
    "1e99999999999*x",
    "9" * 5000 + "*x",
    "x**(1/0)",
    "x/0",
    "x**sqrt(-1)",
    "exp(1e308)*x",
    "x_dot**2\x00",
]


@pytest.mark.parametrize("term", EVIL_TERMS, ids=range(len(EVIL_TERMS)))
def test_malicious_or_invalid_term_is_refused(saved, tmp_path, term):
    doc = _doc(saved)
    doc["terms"][0] = term.replace("{marker}", str(tmp_path / MARKER))
    path = _write(tmp_path, doc)
    with pytest.raises(ValueError, match="term"):
        lio.load_model(path)
    assert not (tmp_path / MARKER).exists()


FIELDS = [f for f in lmf._FIELDS if f not in lmf._OPTIONAL]


@pytest.mark.parametrize("field", FIELDS)
def test_missing_field_is_named(saved, tmp_path, field):
    doc = _doc(saved)
    del doc[field]
    with pytest.raises(ValueError, match=field):
        lio.load_model(_write(tmp_path, doc))


@pytest.mark.parametrize("field", FIELDS)
def test_wrong_json_type_is_named(saved, tmp_path, field):
    doc = _doc(saved)
    doc[field] = {"nested": "object"}
    with pytest.raises(ValueError, match=field):
        lio.load_model(_write(tmp_path, doc))


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda d: d.update(schema_version=2), "schema version 2"),
        (lambda d: d.update(schema_version=True), "schema_version"),
        (lambda d: d.update(format="something-else"), "not a lagsindy model"),
        (lambda d: d.update(extra_field=1), "unknown fields"),
        (lambda d: d["coefficients"].append(1.0), "coefficients"),
        (lambda d: d["coefficients"].__setitem__(0, "1.0"), r"coefficients\[0\]"),
        (lambda d: d["coefficients"].__setitem__(0, True), r"coefficients\[0\]"),
        (lambda d: d["coefficients"].__setitem__(0, None), r"coefficients\[0\]"),
        (lambda d: d["terms"].__setitem__(0, 3), r"terms\[0\]"),
        (lambda d: d["terms"].__setitem__(1, d["terms"][0]), "same term"),
        (lambda d: d.update(terms=[], coefficients=[]), "no terms"),
        (lambda d: d.update(coordinates=["x", "x"]), "twice"),
        (lambda d: d.update(coordinates=["x", "theta_dot"]), "theta_dot"),
        (lambda d: d.update(coordinates=["x", "sin"]), "reserved"),
        (lambda d: d.update(coordinates=["x", "a b"]), "not valid"),
        (lambda d: d.update(coordinates=["x", 1]), r"coordinates\[1\]"),
        (lambda d: d.update(n_features_in=5), "n_features_in"),
        (
            lambda d: d.update(feature_names_in=["a", "b", "c", "d", "e", "f"]),
            "feature_names_in",
        ),
        (lambda d: d.update(case="exec"), "case"),
        (lambda d: d.update(case="fixed"), "fixed_term"),
        (lambda d: d.update(fixed_term="x**7"), "not among its terms"),
        (lambda d: d.update(fixed_term="__import__('os')"), "not valid"),
        (lambda d: d.update(unpenalized=["os.system"]), "not valid"),
        (lambda d: d.update(tau_1d=True), "1-D"),
        (lambda d: d.update(residual="small"), "residual"),
        (lambda d: d["hyperparameters"].update(lam=-1.0), "lam"),
        (lambda d: d["hyperparameters"].update(nonsense=1), "unknown hyperparameters"),
        (lambda d: d["hyperparameters"].update(device="__import__('os')"), "device"),
        (
            lambda d: d["hyperparameters"].update(fixed_term="open('/etc/passwd')"),
            "not valid",
        ),
        (
            lambda d: d["hyperparameters"].update(unpenalized=[["nested"]]),
            "unpenalized",
        ),
        (lambda d: d.update(dissipation=["x_dot"]), r"dissipation\[0\]"),
        (
            lambda d: d.update(dissipation=[dict(_VISCOUS, forces=["-x_dot"])]),
            "2 expressions",
        ),
        (
            lambda d: d.update(
                dissipation=[dict(_VISCOUS, forces=["-x_dot", "exec('1')"])]
            ),
            "not valid",
        ),
        (
            lambda d: d.update(dissipation=[dict(_VISCOUS, code="x")]),
            "exactly the fields",
        ),
        (lambda d: d.update(dissipation=[dict(_VISCOUS, kind="magic")]), "kind"),
        (
            lambda d: d.update(dissipation=[dict(_VISCOUS, forces=["-x_dot**3", "0"])]),
            "does not match",
        ),
        (
            lambda d: d.update(dissipation=[dict(_VISCOUS, coordinates=["y"])]),
            "coordinates",
        ),
        (
            lambda d: d.update(dissipation=[dict(_VISCOUS, coefficient="big")]),
            "coefficient",
        ),
    ],
)
def test_tampered_document_gives_clear_error(saved, tmp_path, change, message):
    doc = _doc(saved)
    change(doc)
    with pytest.raises(ValueError, match=message):
        lio.load_model(_write(tmp_path, doc))


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_non_finite_coefficient_is_refused(saved, tmp_path, literal):
    text = saved.read_text()
    doc = _doc(saved)
    first = json.dumps(doc["coefficients"])
    tampered = text.replace(first, "[" + literal + first[first.index(",") :], 1)
    assert tampered != text
    path = tmp_path / "nan.json"
    path.write_text(tampered)
    with pytest.raises(ValueError, match="NaN|Infinity|finite"):
        lio.load_model(path)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "not valid JSON"),
        (b"[1, 2, 3]", "JSON object"),
        (b"\xff\xfe\x00garbage", "UTF-8"),
        (b'{"format": "lagsindy-model", "format": "x"}', "repeats the key"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply|not valid JSON"),
        (
            b'{"format": "lagsindy-model", "schema_version": ' + b"9" * 5000 + b"}",
            "digits|JSON",
        ),
        (b"\x80\x04\x95pickle", "UTF-8|JSON"),
    ],
)
def test_garbage_files_give_clear_error(tmp_path, content, message):
    path = tmp_path / "g.json"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=message):
        lio.load_model(path)


def test_oversized_file_is_refused_before_reading(saved, monkeypatch):
    monkeypatch.setattr(lmf, "MAX_FILE_BYTES", 100)
    with pytest.raises(ValueError, match="bytes"):
        lio.load_model(saved)


def test_missing_file_raises_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        lio.load_model(tmp_path / "nope.json")


def test_cuda_model_loads_on_cpu_with_a_warning(saved, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    doc = _doc(saved)
    doc["hyperparameters"]["device"] = "cuda"
    with pytest.warns(UserWarning, match="CPU"):
        est = lio.load_model(_write(tmp_path, doc))
    assert est.device == "cpu"


# ---------------------------------------- pandas
def test_coef_table(cart_model):
    table = cart_model.coef_table()
    assert list(table.columns) == ["term", "kind", "coefficient", "kept"]
    assert set(table.kind) == {"lagrangian"}
    assert len(table) == len(cart_model.coef_)
    assert set(table.loc[table.kept, "term"]) == {
        "x_dot**2",
        "theta_dot**2",
        "theta_dot*x_dot*cos(theta)",
        "cos(theta)",
    }
    assert (table.coefficient[~table.kept] == 0).all()


@pytest.mark.filterwarnings("ignore:X has feature names")
def test_dataframe_in_gives_named_frames_out(cart_model, cart_data):
    df = cart_data.to_frame().iloc[100:160]
    forces = cart_model.predict(df)
    acc = cart_model.predict_acceleration(df, df)  # tau_<q> columns matched by name
    assert list(forces.columns) == ["tau_x", "tau_theta"] and forces.index.equals(
        df.index
    )
    assert list(acc.columns) == ["x_ddot", "theta_ddot"] and acc.index.equals(df.index)
    X = df[cart_data.feature_names].to_numpy()
    np.testing.assert_allclose(forces.to_numpy(), cart_model.predict(X), atol=1e-12)
    tau = df[["tau_x", "tau_theta"]].to_numpy()
    np.testing.assert_allclose(
        acc.to_numpy(), cart_model.predict_acceleration(X, tau), atol=1e-12
    )
    assert isinstance(cart_model.predict(X), np.ndarray)


def test_multiarm_loader_reports_missing_data(tmp_path, monkeypatch):
    monkeypatch.setenv(lio.MULTIARM_ENV, str(tmp_path / "absent"))
    with pytest.raises(FileNotFoundError, match="LAGSINDY_MULTIARM_DIR"):
        lio.load_multiarm_pendulum()
    with pytest.raises(ValueError, match="which"):
        lio.load_multiarm_pendulum(tmp_path, which="quadruple")


def test_multiarm_loader_reads_the_recordings():
    try:
        folder = lio.find_multiarm_pendulum()
    except FileNotFoundError:
        pytest.skip("MultiArm-Pendulum data not available")
    single = lio.load_multiarm_pendulum(folder, which="single", split="id")
    assert list(single.columns) == ["trajectory", "t", "theta", "theta_dot_filtered"]
    assert single.trajectory.nunique() == 4 and len(single) == 4 * 9167
    assert np.all(np.diff(single.t) > 0)  # segments join into one record
    assert 1.0 < single.theta.min() and single.theta.max() < 5.0  # pi = hanging down
    double = lio.load_multiarm_pendulum(folder, which="double", split="vad")
    assert list(double.columns) == [
        "trajectory",
        "t",
        "theta1",
        "theta2",
        "theta1_dot_filtered",
        "theta2_dot_filtered",
    ]


# --------------------------------------------------------------------------- 0.1.0 files
_V010 = Path(__file__).resolve().parent / "data" / "models_0_1"


@pytest.mark.parametrize(
    "name", ["forces", "forces_1d", "fixed_term", "fixed_mass", "cart_dissipation"]
)
def test_models_saved_by_0_1_0_load_and_predict_identically(name):
    """Files written by lagsindy 0.1.0 (tests/data/models_0_1/make.py) load, print
    the same Lagrangian and predict what 0.1.0 predicted."""
    import json

    recorded = json.loads((_V010 / "predictions.json").read_text())
    assert recorded["lagsindy_version"] == "0.1.0"
    entry = recorded["models"][name]
    est = lio.load_model(_V010 / f"{name}.json")
    X = np.asarray(entry["X"])
    assert est.equation() == entry["equation"]
    # measured: identical to the last bit on this machine; 1e-12 leaves room for
    # another BLAS (the forces are O(1..100))
    np.testing.assert_allclose(est.predict(X), entry["predict"], rtol=1e-12, atol=1e-12)
    tau = entry.get("tau")
    if tau is not None:
        tau = np.asarray(tau)
        tau = tau if tau.ndim == 2 else tau[:, None]
    np.testing.assert_allclose(
        est.predict_acceleration(X, tau),
        entry["predict_acceleration"],
        rtol=1e-10,
        atol=1e-10,
    )
