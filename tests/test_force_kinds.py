"""The force-kind registry (lagsindy.force_kinds): every kind's contract, and a kind
registered by a user working end to end."""

import json

import numpy as np
import pytest
import sympy as sp

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy, force_kinds
from lagsindy._expr import parse_expression, state_names
from lagsindy.diagnostics.report import Candidate, _units
from lagsindy.dissipation import ForceTerm, library_of, make_term, rebuild_term
from lagsindy.force_kinds import ForceKind
from lagsindy.io.model_file import expression_to_string
from lagsindy.systems import make_dataset
from lagsindy.systems.base import System

COORDS = ["a", "b", "c"]
UNITS = {c: ("m", "N") for c in COORDS}
KIND_NAMES = force_kinds.names()  # the built-in kinds (no user kind registered yet)


def _terms(kind):
    """A term of ``kind`` on every target of three coordinates (default parameters)."""
    record = force_kinds.get(kind)
    return [make_term(kind, record.target(t), COORDS) for t in record.targets(COORDS)]


def _states(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-2.0, 2.0, (n, 2 * len(COORDS)))


def _values(exprs, states):
    """``exprs`` (in q, q_dot of COORDS) at each row of ``states``."""
    symbols = [
        sp.Symbol(n, real=True) for n in state_names(COORDS, accelerations=False)
    ]
    f = sp.lambdify(symbols, list(exprs), "numpy")
    return np.array([np.broadcast_to(v, len(states)) for v in f(*states.T)]).T


