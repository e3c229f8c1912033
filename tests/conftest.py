import numpy as np
import pytest
import torch

from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


@pytest.fixture(autouse=True)
def _seed():
    """Tests that draw random numbers themselves start from a known state."""
    np.random.seed(0)
    torch.manual_seed(0)
    yield


@pytest.fixture(scope="session")
def cart_active():
    """Paper-size noise-free cart-pendulum data, tau = a sin(wt) + b cos(wt) on the cart."""
    return make_dataset(cart_pendulum(), excitation="sincos", random_state=0)


@pytest.fixture(scope="session")
def single_active():
    return make_dataset(
        single_pendulum(), n_trajectories=40, excitation="paper", random_state=1
    )


@pytest.fixture(scope="session")
def single_passive():
    return make_dataset(
        single_pendulum(), n_trajectories=40, excitation=None, random_state=2
    )
