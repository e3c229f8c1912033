"""Fits, bootstrap and diagnosis from partitioned data equal the in-memory ones.

Chunks (no Dask) everywhere; a 2-worker ``dask.distributed.LocalCluster`` and
Parquet when Dask is installed (``pip install 'lagsindy[dask]'``).
"""

import warnings

import numpy as np
import pytest
import torch

from lagsindy import LagrangianSINDy, bootstrap, diagnose, pipeline
from lagsindy.formulation.forms import StrongForm
from lagsindy.partitioned import (
    PartitionedData,
    combine,
    is_partitioned,
    partitioned_setup,
)
from lagsindy.partitioned.statistics import strong_pass
from lagsindy.systems import make_dataset, single_pendulum

SYSTEM = single_pendulum()
# Coefficients: in-memory against partitioned, relative to the largest; measured
# 0 to 3e-14 on these data (rounding of the summation order; the in-memory fit of
# the same rows with the trajectories in reverse order moves them by 1e-12 on a
# double pendulum).
RTOL = 1e-12


def _data(passive=False, noise=1e-3, n=12, seed=0):
    return make_dataset(
        SYSTEM,
        n_trajectories=n,
        duration=2.0,
        excitation=None if passive else "paper",
        noise=noise,
        random_state=seed,
    )


def _chunks(frame, per=5):
    """Whole trajectories per chunk, unequal chunks (5, 5, 2)."""
    key = np.asarray(frame["trajectory"]) // per
    return [part for _, part in frame.groupby(key, sort=True)]


def _estimator(form, passive, fixed_term="theta_dot**2"):
    kw = {"formulation": form}
    if passive:
        kw["fixed_term"] = fixed_term
    return LagrangianSINDy(SYSTEM.paper_library(), **kw)


def _in_memory(form, passive, data, **kw):
    est = _estimator(form, passive, **kw)
    return est.fit(data.X, data.tau, groups=data.groups)


def _same(a, b, rtol=RTOL):
    scale = np.abs(a.fitted_.all_coef()).max()
    got = np.abs(a.fitted_.all_coef() - b.fitted_.all_coef()).max() / scale
    assert got <= rtol, got
    assert np.array_equal(a.support_, b.support_)
    assert a.formulation_ == b.formulation_ and a.case_ == b.case_
    for name in ("window_", "fixed_term_", "normalization_"):
        assert getattr(a, name, None) == getattr(b, name, None), name
    if getattr(a, "dt_", None) is not None:
        assert a.dt_ == b.dt_  # the weighted median is exact
    if getattr(a, "noise_cov_", None) is not None:
        np.testing.assert_allclose(b.noise_cov_, a.noise_cov_, rtol=1e-12)
    else:
        assert getattr(b, "noise_cov_", None) is None
    # a relative residual (a difference of sums): 5e-14 apart, measured
    np.testing.assert_allclose(b.residual_, a.residual_, rtol=0, atol=1e-12)


@pytest.mark.parametrize("form", ["strong", "weak", "auto"])
@pytest.mark.parametrize("passive", [False, True])
def test_chunks_equal_in_memory(form, passive):
    data = _data(passive)
    want = _in_memory(form, passive, data)
    got = _estimator(form, passive).fit(_chunks(data.to_frame()))
    _same(want, got)
    assert list(got.feature_names_in_) == ["theta", "theta_dot", "theta_ddot"]
    head = data.to_frame()[list(got.feature_names_in_)].iloc[:50]
    np.testing.assert_allclose(got.predict(head), want.predict(data.X[:50]))


def test_auto_falls_back_to_the_strong_form_like_in_memory():
    """Trajectories shorter than the weak form's 81-sample window: the same
    warning and the same strong-form model as in memory."""
    data = make_dataset(
        SYSTEM, n_trajectories=12, duration=0.5, noise=1e-3, random_state=0
    )
    with pytest.warns(UserWarning, match="fell back to the strong form"):
        want = _in_memory("auto", False, data)
    with pytest.warns(UserWarning, match="fell back to the strong form") as seen:
        got = _estimator("auto", False).fit(_chunks(data.to_frame()))
    assert got.formulation_ == "strong"
    _same(want, got)
    assert seen[0].filename == __file__  # points at the caller's fit


