"""Determinism (issue #8, item 3).

The same data and ``random_state`` give bit-identical coefficients across runs,
across pickling and in a fresh interpreter, and a fit never draws from or changes
the global random state of numpy, torch or Python.
"""

import pickle
import random
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

import lagsindy.cases.acceleration as case_ii
import lagsindy.cases.fixed as case_iii
from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.solvers import StagedFISTA
from lagsindy.systems import make_dataset, single_pendulum

TERMS = [
    "theta_dot**2",
    "cos(theta)",
    "theta**2",
    "theta_dot**2*cos(theta)",
    "sin(theta)",
]


@pytest.fixture(scope="module")
def active():
    return make_dataset(
        single_pendulum(), n_trajectories=4, duration=1.5, random_state=0
    )


@pytest.fixture(scope="module")
def passive():
    return make_dataset(
        single_pendulum(),
        n_trajectories=4,
        duration=1.5,
        excitation=None,
        random_state=1,
    )


@pytest.fixture
def subsampling(monkeypatch):
    """Make the row subsamples (case III ranking, case II) kick in on small data."""
    monkeypatch.setattr(case_iii, "SELECTION_ROWS", 150)
    monkeypatch.setattr(case_ii, "CASE_II_ROWS", 200)


def library():
    return CandidateLibrary.from_terms(["theta"], TERMS)


FITS = {
    "forces": (dict(), True),
    "fixed": (dict(fixed_term="theta_dot**2"), False),
    "search": (dict(), False),  # case III, every candidate tried, ranked on a subsample
    "acceleration": (
        dict(case="acceleration", solver=StagedFISTA(max_iter=2000)),
        False,
    ),
}


def _fit(kind, data, **extra):
    params, forced = FITS[kind]
    est = LagrangianSINDy(library(), **params, **extra)
    return est.fit(data.X, data.tau) if forced else est.fit(data.X)


def _data(kind, active, passive):
    return active if FITS[kind][1] else passive


def _global_states():
    return np.random.get_state(), torch.get_rng_state().clone(), random.getstate()


def _assert_same_states(before, after):
    (np_a, torch_a, py_a), (np_b, torch_b, py_b) = before, after
    assert (
        np_a[0] == np_b[0] and np.array_equal(np_a[1], np_b[1]) and np_a[2:] == np_b[2:]
    )
    assert torch.equal(torch_a, torch_b)
    assert py_a == py_b


@pytest.mark.parametrize("kind", list(FITS))
@pytest.mark.parametrize("random_state", [None, 0])
def test_same_data_same_coefficients_bit_for_bit(
    kind, random_state, active, passive, subsampling
):
    data = _data(kind, active, passive)
    a = _fit(kind, data, random_state=random_state)
    b = _fit(kind, data, random_state=random_state)
    assert a.coef_.tobytes() == b.coef_.tobytes()
    assert a.fixed_term_ == b.fixed_term_ and a.n_iter_ == b.n_iter_
    for sa, sb in zip(a.stages_, b.stages_, strict=True):
        assert sa.coef.tobytes() == sb.coef.tobytes()


@pytest.mark.parametrize("kind", list(FITS))
@pytest.mark.parametrize("random_state", [None, 0, "instance"])
def test_fit_leaves_global_random_state_alone(
    kind, random_state, active, passive, subsampling
):
    data = _data(kind, active, passive)
    if random_state == "instance":
        random_state = np.random.RandomState(
            3
        )  # the caller's own generator may advance
    np.random.seed(12345)
    torch.manual_seed(12345)
    random.seed(12345)
    before = _global_states()
    _fit(kind, data, random_state=random_state)
    _assert_same_states(before, _global_states())


def test_random_state_matters_only_through_the_subsample(passive, subsampling):
    """An int seed and a RandomState with that seed draw the same rows."""
    a = _fit("search", passive, random_state=7)
    b = _fit("search", passive, random_state=np.random.RandomState(7))
    assert a.coef_.tobytes() == b.coef_.tobytes()


def test_global_seed_does_not_change_the_fit(passive, subsampling):
    np.random.seed(0)
    a = _fit("search", passive)
    np.random.seed(1)
    b = _fit("search", passive)
    assert a.coef_.tobytes() == b.coef_.tobytes()


def test_pickled_estimators_fit_and_predict_identically(active, passive, subsampling):
    for kind in ("forces", "search"):
        data = _data(kind, active, passive)
        params, forced = FITS[kind]
        est = LagrangianSINDy(library(), random_state=0, **params)
        unfitted = pickle.loads(pickle.dumps(est))
        args = (data.X, data.tau) if forced else (data.X,)
        est.fit(*args)
        unfitted.fit(*args)
        assert est.coef_.tobytes() == unfitted.coef_.tobytes()
        back = pickle.loads(pickle.dumps(est))
        assert back.coef_.tobytes() == est.coef_.tobytes()
        assert back.predict(data.X).tobytes() == est.predict(data.X).tobytes()
        assert back.fit(*args).coef_.tobytes() == est.coef_.tobytes()


def test_same_coefficients_in_a_fresh_interpreter(active):
    """Nothing in the fit depends on process state (import order, caches, seeds)."""
    est = LagrangianSINDy(library()).fit(active.X, active.tau)
    script = textwrap.dedent(
        f"""
        import numpy as np
        from lagsindy import CandidateLibrary, LagrangianSINDy
        from lagsindy.systems import make_dataset, single_pendulum
        np.random.seed(99)
        data = make_dataset(single_pendulum(), n_trajectories=4, duration=1.5,
                            random_state=0)
        lib = CandidateLibrary.from_terms(["theta"], {TERMS!r})
        est = LagrangianSINDy(lib).fit(data.X, data.tau)
        print(est.coef_.tobytes().hex())
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
        cwd=str(__import__("pathlib").Path(__file__).parents[1]),
    )
    assert out.stdout.strip() == est.coef_.tobytes().hex()


def test_thread_count_does_not_change_the_fit(active):
    """The Gram accumulation and the solver give the same bits on 1 or 2 threads."""
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = LagrangianSINDy(library()).fit(active.X, active.tau).coef_
        torch.set_num_threads(2)
        two = LagrangianSINDy(library()).fit(active.X, active.tau).coef_
    finally:
        torch.set_num_threads(threads)
    assert one.tobytes() == two.tobytes()
