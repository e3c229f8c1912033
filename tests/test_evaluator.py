"""The one evaluator of per-term Euler-Lagrange parts (lagsindy.evaluator).

Sympy terms (batched kernels, torch.func for the others) and a torch term function
(a planar two-link arm's energies, written as torch code) against sympy's own
Euler-Lagrange equations, against each other, and the NumPy path against torch.
"""

import pickle

import numpy as np
import pytest
import sympy as sp
import torch
from _sympy_reference import random_states, sympy_columns
from sympy.calculus.euler import euler_equations

from lagsindy._expr import compile_torch, symbols_for
from lagsindy.evaluator import (
    NumpyParts,
    TermEvaluator,
    TorchTerms,
    euler_lagrange_parts,
    is_term_function,
    lagrangian_columns,
    lagrangian_components,
)
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    single_pendulum,
    spherical_pendulum,
)

SYSTEMS = [single_pendulum, cart_pendulum, double_pendulum, spherical_pendulum]
ARM = ["q1", "q2"]
# Agreement of two evaluations that differ only in rounding, relative to the
# largest entry (measured: 1e-16 to 3.5e-16 in every comparison of this file).
ROUNDING = 2e-15
L1, G = 0.7, 9.81


def _arm_sympy():
    """The arm's terms in sympy: what the torch code below computes."""
    (q1, q2), (w1, w2), _ = symbols_for(ARM)
    return [
        (w1**2) / 2,  # link 1's rotation
        (w1 + w2) ** 2 / 2,  # link 2's rotation
        L1 * w1 * (w1 + w2) * sp.cos(q2),  # link 2's centre: elbow x rotation
        (L1 * w1) ** 2 / 2,  # the elbow's translation
        -G * L1 * sp.sin(q1),  # heights (potential energy, sign of L)
        -G * sp.sin(q1 + q2),
    ]


def _arm_energies(q, qd):
    """Per-parameter energies of a planar two-link arm from its kinematics (torch)."""
    w1, w2 = qd[0], qd[0] + qd[1]
    elbow_v = L1 * w1 * torch.stack([-torch.sin(q[0]), torch.cos(q[0])])
    normal = torch.stack([-torch.sin(q[0] + q[1]), torch.cos(q[0] + q[1])])
    return torch.stack(
        [
            w1**2 / 2,
            w2**2 / 2,
            (elbow_v * normal).sum() * w2,
            (elbow_v * elbow_v).sum() / 2,
            -G * L1 * torch.sin(q[0]),
            -G * torch.sin(q[0] + q[1]),
        ]
    )


ARM_TERMS = TorchTerms([f"arm{k}" for k in range(6)], _arm_energies)


def _euler_columns(terms, names, q, qd, qdd):
    """Theta[s, i, k] from ``sympy.calculus.euler.euler_equations``."""
    t = sp.Symbol("t")
    q_s, qd_s, qdd_s = symbols_for(names)
    funcs = [sp.Function(n)(t) for n in names]
    to_t = {**dict(zip(q_s, funcs)), **{v: f.diff(t) for v, f in zip(qd_s, funcs)}}
    back = {f.diff(t, 2): a for f, a in zip(funcs, qdd_s)}
    back.update({f.diff(t): v for f, v in zip(funcs, qd_s)})
    # markers b_i q_i, set to 0 after: sympy drops equations such as 0 = 0 or 1 = 0
    marks = sp.symbols(f"b0:{len(names)}")
    marked = sum(b * f for b, f in zip(marks, funcs))
    exprs = []
    for term in terms:
        eqs = euler_equations(sp.sympify(term).subs(to_t) + marked, funcs, t)
        assert len(eqs) == len(names)
        # sympy's lhs is dL/dq - d/dt dL/dqd: the column is its negative
        for eq in eqs:
            e = -eq.lhs.subs(back).subs({b: 0 for b in marks})
            exprs.append(e.subs(dict(zip(funcs, q_s))))
    f = sp.lambdify(q_s + qd_s + qdd_s, exprs, modules="numpy")
    n = q.shape[0]
    values = f(*q.numpy().T, *qd.numpy().T, *qdd.numpy().T)
    out = np.stack([np.broadcast_to(np.asarray(v, float), (n,)) for v in values], 1)
    return out.reshape(n, len(terms), len(names)).transpose(0, 2, 1)


def _close(got, want, rel):
    got, want = np.asarray(got), np.asarray(want)
    np.testing.assert_allclose(got, want, rtol=rel, atol=rel * np.abs(want).max())