def test_summed_statistics_equal_in_memory():
    data = _data()
    est = _estimator("strong", False)
    setup, _ = _setup(est, data)
    source = PartitionedData(_chunks(data.to_frame()))
    total = source.map_reduce(strong_pass(setup, torch.float64), combine)
    Xt = torch.as_tensor(data.X)
    tau = torch.as_tensor(data.tau)
    want = pipeline.fit_statistics(StrongForm(), setup, Xt, tau, data.groups)
    # the probe columns are in the raw sums: compare the full Gram
    full = want[0]().probe_gram
    scale = full.abs().max()
    assert float((total["gram"] - full).abs().max() / scale) < 1e-14  # 2e-16
    assert total["n"] == len(data.X)


def _setup(est, data):
    source = PartitionedData(_chunks(data.to_frame()))
    return partitioned_setup(est.get_params(deep=False), source)


def test_case_iii_search_and_mass_gather_the_same_rows():
    """fixed_term=None ranks candidates, "mass" normalizes, on rows of the data:
    the partitioned fit gathers exactly the rows the in-memory fit evaluates
    (6000 rows here, above the 4000 and 2000 row subsamples)."""
    data = _data(passive=True, n=30)
    frame = data.to_frame()
    for fixed in (None, "mass"):
        want = _in_memory("strong", True, data, fixed_term=fixed)
        got = _estimator("strong", True, fixed_term=fixed).fit(_chunks(frame, 7))
        _same(want, got)


def test_gathered_rows_are_the_in_memory_rows():
    """Case III's and case II's row subsamples, gathered from the partitions, are
    the rows of the concatenated data at the same indices."""
    from lagsindy.partitioned.fit import _gathered

    data = _data(passive=True, n=30)
    est = _estimator("strong", True, fixed_term=None)
    source = PartitionedData(_chunks(data.to_frame(), 7))
    setup, _ = partitioned_setup(est.get_params(deep=False), source)
    total = source.map_reduce(strong_pass(setup, torch.float64), combine)
    rows = _gathered(source, setup, total, torch.float64, "cpu")
    assert rows.shape == data.X.shape
    pick = setup.solver.subsample_rows(len(data.X), 2000)  # case III's scoring rows
    np.testing.assert_array_equal(rows[torch.as_tensor(pick)].numpy(), data.X[pick])
    missing = np.setdiff1d(np.arange(len(data.X)), rows.rows)
    assert missing.size  # case III gathers 4000 of the 6000 rows, not all
    with pytest.raises(IndexError):
        rows[torch.as_tensor(missing[:1])]


@pytest.mark.parametrize("bins", [8, 4096])
def test_weak_dt_is_the_exact_weighted_median(monkeypatch, bins):
    """Partitions with different local medians: the three-round median equals
    the in-memory estimate bit for bit, however coarse the histogram (8 bins:
    hundreds of ratios in the median's bin; a wrong weight under that bin moved
    dt by 2e-10 on a double pendulum)."""
    from lagsindy.partitioned import statistics

    monkeypatch.setattr(statistics, "MEDIAN_BINS", bins)
    data = _data(noise=2e-3, n=12, seed=3)
    want = _in_memory("weak", False, data)
    got = _estimator("weak", False).fit(_chunks(data.to_frame(), 2))
    assert got.dt_ == want.dt_
    _same(want, got)


def test_tuples_and_a_one_shot_iterator():
    data = _data()
    want = _in_memory("strong", False, data)
    rows = np.array_split(np.arange(len(data.X)), [800, 1600])  # 4, 4, 4 trajectories
    parts = [(data.X[r], data.tau[r], data.groups[r]) for r in rows]
    got = _estimator("strong", False).fit(iter(parts))  # one pass is enough
    _same(want, got)
    with pytest.raises(ValueError, match="one-shot iterator"):
        _estimator("weak", False).fit(iter(parts))
    got = _estimator("weak", False).fit(lambda: iter(parts))  # a new one per pass
    _same(_in_memory("weak", False, data), got)


def test_split_trajectory_is_refused():
    data = _data()
    frame = data.to_frame()
    parts = [frame.iloc[:1100], frame.iloc[1100:]]  # trajectory 5 in both
    with pytest.raises(ValueError, match=r"trajectories \[5\] are split across"):
        _estimator("strong", False).fit(parts)


