"""
Balance a cart-pendulum with an LQR designed on a model identified from noisy data
==================================================================================

1. Simulate the cart-pendulum driven on the cart and record positions with sensor
   noise (sigma = 0.01; velocities and accelerations are estimated from them).
2. Identify its Lagrangian with LagrangianSINDy.
3. Linearize the *identified* model at the upright equilibrium (theta = pi) with
   lagsindy.export.linearize: only the cart is driven, input_matrix = [[1], [0]].
4. Design an LQR with scipy's Riccati solver and stabilize the *true* simulated
   system from 0.3 rad off upright.

Run: python examples/control_lqr_cartpole.py   (about 10 s)
(LAGSINDY_EXAMPLE_QUICK=1 uses less data.)
"""

import os

import numpy as np
from scipy.linalg import solve_continuous_are

from lagsindy import LagrangianSINDy
from lagsindy.export import linearize
from lagsindy.systems import cart_pendulum, make_dataset

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"

system = cart_pendulum()  # the "real" machine: we only use it to make data and to run
data = make_dataset(
    system,
    n_trajectories=20 if QUICK else 50,
    excitation="sincos",
    noise=0.01,
    protocol="sensor",  # noise on the positions; derivatives estimated from them
    random_state=0,
)
est = LagrangianSINDy(system.paper_library()).fit(data.X, data.tau, groups=data.groups)
print("true:   ", system.equation())
print("learned:", est.equation())

# The learned model's input is the generalized force on each coordinate; the
# machine has one motor, on the cart: u enters as B u with B = [[1], [0]].
x_eq = np.array([0.0, np.pi, 0.0, 0.0])  # cart at 0, pendulum upright, at rest
lin = linearize(est, x_eq, u_eq=[0.0], input_matrix=[[1.0], [0.0]])
print("A =\n", np.round(lin.A, 3))
print("B =", np.round(lin.B.ravel(), 3))
print(f"equilibrium residual: {lin.residual:.1e}")

Q = np.diag([1.0, 10.0, 1.0, 1.0])
R = np.array([[0.1]])
P = solve_continuous_are(lin.A, lin.B, Q, R)
K = np.linalg.solve(R, lin.B.T @ P)
print("LQR gain K =", np.round(K.ravel(), 3))
print("closed-loop poles of the learned model:", np.round(np.linalg.eigvals(lin.A - lin.B @ K), 2))


def controller(t, state):
    """u = -K (x - x_eq), the angle error wrapped to (-pi, pi]."""
    error = np.asarray(state, dtype=float) - x_eq
    error[1] = (error[1] + np.pi) % (2 * np.pi) - np.pi
    return -K @ error


t = np.linspace(0.0, 5.0, 501)
x0 = np.array([0.0, np.pi + 0.3, 0.0, 0.0])  # 0.3 rad off upright
states = system.simulate(x0, t, controller)  # the TRUE system, closed loop
final_error = abs(states[-1, 1] - np.pi)
print(f"angle error: {abs(x0[1] - np.pi):.2f} rad at t=0, {final_error:.2e} rad at t=5 s")
print(f"largest cart force: {np.abs([controller(0, s) for s in states]).max():.2f} N")
print("stabilized:", bool(final_error < 0.01))
