"""The benchmark scripts run end to end (at tiny sizes) and their helpers are right.

The scripts' full-size results are in ``benchmarks/results``; these tests only make
sure the code paths cannot rot: each script's ``main`` runs with ``--quick`` and
``LAGSINDY_BENCH_TINY=1`` (a few short trajectories) into a temporary results folder.
"""

import importlib.util
import json
import types
import warnings

import numpy as np
import pytest
import torch

import benchmarks._common as common
from benchmarks import __main__ as runner
from benchmarks import _evaluate, paper_tables
from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


@pytest.fixture
def tiny_results(tmp_path, monkeypatch):
    """Tiny sizes, and results written to a temporary folder instead of the repo's."""
    monkeypatch.setenv("LAGSINDY_BENCH_TINY", "1")
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    return tmp_path


def _check_header(text):
    assert "- command: `LAGSINDY_BENCH_TINY=1 python -m benchmarks." in text
    assert "- date: " in text
    assert "- machine: " in text and "torch threads" in text


@pytest.mark.slow  # a benchmark script end to end (the methods it measures have their own tests)
def test_long_record_tiny(tiny_results):
    from benchmarks import long_record

    assert long_record.main(["--quick"]) == 0
    text = (tiny_results / "long_record_quick.md").read_text()
    _check_header(text)
    row = next(line for line in text.splitlines() if line.startswith("| 2000 |"))
    assert "| this |" in row and "MiB" in row and "error:" not in row


def test_runner_discovers_every_public_main():
    found = runner.discover()
    assert {"paper_tables", "sindy_pi", "speed"} <= set(found)
    assert not any(name.startswith("_") for name in found)
    assert all(callable(module.main) for module in found.values())


def test_runner_passes_quick_and_reports_failures(monkeypatch, capsys):
    calls = []

    def ok_main(argv):
        calls.append(("ok", list(argv), common.RUNNER_COMMAND))

    def bad_main(argv):
        calls.append(("bad", list(argv), common.RUNNER_COMMAND))
        raise RuntimeError("boom")

    fake = {
        "aa": types.SimpleNamespace(main=ok_main, __doc__="A."),
        "bb": types.SimpleNamespace(main=bad_main, __doc__="B."),
    }
    monkeypatch.setattr(runner, "discover", lambda: fake)
    assert runner.main(["--quick"]) == 1
    assert calls == [
        ("ok", ["--quick"], "python -m benchmarks --quick aa"),
        ("bad", ["--quick"], "python -m benchmarks --quick bb"),
    ]
    assert common.RUNNER_COMMAND is None
    assert "FAILED: ['bb']" in capsys.readouterr().out
    calls.clear()
    assert runner.main(["aa"]) == 0
    assert calls == [("ok", [], "python -m benchmarks aa")]
    with pytest.raises(SystemExit):
        runner.main(["nope"])


def test_compare_structure_up_to_scale():
    system = single_pendulum()
    lib = system.paper_library().build()
    true = system.true_coefficients(lib)
    est = types.SimpleNamespace(
        library_=lib, coef_=2.0 * true, term_names_=lib.get_feature_names_out()
    )
    res = _evaluate.compare_structure(system, est, up_to_scale=True)
    assert (
        res["correct"]
        and res["coef_error"] < 1e-12
        and res["scale"] == pytest.approx(2)
    )
    # Not up to scale, twice the Lagrangian is 100 % off.
    res = _evaluate.compare_structure(system, est, up_to_scale=False)
    assert res["correct"] and res["coef_error"] == pytest.approx(1.0)
    coef = true.copy()
    coef[lib.index("theta**2")] = 0.1
    coef[lib.index("cos(theta)")] = 0.0
    est.coef_ = coef
    res = _evaluate.compare_structure(system, est, up_to_scale=True)
    assert not res["correct"]
    assert res["extra"] == ["theta**2"] and res["missing"] == ["cos(theta)"]


