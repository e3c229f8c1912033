"""Fixtures of the command-line tests: a small data set and model, made once."""

import pytest

from lagsindy.cli import main


@pytest.fixture(scope="session")
def workdir(tmp_path_factory):
    """A small forced cart-pendulum data set, a positions-only copy, a model."""
    d = tmp_path_factory.mktemp("cli")
    assert (
        main(
            [
                "simulate",
                "--system",
                "cart_pendulum",
                "--trajectories",
                "6",
                "--duration",
                "4",
                "--noise",
                "0.001",
                "--seed",
                "1",
                "--out",
                str(d / "data.csv"),
                "--quiet",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "simulate",
                "--system",
                "cart_pendulum",
                "--trajectories",
                "6",
                "--duration",
                "4",
                "--positions-only",
                "--seed",
                "2",
                "--out",
                str(d / "q.csv"),
                "--quiet",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "fit",
                str(d / "data.csv"),
                "--coordinates",
                "x,theta",
                "--angles",
                "theta",
                "--library",
                "poly3",
                "--out",
                str(d / "model.json"),
                "--quiet",
            ]
        )
        == 0
    )
    return d


@pytest.fixture
def no_derivatives(monkeypatch):
    """Derivative estimation fails the test: checks must come before it."""
    import lagsindy.differentiation

    def boom(*args, **kwargs):
        raise AssertionError("derivatives were estimated before the argument check")

    monkeypatch.setattr(lagsindy.differentiation, "derivatives", boom)