# -- the contract every registered kind meets ---------------------------------------


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_every_kind_builds_a_force_on_its_own_coordinates(kind):
    record = force_kinds.get(kind)
    for term in _terms(kind):
        assert term.name == f"{kind}({','.join(term.coordinates)})"
        assert len(term.coordinates) == record.arity
        assert len(term.forces) == len(COORDS)
        others = [c for c in COORDS if c not in term.coordinates]
        assert all(term.forces[COORDS.index(c)] == 0 for c in others)
        values = _values(term.forces, _states())
        assert np.all(np.isfinite(values)) and np.any(values != 0)
        if term.rayleigh is not None:  # the force is -dD/dq_dot
            qd = [sp.Symbol(f"{c}_dot", real=True) for c in COORDS]
            want = _values([-sp.diff(term.rayleigh, s) for s in qd], _states())
            np.testing.assert_allclose(values, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_dissipative_kinds_only_remove_energy(kind):
    # Power of the force for a unit coefficient, sum_i Q_i q_dot_i, at random states:
    # never positive for a dissipative kind (its coefficient is constrained >= 0);
    # a kind that is not (bias) feeds energy in somewhere, so its sign stays free.
    record = force_kinds.get(kind)
    states = _states()
    velocities = states[:, len(COORDS) :]
    for term in _terms(kind):
        power = np.sum(_values(term.forces, states) * velocities, axis=1)
        assert term.dissipative == record.dissipative == record.nonnegative
        if record.dissipative:
            assert power.max() <= 1e-12
        else:
            assert power.max() > 0.1


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_every_kind_has_units_and_report_wording(kind):
    record = force_kinds.get(kind)
    for term in _terms(kind):
        units = term.units(UNITS)
        assert units == record.coefficient_units("m", "N") and "N" in units
        cand = Candidate(kind, term.name, term.coordinates, term)
        assert cand.description == record.wording and record.wording != kind
        assert _units(cand, UNITS, passive=False) == units
        words = _units(cand, None, passive=False)
        assert words == record.unit_words(term.coordinates)
        assert term.coordinates[0] in words
        assert _units(cand, None, passive=True) == "rel. to fixed term"


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_every_kind_survives_the_model_files_text(kind):
    # A model file stores a term's forces as text; loading rebuilds the term from
    # its kind, coordinates and the parameters read back from that text.
    record = force_kinds.get(kind)
    allowed = state_names(COORDS, accelerations=False)
    changed = {name: 1.7 * default for name, default in record.parameters}
    for target in record.targets(COORDS):
        term = make_term(kind, record.target(target), COORDS, **changed)
        assert term.parameters == pytest.approx(changed, rel=1e-14)
        text = [expression_to_string(f) for f in term.forces]
        parsed = [parse_expression(t, allowed) for t in text]
        again = rebuild_term(kind, term.coordinates, COORDS, parsed)
        assert again.name == term.name
        assert again.parameters == pytest.approx(changed, rel=1e-14)
        np.testing.assert_allclose(
            _values(again.forces, _states()),
            _values(term.forces, _states()),
            rtol=1e-13,
            atol=1e-15,
        )


@pytest.mark.parametrize(
    "kind", [k for k in KIND_NAMES if force_kinds.get(k).parameters]
)
def test_forces_without_the_kinds_shape_are_refused(kind):
    a_dot = sp.Symbol("a_dot", real=True)
    for forces in ([-a_dot, 0, 0], [-sp.tanh(a_dot) * sp.tanh(2 * a_dot), 0, 0]):
        with pytest.raises(ValueError, match=f"a {kind} term"):
            rebuild_term(kind, ("a",), COORDS, forces)


def test_every_kind_is_named_by_the_cli_and_in_diagnoses_catalogue_as_marked():
    from lagsindy.cli.parser import _catalogue_help
    from lagsindy.diagnostics import DEFAULT_CATALOGUE
    from lagsindy.formulation.probes import PROBE_KINDS

    help_text = _catalogue_help()
    for record in force_kinds.kinds():
        assert record.name in help_text
        assert (record.name in DEFAULT_CATALOGUE) == record.in_default_catalogue
    # the catalogue's order (the search's candidate columns) is the old one
    assert tuple(DEFAULT_CATALOGUE)[:8] == (
        "delay",
        "viscous",
        "relative",
        "drag",
        "coulomb",
        "bias",
        "gain",
        "conservative",
    )
    assert PROBE_KINDS == ("viscous", "coulomb")


def test_old_names_still_importable_and_bias_is_not_dissipative():
    from lagsindy.dissipation import DEFAULT_EPS, DISSIPATIVE_KINDS, KINDS

    legacy = ("viscous", "relative", "drag", "coulomb", "bias")
    assert KINDS == force_kinds.names() and KINDS[:5] == legacy
    assert DISSIPATIVE_KINDS[:4] == legacy[:4] and "bias" not in DISSIPATIVE_KINDS
    assert DISSIPATIVE_KINDS == tuple(
        k for k in KINDS if force_kinds.get(k).dissipative
    )
    assert DEFAULT_EPS == 0.01
    # diagnose's sets (used by its search) agree with the records: bias is a force
    # kind (built by the dissipation library) whose sign is free
    from lagsindy.diagnostics.catalogue import _DISSIPATIVE, _NONNEGATIVE

    assert "bias" in _DISSIPATIVE and "bias" not in _NONNEGATIVE
    assert list(_NONNEGATIVE) == list(DISSIPATIVE_KINDS)
    assert "gain" not in _DISSIPATIVE and "magic" not in _NONNEGATIVE


def _oscillator(force, name="oscillator"):
    """A forced unit mass on a spring (stiffness 4) with the extra force ``force``."""
    x, x_dot = sp.symbols("x x_dot", real=True)
    return System(
        x_dot**2 / 2 - 2 * x**2,
        ["x"],
        initial_ranges={"x": (-1, 1), "x_dot": (-1, 1)},
        library=lambda: CandidateLibrary.from_terms(["x"], ["x**2", "x_dot**2"]),
        paper_input=lambda t, w: (2 * np.cos(w * t))[:, None],
        forces=[force(x, x_dot)],
        name=name,
    )


def test_a_bias_force_is_fitted_with_its_sign():
    # bias is not constrained: a negative offset force is found as negative
    system = _oscillator(lambda x, v: sp.Float(-0.3) - sp.Float(0.2) * v)
    data = make_dataset(system, n_trajectories=4, excitation="paper", random_state=0)
    est = LagrangianSINDy(
        system.paper_library(),
        dissipation=DissipationLibrary(["viscous", "bias"]),
        formulation="strong",
    ).fit(data.X, data.tau)
    # exact derivatives: exact to rounding (measured relative error 5.2e-14)
    np.testing.assert_allclose(est.dissipation_coef_, [0.2, -0.3], rtol=3e-13)


# -- a kind a user registers ---------------------------------------------------------


def _cubic(q, qd, *, scale):
    return None, (qd[0] / sp.Float(scale)) ** 4 / 4


def _read_cubic(forces, q, qd):
    # force -(v/s)**3 / s: the coefficient of v**3 is -1/s**4
    coeff = sp.Add(*forces).as_coeff_Mul()[0]
    if sp.Add(*forces) != coeff * qd[0] ** 3 or coeff >= 0:
        raise ValueError("its force is not -c * q_dot**3")
    return {"scale": float((-coeff) ** -0.25)}


CUBIC = ForceKind(
    "cubic_damping",
    _cubic,
    dissipative=True,
    units="{F}*s^3/{q}^3",
    units_text="per unit of {0}_dot^3",
    wording="cubic damping",
    parameters=(("scale", 1.0),),
    read_parameters=_read_cubic,
    in_default_catalogue=True,
)


@pytest.fixture
def cubic():
    force_kinds.register(CUBIC)
    yield CUBIC
    force_kinds.unregister(CUBIC.name)


def test_a_registered_kind_is_fitted_saved_and_reported(cubic, tmp_path):
    from lagsindy.diagnostics import DEFAULT_CATALOGUE

    system = _oscillator(lambda x, v: -sp.Float(0.4) * v**3, "cubic oscillator")
    data = make_dataset(system, n_trajectories=4, excitation="paper", random_state=1)
    dissipation = DissipationLibrary(["viscous", "cubic_damping"])
    est = LagrangianSINDy(
        system.paper_library(), dissipation=dissipation, formulation="strong"
    ).fit(data.X, data.tau)
    assert [t.name for t in est.dissipation_terms_] == [
        "viscous(x)",
        "cubic_damping(x)",
    ]
    # exact derivatives: exact to rounding (measured error 1.7e-16, one ulp of 0.4;
    # the bound leaves room for another machine's summation order)
    np.testing.assert_allclose(est.dissipation_coef_, [0.0, 0.4], atol=1e-14)
    assert est.dissipation_terms_[1].units({"x": ("m", "N")}) == "N*s^3/m^3"
    # the model file stores it and loading rebuilds it through the registry
    path = est.save(tmp_path / "cubic.json")
    entry = json.loads(path.read_text())["dissipation"][1]
    assert entry["kind"] == "cubic_damping" and entry["forces"] == ["-1.0*x_dot**3"]
    loaded = LagrangianSINDy.load(path)
    assert loaded.dissipation_terms_ == est.dissipation_terms_
    np.testing.assert_array_equal(loaded.predict(data.X), est.predict(data.X))
    # diagnose proposes it (registered with in_default_catalogue=True), before the
    # gain and conservative candidates; its own parameter travels with the library
    assert tuple(DEFAULT_CATALOGUE)[-3:] == ("cubic_damping", "gain", "conservative")
    scaled = DissipationLibrary(
        ["cubic_damping"], coordinates=["x"], parameters={"scale": 2.0}
    ).build()
    (term,) = scaled.terms_
    assert term.forces == (-x_dot_cubed(2.0),) and term.parameters == {"scale": 2.0}
    assert library_of(scaled.terms_, ["x"]).build().terms_ == scaled.terms_


def x_dot_cubed(scale):
    return sp.Symbol("x_dot", real=True) ** 3 / sp.Float(scale) ** 4


def test_unregistered_kind_is_refused_everywhere(cubic, tmp_path):
    force_kinds.unregister(cubic.name)
    try:
        with pytest.raises(ValueError, match="unknown dissipation kinds"):
            DissipationLibrary(["cubic_damping"], coordinates=["x"]).build()
        with pytest.raises(ValueError, match="unknown dissipation kind"):
            make_term("cubic_damping", "x", ["x"])
        from lagsindy.diagnostics import DEFAULT_CATALOGUE

        assert "cubic_damping" not in DEFAULT_CATALOGUE
    finally:
        force_kinds.register(cubic)  # the same record may come back


def test_registry_refuses_unclear_records():
    build = CUBIC.build
    with pytest.raises(ValueError, match="already registered"):
        force_kinds.register(force_kinds.get("viscous"))
    with pytest.raises(ValueError, match="built-in"):
        force_kinds.unregister("coulomb")
    with pytest.raises(ValueError, match="reserved"):
        ForceKind("gain", build)
    with pytest.raises(ValueError, match="identifier"):
        ForceKind("two words", build)
    with pytest.raises(ValueError, match="read_parameters"):
        ForceKind("needs_reader", build, parameters=(("scale", 1.0),))
    with pytest.raises(ValueError, match="template"):
        ForceKind("bad_units", build, units="{G}")
    with pytest.raises(ValueError, match="arity"):
        ForceKind("nullary", build, arity=0)
    with pytest.raises(ValueError, match="unknown dissipation kind 'sticky'"):
        force_kinds.get("sticky")
    # a name keeps its meaning for the session (fits cache the terms built from it)
    first = force_kinds.register(ForceKind("once_only", build))
    force_kinds.unregister("once_only")
    with pytest.raises(ValueError, match="earlier in this session"):
        force_kinds.register(ForceKind("once_only", lambda q, qd: (None, qd[0] ** 2)))
    force_kinds.register(first)
    force_kinds.unregister("once_only")


def test_library_parameters_are_checked():
    with pytest.raises(ValueError, match="no force kind has"):
        DissipationLibrary(["viscous"], coordinates=["x"], parameters={"v": 1}).build()
    with pytest.raises(ValueError, match="eps="):
        DissipationLibrary(
            ["coulomb"], coordinates=["x"], parameters={"eps": 1}
        ).build()
    with pytest.raises(ValueError, match="not among"):
        DissipationLibrary(["viscous"], coordinates=["x"], eps={"y": 0.1}).build()
    with pytest.raises(ValueError, match="no parameters"):
        make_term("viscous", "x", ["x"], scale=2.0)
    with pytest.raises(ValueError, match="eps must be positive"):
        make_term("coulomb", "x", ["x"], eps=0.0)
    # a term spec may carry its own parameters
    lib = DissipationLibrary(
        (), coordinates=["x"], terms=[("coulomb", "x", {"eps": 0.5})]
    )
    (term,) = lib.build().terms_
    assert term.eps == 0.5 and isinstance(term, ForceTerm)
    with pytest.raises(ValueError, match="dict of parameters"):
        DissipationLibrary((), coordinates=["x"], terms=[("coulomb", "x", 0.5)]).build()


# -- Stribeck friction: a kind added as one record -----------------------------------

EPS, V_S = 0.05, 0.3  # smoothing and Stribeck velocities of the data below


def _stribeck_force(x, v):
    # mu_c = 0.3, mu_s = 0.5: -(0.3 + 0.2 exp(-(v/V_S)**2)) tanh(v/EPS)
    smooth = sp.tanh(v / sp.Float(EPS))
    bump = sp.exp(-((v / sp.Float(V_S)) ** 2))
    return -(sp.Float(0.3) + sp.Float(0.2) * bump) * smooth


@pytest.fixture(scope="module")
def stribeck_data():
    system = _oscillator(_stribeck_force, "Stribeck oscillator")
    return make_dataset(system, n_trajectories=4, excitation="paper", random_state=2)


def _stribeck_fit(data, kinds):
    return LagrangianSINDy(
        CandidateLibrary.from_terms(["x"], ["x**2", "x_dot**2"]),
        dissipation=DissipationLibrary(kinds, eps=EPS, parameters={"v_s": V_S}),
        formulation="strong",
    ).fit(data.X, data.tau, groups=data.groups)


def test_stribeck_is_fitted_beside_coulomb_and_saved(stribeck_data, tmp_path):
    est = _stribeck_fit(stribeck_data, ["coulomb", "stribeck"])
    stribeck = est.dissipation_terms_[1]
    assert stribeck.name == "stribeck(x)"
    assert stribeck.parameters == pytest.approx({"eps": EPS, "v_s": V_S}, rel=1e-14)
    # exact derivatives: exact to rounding (measured error 3.9e-14 and 6.6e-14)
    np.testing.assert_allclose(est.dissipation_coef_, [0.3, 0.2], atol=2e-13)
    np.testing.assert_allclose(est.coef_, [-2.0, 0.5], atol=3e-13)
    path = est.save(tmp_path / "stribeck.json")
    entry = json.loads(path.read_text())["dissipation"][1]
    assert entry["kind"] == "stribeck" and "exp(" in entry["forces"][0]
    loaded = LagrangianSINDy.load(path)
    assert [t.name for t in loaded.dissipation_terms_] == ["coulomb(x)", "stribeck(x)"]
    assert loaded.dissipation_terms_[1].parameters == pytest.approx(
        {"eps": EPS, "v_s": V_S}, rel=1e-14
    )
    X = stribeck_data.X
    np.testing.assert_array_equal(loaded.predict(X), est.predict(X))  # measured
    assert loaded.dissipation.get_params()["parameters"] == {"v_s": {"x": V_S}}


def test_diagnose_finds_stribeck_when_asked_and_reports_its_units(stribeck_data):
    from lagsindy import diagnose
    from lagsindy.diagnostics import DEFAULT_CATALOGUE

    assert "stribeck" not in DEFAULT_CATALOGUE  # proposed only when named
    est = _stribeck_fit(stribeck_data, ["coulomb"])
    report = diagnose(
        est,
        stribeck_data.X,
        stribeck_data.tau,
        groups=stribeck_data.groups,
        catalogue=["stribeck"],
        eps={"x": EPS},
        units={"x": ("m", "N")},
    )
    (step,) = [s for s in report.steps if s.how != "start"]
    assert step.candidate.name == "stribeck(x)" and step.units == "N"
    assert report.effects == ["stribeck(x)"]
    # the table lists the starting model's effects too (#44)
    assert [(s.candidate.name, s.how) for s in report.steps[1:]] == [
        ("coulomb(x)", "start")
    ]
    text = str(report)
    assert "Stribeck friction" in text and "stribeck(x)" in text
    # the candidate took v_s from the model's dissipation library
    final = dict(zip(report.final.dissipation_terms_, report.final.dissipation_coef_))
    (term,) = [t for t in final if t.kind == "stribeck"]
    assert term.parameters == pytest.approx({"eps": EPS, "v_s": V_S}, rel=1e-14)
    # the final refit is exact to rounding (measured relative error 1.5e-13)
    assert final[term] == pytest.approx(0.2, rel=7e-13)


def test_terms_of_one_coordinate_keep_their_own_parameters():
    coords = ["x"]
    terms = [
        make_term("coulomb", "x", coords, eps=0.02),
        make_term("stribeck", "x", coords, eps=0.05, v_s=0.4),
    ]
    lib = library_of(terms, coords)
    # the coordinate's eps is the first term's; the Stribeck term keeps its own
    assert lib.eps == {"x": 0.02}
    assert lib.terms[1] == ("stribeck", "x", {"eps": 0.05, "v_s": 0.4})
    assert lib.build().terms_ == terms


@pytest.fixture(scope="module")
def two_oscillators():
    """A fitted model of two forced, uncoupled oscillators (x, y)."""
    x, y, x_dot, y_dot = sp.symbols("x y x_dot y_dot", real=True)
    system = System(
        (x_dot**2 + y_dot**2) / 2 - 2 * x**2 - y**2,
        ["x", "y"],
        initial_ranges={"x": (-1, 1), "x_dot": (-1, 1), "y": (-1, 1), "y_dot": (-1, 1)},
        paper_input=lambda t, w: np.stack([np.cos(w * t), np.sin(w * t)], axis=1),
        name="two oscillators",
    )
    data = make_dataset(system, n_trajectories=3, excitation="paper", random_state=3)
    library = CandidateLibrary.from_terms(["x", "y"], ["x**2", "y**2", "x_dot**2"])
    library = library + CandidateLibrary.from_terms(["x", "y"], ["y_dot**2"])
    dissipation = DissipationLibrary(["viscous"], eps=0.02, parameters={"v_s": 0.4})
    est = LagrangianSINDy(library, dissipation=dissipation, formulation="strong")
    return est.fit(data.X, data.tau)


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_diagnoses_candidates_are_the_terms_its_refits_build(kind, two_oscillators):
    # diagnose builds each candidate from the catalogue and refits with it through
    # the model's dissipation library: both must give the very same term (diagnose's
    # eps for the coordinate, the library's other parameters)
    from lagsindy.diagnostics.catalogue import _catalogue
    from lagsindy.diagnostics.scoring import _fit_model

    est, eps = two_oscillators, {"x": 0.05, "y": 0.07}
    candidates = _catalogue(est, [kind], None, [], None, eps)
    record = force_kinds.get(kind)
    present = {t.name for t in est.dissipation_terms_}  # viscous(x), viscous(y)
    names = {f"{kind}({','.join(t)})" for t in record.targets(["x", "y"])}
    assert {c.name for c in candidates} == names - present
    refit = _fit_model(est, None, None, None, penalized=candidates, eps=eps, fit=False)
    library = refit.dissipation.set_params(coordinates=["x", "y"]).build()
    built = {t.name: t for t in library.terms_}
    for cand in candidates:
        assert built[cand.name] == cand.term
        assert cand.term.parameters == {
            name: eps[cand.coordinates[0]] if name == "eps" else 0.4
            for name in record.parameter_names
        }