def test_paper_entries_parse_and_mark_their_extra_terms():
    for table in (paper_tables.PAPER_TABLE_I, paper_tables.PAPER_TABLE_II):
        for name, rows in table.items():
            assert sorted(rows) == sorted(_evaluate.NOISE_LEVELS)
    from lagsindy.systems import PAPER_SYSTEMS

    single = PAPER_SYSTEMS["single_pendulum"]()
    res = paper_tables.paper_structure(
        single, paper_tables.PAPER_TABLE_II["single_pendulum"][1e-1]
    )
    assert res["extra"] == sorted(["theta_dot*sin(theta)", "sin(theta)**2", "theta**2"])
    assert paper_tables.paper_structure(
        single, paper_tables.PAPER_TABLE_II["single_pendulum"][6e-2]
    )["correct"]
    sph = PAPER_SYSTEMS["spherical_pendulum"]()
    res = paper_tables.paper_structure(
        sph, paper_tables.PAPER_TABLE_II["spherical_pendulum"][1e-1]
    )
    # sin(2 theta) is 2 sin cos after expansion.
    assert "phi_dot**2*sin(theta)*cos(theta)" in res["extra"]


@pytest.mark.slow  # 9 s; `python -m benchmarks --quick` runs the script too
def test_paper_tables_tiny(tiny_results):
    paper_tables.main(["--quick", "--systems", "cart_pendulum"])
    text = (tiny_results / "paper_tables_quick.md").read_text()
    _check_header(text)
    assert "### cart-pendulum" in text
    assert "automatic fixed-term search" in text
    # The paper's entry is shown beside ours.
    assert paper_tables.PAPER_TABLE_I["cart_pendulum"][2e-2] in text
    assert not (tiny_results / "paper_tables.md").exists()


needs_pysindy = pytest.mark.skipif(
    importlib.util.find_spec("pysindy") is None
    or importlib.util.find_spec("cvxpy") is None,
    reason="pysindy[cvxpy] not installed (pip install -e .[test])",
)


@needs_pysindy
def test_sindy_pi_structure_criterion():
    from benchmarks import sindy_pi

    system = cart_pendulum()
    terms, acc, symbols = sindy_pi.sindy_pi_library(system)
    assert len(terms) == 60 and sum(a >= 0 for a in acc) == 10
    names = [str(t) for t in terms]
    data = make_dataset(
        system, n_trajectories=3, duration=2.0, excitation=None, random_state=0
    )

    def equation(pairs):
        e = np.zeros(len(terms))
        for name, value in pairs.items():
            e[names.index(name)] = value
        return e

    x_eq = {
        "x_ddot": 1.0,
        "theta_ddot*cos(theta)": 1 / 3,
        "theta_dot**2*sin(theta)": -1 / 3,
    }
    th_eq = {"theta_ddot": 1.0, "x_ddot*cos(theta)": 1.0, "sin(theta)": 9.81}
    good = sindy_pi.SINDyPIResult(
        terms,
        acc,
        symbols,
        [
            (names.index("x_ddot"), equation(x_eq)),
            (names.index("theta_ddot"), equation(th_eq)),
        ],
        0.0,
        1.0,
    )
    assert sindy_pi.sindy_pi_structure(good, system, data.X_clean)["correct"]
    # The true model integrates like the truth.
    x0 = system.sample_initial_states(2, random_state=1)
    t = np.linspace(0, 1, 51)
    states = sindy_pi.simulate_sindy_pi(good, system, x0, t)
    assert sindy_pi.rmse_q(system.simulate(x0, t), states, 2) < 1e-6
    # An extra term, or a missing one, is not the correct structure.
    extra = sindy_pi.SINDyPIResult(
        terms,
        acc,
        symbols,
        [(names.index("x_ddot"), equation({**x_eq, "x": 0.01})), good.equations[1]],
        0.0,
        1.0,
    )
    res = sindy_pi.sindy_pi_structure(extra, system, data.X_clean)
    assert not res["correct"] and "superfluous" in res["detail"][0]
    missing = dict(th_eq)
    del missing["sin(theta)"]
    bad = sindy_pi.SINDyPIResult(
        terms,
        acc,
        symbols,
        [good.equations[0], (names.index("theta_ddot"), equation(missing))],
        0.0,
        1.0,
    )
    res = sindy_pi.sindy_pi_structure(bad, system, data.X_clean)
    assert not res["correct"] and "missing" in res["detail"][0]


@needs_pysindy
@pytest.mark.slow  # a benchmark script end to end (the methods it measures have their own tests)
def test_sindy_pi_tiny(tiny_results):
    from benchmarks import sindy_pi

    sindy_pi.main(["--quick", "--systems", "cart_pendulum"])
    text = (tiny_results / "vs_sindy_pi_quick.md").read_text()
    _check_header(text)
    assert "## Robustness ratio" in text and "| cart pendulum |" in text
    assert text.count("| 0.02 | SINDy-PI |") == 1


