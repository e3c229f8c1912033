"""
Quick start: the cart-pendulum
==============================

Discover the cart-pendulum's Lagrangian from forced, noisy trajectories: 100
simulated trajectories of 5 s at 100 Hz (the paper's setting), a sinusoidal force on
the cart, independent noise on ``q``, ``q_dot`` and ``q_ddot``, and the paper's
library of 39 candidate terms.

Run: ``python examples/quickstart.py`` (about 10 s;
``LAGSINDY_EXAMPLE_QUICK=1`` uses less data).
"""

import os

from lagsindy import LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"

system = cart_pendulum()
print("true:   ", system.equation())

# 100 trajectories x 5 s at 100 Hz (the paper's setting); tau = a sin(wt) + b cos(wt)
# on the cart; independent Gaussian noise (sigma = 0.01) on q, q_dot and q_ddot.
data = make_dataset(
    system,
    n_trajectories=20 if QUICK else 100,
    excitation="sincos",
    noise=0.01,
    protocol="paper",
    random_state=0,
)

est = LagrangianSINDy(system.paper_library(), verbose=1)
est.fit(data.X, data.tau)
print("learned:", est.equation())
print("R^2 of the forces:", round(est.score(data.X, data.tau), 5))
print(est.coef_table().query("kept").to_string(index=False))