def test_derivatives_per_partition():
    from lagsindy.differentiation import derivatives

    data = _data(noise=0.0)
    frame = data.to_frame()[["trajectory", "t", "theta", "tau_theta"]]
    options = {"method": "savgol", "window": 9}
    X = derivatives(data.X[:, :1], data.t, groups=data.groups, **options)
    want = _estimator("strong", False).fit(X, data.tau, groups=data.groups)
    source = PartitionedData(_chunks(frame), derivatives=options, time="t")
    got = _estimator("strong", False).fit(source)
    _same(want, got)


def test_bootstrap_from_chunks_equals_in_memory():
    data = _data()
    est = _estimator("weak", False)
    want = bootstrap(
        est, data.X, data.tau, groups=data.groups, n_resamples=8, random_state=0
    )
    got = bootstrap(est, _chunks(data.to_frame()), n_resamples=8, random_state=0)
    assert got.fast_path
    np.testing.assert_allclose(got.coefficient, want.coefficient, rtol=1e-12)
    np.testing.assert_allclose(got.samples, want.samples, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(got.inclusion, want.inclusion)
    with pytest.raises(ValueError, match="at least 10"):
        few = data.to_frame()
        bootstrap(est, _chunks(few[few.trajectory < 6]), n_resamples=4)


def test_not_partitioned():
    data = _data()
    assert not is_partitioned(data.X) and not is_partitioned(data.to_frame())
    assert not is_partitioned([[1.0, 2.0, 3.0]])
    assert not is_partitioned([(1.0, 2.0, 3.0), (0.5, 1.0, 2.0)])  # rows
    assert is_partitioned(_chunks(data.to_frame()))


# --------------------------------------------------------------------- Dask
@pytest.fixture(scope="module")
def client():
    pytest.importorskip("dask.dataframe")
    distributed = pytest.importorskip("dask.distributed")
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    )
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()


def _dask_frame(frame, npartitions=3):
    import dask.dataframe as dd

    # partition boundaries on trajectories: divisions of a sorted trajectory index
    indexed = frame.set_index("trajectory", drop=False)
    return dd.from_pandas(indexed, npartitions=npartitions, sort=True).reset_index(
        drop=True
    )


@pytest.mark.parametrize("form", ["strong", "weak"])
@pytest.mark.parametrize("passive", [False, True])
def test_local_cluster_equals_in_memory(client, form, passive):
    data = _data(passive)
    ddf = _dask_frame(data.to_frame())
    assert ddf.npartitions == 3
    got = _estimator(form, passive).fit(ddf)
    _same(_in_memory(form, passive, data), got)
    assert client.run(lambda: 1)  # the cluster's two workers ran it
    assert len(client.scheduler_info()["workers"]) == 2


def test_local_cluster_bootstrap_and_diagnose(client):
    data = _data()
    ddf = _dask_frame(data.to_frame())
    est = _estimator("strong", False)
    want = bootstrap(
        est, data.X, data.tau, groups=data.groups, n_resamples=8, random_state=1
    )
    got = bootstrap(est, ddf, n_resamples=8, random_state=1)
    np.testing.assert_allclose(got.samples, want.samples, rtol=1e-12, atol=1e-14)
    fitted = est.fit(data.X, data.tau)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = diagnose(fitted, data.X, data.tau, groups=data.groups, max_effects=1)
        b = diagnose(fitted, ddf, groups="trajectory", max_effects=1)
    assert a.effects == b.effects
    np.testing.assert_allclose(
        b.final.fitted_.all_coef(), a.final.fitted_.all_coef(), rtol=1e-12
    )


def test_parquet_and_dask_array(client, tmp_path):
    da = pytest.importorskip("dask.array")
    pytest.importorskip("pyarrow")
    data = _data()
    frame = data.to_frame()
    path = tmp_path / "log.parquet"
    _dask_frame(frame).to_parquet(path)
    want = _in_memory("weak", False, data)
    _same(want, _estimator("weak", False).fit(str(path)))
    # arrays: [X, tau, trajectory] columns, row blocks of whole trajectories
    table = np.column_stack([data.X, data.tau, data.groups])
    arr = da.from_array(table, chunks=(800, 3))
    source = PartitionedData(arr, trajectory=4, tau=[3])
    _same(want, _estimator("weak", False).fit(source))