def test_speed_default_section_and_one_measurement(tiny_results):
    from benchmarks import speed

    speed.main(["--quick", "--no-scaling"])
    text = (tiny_results / "speed_quick.md").read_text()
    _check_header(text)
    assert "median fit time" in text and "How the cost grows" not in text
    res = speed.measure({"n_rows": 1000, "degree": 3, "device": "cpu", "repeats": 3})
    assert res["n_terms"] == 39 and res["correct"]
    # the reported time is the median of the repeats (never a bound on wall-clock)
    assert len(res["times"]) == 3 and res["time"] == sorted(res["times"])[1]
    # each timed fit is the whole fit: the same iterations as a fit outside the timer
    library = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=3)
    X, tau = speed.random_rows(cart_pendulum(), 1000)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the weak form cannot run on random rows
        assert res["n_iter"] == LagrangianSINDy(library).fit(X, tau).n_iter_
    assert res["threads"] >= 1
    assert res["peak_rss_mib"] >= res["rss_before_mib"] > 0
    # the measurement travels from its subprocess as JSON
    assert json.loads(json.dumps(res)) == res


@pytest.mark.slow
def test_speed_tiny(tiny_results):
    """The whole script, scaling study in subprocesses included (about a minute)."""
    from benchmarks import speed

    speed.main(["--quick"])
    text = (tiny_results / "speed_quick.md").read_text()
    _check_header(text)
    assert "median fit time" in text
    assert "Against the number of samples" in text and "| 1000 | cpu |" in text
    assert "error:" not in text
    assert (tiny_results / "speed_quick.png").stat().st_size > 1000


def _has_multiarm():
    from lagsindy.io import find_multiarm_pendulum

    try:
        find_multiarm_pendulum()
    except FileNotFoundError:
        return False
    return True


@pytest.mark.skipif(not _has_multiarm(), reason="MultiArm-Pendulum data not found")
def test_measured_tiny(tiny_results):
    from benchmarks import measured

    measured.main(["--quick"])
    text = (tiny_results / "measured_quick.md").read_text()
    _check_header(text)
    assert "## Single pendulum" in text and "authors (damped)" in text
    lines = text.splitlines()
    # The recovered pendulum ratio (strong and weak form) is within 0.5 % of the
    # authors' 2 m g a / J (measured -0.26 % strong, -0.21 % weak at 50 Hz).
    _, truth = measured.authors_model("single")
    row = next(line for line in lines if line.startswith("| `cos(phi)` |"))
    for cell in row.split("|")[3:5]:
        assert float(cell.split()[0]) == pytest.approx(truth["cos(phi)"], rel=0.005)
    # The refined weak fit keeps the two terms (a row of the summary table).
    row = next(line for line in lines if line.startswith("| single | refined |"))
    assert row.split("|")[3].strip() == "2"
    # Diagnosis finds the joint's viscous damping and it improves the validation:
    # R^2 0.99986 -> 0.99995, median 5 s rollout 0.038 -> 0.013 rad (measured).
    row = next(
        line for line in lines if line.startswith("| single | diagnosed (weak fit) |")
    )
    cells = [c.strip() for c in row.split("|")]
    assert "viscous(phi)" in cells[3]
    r2_before, r2_after = (float(v) for v in cells[6].split(" -> "))
    assert r2_after > r2_before
    roll_before, roll_after = (float(v) for v in cells[7].split(" (")[0].split(" -> "))
    assert roll_after < 0.5 * roll_before
    # The bootstrap table has an interval for the damping effect.
    row = next(
        line for line in lines if line.startswith("| `viscous(phi)` | dissipation")
    )
    low, high = (float(v) for v in row.split("|")[4].strip(" []").split(","))
    assert 0 < low < high
    assert (tiny_results / "measured_single_rollout_quick.png").stat().st_size > 1000
    assert (tiny_results / "measured_single_diagnosis_quick.png").stat().st_size > 1000


@pytest.mark.slow  # a benchmark script end to end (the methods it measures have their own tests)
def test_case2_tiny(tiny_results):
    from benchmarks import case2

    case2.main(["--quick"])
    text = (tiny_results / "case2_quick.md").read_text()
    _check_header(text)
    row = next(
        line for line in text.splitlines() if line.startswith("| single pendulum")
    )
    assert "| yes |" in row  # noise-free single pendulum: case II finds the structure