@pytest.mark.parametrize("system", SYSTEMS)
def test_columns_agree_with_sympy_euler_equations(system):
    """The columns of the paper's libraries equal sympy's euler_equations."""
    lib = system().paper_library()
    names = lib.coordinates_
    terms = lib.terms_[:: 1 + len(lib.terms_) // 12]  # sympy's part is slow
    q, qd, qdd = random_states(len(names), 25, 0)
    got = TermEvaluator(names, terms).columns(q, qd, qdd)
    _close(got, _euler_columns(terms, names, q, qd, qdd), ROUNDING)


def test_torch_term_function_columns_agree_with_sympy():
    """A torch term function (the arm) gives sympy's Euler-Lagrange columns."""
    assert is_term_function(ARM_TERMS) and not is_term_function(_arm_sympy())
    q, qd, qdd = random_states(2, 30, 1)
    ev = TermEvaluator(ARM, ARM_TERMS)
    assert ev.n_terms == 6 and ev.names == ARM_TERMS.names and ev.kernels is None
    got = ev.columns(q, qd, qdd).numpy()
    want = _euler_columns(_arm_sympy(), ARM, q, qd, qdd)
    _close(got, want, ROUNDING)
    _close(got, sympy_columns(_arm_sympy(), ARM, q, qd, qdd), ROUNDING)
    _close(ev.values(q, qd), TermEvaluator(ARM, _arm_sympy()).values(q, qd), ROUNDING)


def test_components_agree_with_sympy_derivatives():
    """M, N and O of both providers equal sympy's derivatives of every term."""
    terms = _arm_sympy()
    q_s, qd_s, _ = symbols_for(ARM)
    q, qd, _ = random_states(2, 12, 2)
    args = q_s + qd_s
    for ev in (TermEvaluator(ARM, terms), TermEvaluator(ARM, ARM_TERMS)):
        m_mat, n_mat, o = (t.numpy() for t in ev.components(q, qd))
        for k, term in enumerate(terms):
            for i in range(2):
                f = sp.lambdify(args, sp.diff(term, q_s[i]))
                want = np.broadcast_to(f(*q.numpy().T, *qd.numpy().T), (12,))
                _close(o[:, k, i], want, ROUNDING)
                for j in range(2):
                    for got, var in ((m_mat, qd_s[j]), (n_mat, q_s[j])):
                        f = sp.lambdify(args, sp.diff(term, qd_s[i], var))
                        want = np.broadcast_to(f(*q.numpy().T, *qd.numpy().T), (12,))
                        _close(got[:, k, i, j], want, ROUNDING)


def _paths(terms, names, forces=()):
    """The same terms through the batched kernels and through torch.func only."""
    q_s, qd_s, _ = symbols_for(names)
    plain = TorchTerms([str(t) for t in terms], compile_torch(terms, (q_s, qd_s)))
    return TermEvaluator(names, terms, forces), TermEvaluator(names, plain, forces)


@pytest.mark.parametrize("system", [cart_pendulum, double_pendulum])
def test_batched_and_torch_func_paths_agree(system):
    """Every part of the batched kernels equals the torch.func path's to rounding."""
    lib = system().paper_library()
    names = lib.coordinates_
    w = symbols_for(names)[1]
    terms = lib.terms_[:: 1 + len(lib.terms_) // 16]  # torch.func's part is slow
    batched, general = _paths(terms, names, forces=[[-w[0], 0 * w[0]]])
    assert batched.fully_batched and not general.fully_batched
    q, qd, qdd = random_states(2, 40, 3)
    pairs = [
        (batched.columns(q, qd, qdd), general.columns(q, qd, qdd)),
        (batched.columns_t(q, qd, qdd), general.columns_t(q, qd, qdd)),
        *zip(batched.components(q, qd), general.components(q, qd)),
        *zip(batched.parts(q, qd), general.parts(q, qd)),
        (batched.mass_matrices_t(q, qd), general.mass_matrices_t(q, qd)),
        (batched.gradients_t(q, qd), general.gradients_t(q, qd)),
        (batched.hessians_t(q, qd), general.hessians_t(q, qd)),
    ]
    for got, want in pairs:
        _close(got, want, ROUNDING)
    # each path's layouts hold the same values (the samples-last ones are the
    # batched kernels' own: no arithmetic between them)
    for ev in (batched, general):
        assert torch.equal(
            ev.mass_matrices_t(q, qd), ev.mass_matrices(q, qd).permute(1, 2, 3, 0)
        )
        assert torch.equal(ev.gradients_t(q, qd), ev.gradients(q, qd).permute(1, 2, 0))
        assert torch.equal(ev.hessians_t(q, qd), ev.hessians(q, qd).permute(1, 2, 3, 0))
        assert torch.equal(
            ev.columns_t(q, qd, qdd), ev.columns(q, qd, qdd).permute(1, 2, 0)
        )
        assert torch.equal(
            ev.force_jacobians_t(q, qd), ev.force_jacobians(q, qd).permute(1, 2, 3, 0)
        )
        out = torch.full((2, ev.n_columns, 40), float("nan"), dtype=torch.float64)
        assert torch.equal(
            ev.columns_into(q, qd, qdd, out, {}), ev.columns_t(q, qd, qdd)
        )


def test_parts_give_the_columns():
    """M_k qdd + h_k is the column of each term, -Q_j that of each force."""
    x, t = sp.symbols("x theta", real=True)
    xd, td = sp.symbols("x_dot theta_dot", real=True)
    terms = [xd**2, xd * td * sp.cos(t), sp.exp(-(x**2)) * td**2, sp.cos(t)]
    ev = TermEvaluator(["x", "theta"], terms, forces=[[-sp.tanh(5 * xd), td]])
    assert not ev.fully_batched  # exp(-x^2) takes the torch.func path
    q, qd, qdd = random_states(2, 20, 4)
    mass, bias = ev.parts(q, qd)
    assert mass.shape == (20, 4, 2, 2) and bias.shape == (20, 5, 2)
    want = ev.columns(q, qd, qdd)
    got = torch.einsum("skij,sj->sik", mass, qdd) + bias[:, :4].transpose(1, 2)
    _close(got, want[:, :, :4], ROUNDING)
    assert torch.equal(bias[:, 4:].transpose(1, 2), want[:, :, 4:])


def test_numpy_parts_equal_the_torch_parts():
    """The compiled NumPy path (refine's rollouts, simulation) equals the torch
    parts, for sympy terms (lambdified) and a torch term function (through torch)."""
    xd = symbols_for(ARM)[1]
    forces = [[-xd[0], -(xd[1] ** 3)]]
    q, qd, _ = random_states(2, 15, 5)
    for terms in (_arm_sympy(), ARM_TERMS):
        ev = TermEvaluator(ARM, terms, forces)
        fast = ev.numpy_parts()
        assert ev.numpy_parts() is fast  # compiled once
        assert (fast.n_dof, fast.n_lagrangian, fast.n_features) == (2, 6, 7)
        mass, bias = fast.parts(q.numpy(), qd.numpy())
        want_m, want_h = ev.parts(q, qd)
        _close(mass, want_m.numpy(), ROUNDING)
        _close(bias, want_h.numpy(), ROUNDING)
    # the same term set compiles once per process
    again = TermEvaluator(ARM, _arm_sympy(), forces).numpy_parts()
    assert again is TermEvaluator(ARM, _arm_sympy(), forces).numpy_parts()


def test_one_model_by_reverse_mode_equals_the_combined_parts():
    """numpy_model of a torch term function (reverse-mode derivatives of the
    scalar L) equals the sympy terms' compiled parts combined; so do the energies."""
    xd = symbols_for(ARM)[1]
    forces = [[-xd[0], -(xd[1] ** 3)]]
    coef = np.array([1.3, 0.4, 0.25, 2.0, 0.5, 0.3, 0.7])
    q, qd, _ = random_states(2, 15, 10)
    sym = TermEvaluator(ARM, _arm_sympy(), forces)
    tor = TermEvaluator(ARM, ARM_TERMS, forces)
    mass, bias = sym.numpy_model(coef)(q.numpy(), qd.numpy())
    want_m, want_h = sym.parts(q, qd)
    c = torch.as_tensor(coef)
    _close(mass, torch.einsum("skij,k->sij", want_m, c[:6]).numpy(), ROUNDING)
    _close(bias, torch.einsum("ski,k->si", want_h, c).numpy(), ROUNDING)
    got_m, got_h = tor.numpy_model(coef)(q.numpy(), qd.numpy())
    _close(got_m, mass, ROUNDING)
    _close(got_h, bias, ROUNDING)
    energy = sym.energies(coef, q, qd)
    _close(tor.energies(coef, q, qd), energy, ROUNDING)
    lag = sym.values(q, qd) @ c[:6]
    momenta = torch.einsum("skj,k->sj", sym.gradients(q, qd)[..., 2:], c[:6])
    _close(energy, (qd * momenta).sum(1) - lag, ROUNDING)
    with pytest.raises(ValueError, match="one entry per column"):
        tor.numpy_model(coef[:6])


def test_numpy_parts_from_expressions_keep_constant_entries():
    """Constant entries (here every mass entry) are filled without lambdify."""
    (x,), (xd,), _ = symbols_for(["x"])
    _, m, h = euler_lagrange_parts(3 * xd**2 + x**2, [x], [xd])
    assert m == [[6]] and h == [-2 * x]
    parts = NumpyParts.from_expressions(["x"], [[m[0][0]]], [h, [sp.Integer(4)]])
    mass, bias = parts.parts(np.array([[1.0], [2.0]]), np.zeros((2, 1)))
    np.testing.assert_array_equal(mass[:, 0, 0, 0], [6.0, 6.0])
    np.testing.assert_array_equal(bias[:, :, 0], [[-2.0, 4.0], [-4.0, 4.0]])


def test_force_values_and_jacobians_without_vmap_match_torch_func():
    """Force terms are evaluated for all samples at once (the compiled function is
    elementwise) and differentiated by one reverse pass per force component."""
    x, t = sp.symbols("x theta", real=True)
    xd, td = sp.symbols("x_dot theta_dot", real=True)
    forces = [
        [-sp.tanh(40 * xd), 0],
        [0, -td * sp.Abs(td)],
        [sp.Integer(1), 0],  # a constant offset
        [-(x**2) * td, sp.sin(t) * xd],
    ]
    ev = TermEvaluator(["x", "theta"], [xd**2, sp.cos(t)], forces=forces)
    q, qd, _ = random_states(2, 30, 5)
    f = compile_torch([e for fo in forces for e in fo], symbols_for(["x", "theta"])[:2])
    per_sample = torch.func.vmap(f)(q, qd).reshape(30, 4, 2).transpose(1, 2)
    np.testing.assert_array_equal(ev.force_values(q, qd).numpy(), per_sample.numpy())

    def one(q1, qd1):
        return f(q1, qd1).reshape(4, 2)

    fq, fqd = torch.func.vmap(torch.func.jacfwd(one, argnums=(0, 1)))(q, qd)
    want = torch.cat([fq, fqd], dim=3)
    # measured: identical (both are the same derivative)
    np.testing.assert_allclose(
        ev.force_jacobians(q, qd).numpy(), want.numpy(), rtol=1e-14, atol=1e-14
    )


def test_empty_evaluators_give_empty_parts():
    q, qd, qdd = random_states(2, 5, 6)
    ev = TermEvaluator(ARM, [])
    assert ev.fn is None and ev.n_columns == 0
    assert ev.columns(q, qd, qdd).shape == (5, 2, 0)
    assert ev.columns_t(q, qd, qdd).shape == (2, 0, 5)
    assert ev.gradients(q, qd).shape == (5, 0, 4)
    assert ev.hessians(q, qd).shape == (5, 0, 4, 4)
    assert [t.shape for t in ev.components(q, qd)] == [(5, 0, 2, 2)] * 2 + [(5, 0, 2)]


def test_a_torch_term_function_of_the_wrong_shape_is_refused():
    """A provider whose fn gives one value too few (or a column) would broadcast
    into wrong parts: the evaluator says what it returned instead."""
    short = TorchTerms(["a", "b"], lambda q, qd: qd[:1] ** 2)
    column = TorchTerms(["a", "b"], lambda q, qd: torch.stack([qd, q]))
    broken = TorchTerms(["a"], lambda q, qd: q.item())
    q, qd, qdd = random_states(2, 4, 8)
    for provider, match in (
        (short, r"shape \(2,\).*got \(1,\)"),
        (column, r"got \(2, 2\)"),
    ):
        with pytest.raises(ValueError, match=match):
            TermEvaluator(ARM, provider).columns(q, qd, qdd)
    with pytest.raises(ValueError, match="failed on one sample"):
        TermEvaluator(ARM, broken).mass_matrices(q, qd)


def test_evaluator_pickles_without_compiled_code():
    xd = symbols_for(ARM)[1]
    ev = TermEvaluator(ARM, _arm_sympy(), forces=[[-xd[0], 0 * xd[0]]])
    q, qd, qdd = random_states(2, 8, 7)
    want = ev.columns(q, qd, qdd)
    ev.numpy_parts()
    again = pickle.loads(pickle.dumps(ev))
    assert torch.equal(again.columns(q, qd, qdd), want)


def test_the_0_1_module_keeps_its_names():
    import lagsindy.euler_lagrange as old

    for name in (
        "DEFAULT_CHUNK_SIZE", "NOISE_ROWS", "EulerLagrangeOperator",
        "forward_accelerations", "lagrangian_columns", "lagrangian_components",
        "lagrangian_gradients", "bump_function", "check_time_order",
        "estimate_noise_covariance", "estimate_sampling_interval",
        "trajectory_segments",
    ):  # fmt: skip
        assert hasattr(old, name), name
    assert old.lagrangian_columns is lagrangian_columns
    assert old.lagrangian_components is lagrangian_components