@pytest.mark.slow  # 12 s; `python -m benchmarks --quick` runs the script too
def test_robustness_tiny(tiny_results):
    from benchmarks import robustness

    robustness.main(["--quick"])
    text = (tiny_results / "robustness_quick.md").read_text()
    _check_header(text)
    assert "## Largest sigma with exactly the true terms in every seed" in text
    # Noise-free single pendulum: both formulations and the defaults, with the
    # paper's and the chain library, find the structure.
    row = next(
        line
        for line in text.splitlines()
        if line.startswith("| single_pendulum | active | shared |")
    )
    assert "| strong | weak | defaults | chain |" in text
    assert all(row.split("|")[k].strip() != "none" for k in (5, 6, 7, 8))
    assert (tiny_results / "robustness_quick.png").stat().st_size > 1000
    assert (tiny_results / "robustness_quick.csv").exists()


def test_differentiation_quick_never_overwrites_the_full_result(tiny_results):
    from benchmarks import differentiation

    differentiation.main(["--quick"])
    assert (tiny_results / "differentiation_quick.md").exists()
    assert not (tiny_results / "differentiation.md").exists()


def test_defaults_tiny(tiny_results):
    from benchmarks import defaults

    defaults.main([])
    text = (tiny_results / "defaults_quick.md").read_text()
    _check_header(text)
    rows = [line for line in text.splitlines() if line.startswith("| cart_pendulum")]
    assert (
        "| defaults (weak, window 81) |" in rows[0] and "| strong (strong) |" in rows[1]
    )
    # the verdict line states the target and whether it was met
    assert "target 1 %: largest coefficient error (norm)" in text
    assert "target 3 %: largest coefficient error (norm)" in text
    assert "## 3. The test-function window" in text


@pytest.mark.slow  # a benchmark script end to end (the methods it measures have their own tests)
def test_bootstrap_cost_tiny(tiny_results):
    from benchmarks import bootstrap_cost

    bootstrap_cost.main([])
    text = (tiny_results / "bootstrap_cost_quick.md").read_text()
    _check_header(text)
    rows = [line for line in text.splitlines() if line.startswith("| default")]
    rows += [line for line in text.splitlines() if line.startswith("| strong")]
    assert rows[0].startswith("| default (weak) |") and len(rows) == 2
    assert all(float(r.split("**")[1].rstrip("x")) > 0 for r in rows)


@pytest.mark.slow  # a benchmark script end to end (the methods it measures have their own tests)
def test_noise_correction_tiny(tiny_results):
    from benchmarks import noise_correction

    noise_correction.main([])
    text = (tiny_results / "noise_correction_quick.md").read_text()
    _check_header(text)
    assert "torch threads 1" in text
    row = next(line for line in text.splitlines() if line.startswith("| single"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "after" and len(cells) == 7
    assert all(float(c.rstrip(" s")) > 0 for c in cells[3:])


def test_quick_runner_skips_what_needs_optional_things(monkeypatch, capsys):
    """`python -m benchmarks --quick` goes on past missing packages and data (#18)."""
    import types

    from benchmarks import __main__ as runner

    def module(fn):
        m = types.ModuleType("fake")
        m.main = fn
        return m

    def missing_package(argv):
        raise ModuleNotFoundError("No module named 'pysindy'")

    def missing_data(argv):
        raise FileNotFoundError("no MultiArm-Pendulum data")

    def broken(argv):
        raise RuntimeError("a bug")

    ran = []
    fake = {
        "a": module(missing_package),
        "b": module(missing_data),
        "c": module(ran.append),
        "d": module(ran.append),
    }
    monkeypatch.setattr(runner, "discover", lambda: fake)
    monkeypatch.setattr(runner, "accepts_quick", lambda m: m is not fake["d"])
    assert runner.main(["--quick"]) == 0
    out = capsys.readouterr().out
    assert ran == [["--quick"]]
    assert "a: SKIPPED: ModuleNotFoundError: No module named 'pysindy'" in out
    assert "b: SKIPPED: FileNotFoundError" in out
    assert "d: SKIPPED: its command line has no --quick option" in out
    fake["e"] = module(broken)
    assert runner.main(["--quick"]) == 1
    assert "FAILED: ['e']" in capsys.readouterr().out


def test_every_benchmark_accepts_quick():
    from benchmarks import __main__ as runner

    found = runner.discover()
    assert len(found) >= 7
    assert [n for n, m in found.items() if not runner.accepts_quick(m)] == []


def test_speed_profile_steps_name_existing_functions():
    """The profiled steps of speed.py point at files and functions that exist (a
    module moved by the architecture sweep made the diagnose profile empty)."""
    import re
    from pathlib import Path

    from benchmarks import speed

    root = Path(__file__).resolve().parents[1]
    for label, suffix, names in speed.SEARCH_STEPS + speed.DIAGNOSE_STEPS:
        suffixes = (suffix,) if isinstance(suffix, str) else tuple(suffix)
        matches = [
            p for p in root.glob("lagsindy/**/*.py") if p.as_posix().endswith(suffixes)
        ]
        assert len(matches) == len(suffixes), (label, suffix)
        for path in matches:  # each file named holds one of the functions
            text = path.read_text()
            assert any(re.search(rf"def {n}\(", text) for n in names), (label, path)


def test_paired_comparison_counts_windows_and_brackets_the_median_difference():
    from benchmarks.measured import paired_comparison

    reference = np.array([1.0, 2.0, 3.0, 4.0, 5.0, np.nan])
    errors = np.array([0.5, 2.5, 2.0, 4.5, 4.0, 1.0])  # the nan window is dropped
    pc = paired_comparison(errors, reference)
    assert (pc["wins"], pc["n"]) == (3, 5)
    assert pc["ratio"] == pytest.approx(np.mean([0.5, 1.25, 2 / 3, 1.125, 0.8]))
    assert pc["diff"] == pytest.approx(2.5 - 3.0)
    assert pc["low"] <= pc["diff"] <= pc["high"]


def test_gpu_benchmark_runs_on_cpu_and_says_when_no_gpu(tiny_results):
    from benchmarks import gpu

    gpu.main(["--device", "cpu"])
    text = (tiny_results / "gpu_quick.md").read_text()
    _check_header(text)
    row = next(line for line in text.splitlines() if line.startswith("| 3000 x 39 "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "cpu"
    assert int(cells[6]) > 0  # aten operator calls of the profiled fit
    if not torch.cuda.is_available():
        gpu.main([])
        assert "No GPU on this machine" in (tiny_results / "gpu_quick.md").read_text()


@pytest.mark.gpu
def test_gpu_benchmark_profiles_cuda_kernels(tiny_results):
    from benchmarks import gpu

    gpu.main([])
    text = (tiny_results / "gpu_quick.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| 3000 x 39 "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "cuda" and int(cells[6]) > 0 and cells[7].endswith("MiB")


def test_speed_fit_only_and_floor_fits_replace_only_their_parts():
    """``--fit-only`` rewrites (a) and (b) but not (c); ``--floor-fits`` its own
    subsection of the floor section, not the simulation parts beside it."""
    from benchmarks import speed

    text = (
        "# Fit time\n\n## At the hardware floor (issue 16)\n\nfloor intro\n\n"
        "### Simulation\n\nsim text\n\n"
        "## Passive search and diagnosis against one fit (issue 16)\n\nintro\n\n"
        "### (a) Case I fit, cart-pendulum, 50k rows x 39 terms\n\nold a\n\n"
        "### (b) Memory\n\nold b\n\n### (c) Passive search and diagnosis\n\nc text\n"
    )
    new = speed._replace_between(
        text,
        "### (a) Case I fit, cart-pendulum\n\nnew a and b\n",
        speed.FIT_MARKER,
        speed.FIT_END_MARKER,
    )
    assert "new a and b" in new and "old a" not in new and "old b" not in new
    assert new.endswith("### (c) Passive search and diagnosis\n\nc text\n")
    assert new.startswith(text.split(speed.FIT_MARKER)[0].rstrip("\n"))
    marker, parent = speed.FLOOR_FITS_MARKER, "\n## At the hardware floor"
    first = speed._replace_subsection(
        text, marker.strip() + "\n\nrows 1\n", marker, parent
    )
    assert first.index("floor intro") < first.index("rows 1") < first.index("sim text")
    second = speed._replace_subsection(
        first, marker.strip() + "\n\nrows 2\n", marker, parent
    )
    assert "rows 1" not in second and "rows 2" in second
    assert second.replace("rows 2", "rows 1") == first


@pytest.mark.slow  # a benchmark script end to end (the checks it measures have tests)
def test_light_links_tiny(tiny_results):
    from benchmarks import light_links

    assert light_links.main([]) == 0
    text = (tiny_results / "light_links_quick.md").read_text()
    _check_header(text)
    # the separated library on a 2 % second link: the true terms only with the
    # checks (measured: 1/1 with, 0/1 without)
    assert "| 2 | separated | on | 1/1 |" in text
    assert "| 2 | separated | off | 0/1 |" in text
