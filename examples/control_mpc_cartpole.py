"""
Model predictive control of a cart-pendulum on a model identified from noisy data
=================================================================================

The model is identified as in control_lqr_cartpole.py; lagsindy.export.to_casadi turns
it into CasADi functions, on which a short-horizon MPC (multiple shooting, RK4,
IPOPT) balances the *true* simulated system from 0.3 rad off upright with a bounded
cart force. The LQR of the identified model's linearization gives the terminal cost.

Needs CasADi (pip install casadi); without it the example says so and stops.

Run: python examples/control_mpc_cartpole.py   (about 15 s)
(LAGSINDY_EXAMPLE_QUICK=1 uses less data.)
"""

import importlib.util
import os
import sys

import numpy as np

if importlib.util.find_spec("casadi") is None:
    print("CasADi is not installed (pip install casadi): MPC example skipped")
    sys.exit(0)

import casadi as ca
from scipy.linalg import solve_continuous_are

from lagsindy import LagrangianSINDy
from lagsindy.export import linearize, to_casadi
from lagsindy.systems import cart_pendulum, make_dataset

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"

system = cart_pendulum()
data = make_dataset(
    system,
    n_trajectories=20 if QUICK else 50,
    excitation="sincos",
    noise=0.01,
    protocol="sensor",
    random_state=0,
)
est = LagrangianSINDy(system.paper_library()).fit(data.X, data.tau, groups=data.groups)
print("learned:", est.equation())

B_cart = [[1.0], [0.0]]  # one input: the force on the cart
model = to_casadi(est, input_matrix=B_cart)
x_eq = np.array([0.0, np.pi, 0.0, 0.0])
Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), np.array([[0.1]])
lin = linearize(est, x_eq, [0.0], input_matrix=B_cart)
P = solve_continuous_are(lin.A, lin.B, Q, R)  # terminal cost: the LQR's value

N, dt, u_max = 20, 0.05, 20.0  # 1 s horizon, force bounded to 20 N


def rk4(x, u):
    f = model.state_derivative
    k1 = f(x, u)
    k2 = f(x + dt / 2 * k1, u)
    k3 = f(x + dt / 2 * k2, u)
    k4 = f(x + dt * k3, u)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


opti = ca.Opti()
X, U, x_now = opti.variable(4, N + 1), opti.variable(1, N), opti.parameter(4)
cost = 0
for k in range(N):
    e = X[:, k] - x_eq
    cost += dt * (ca.bilin(Q, e, e) + R[0, 0] * U[0, k] ** 2)
    opti.subject_to(X[:, k + 1] == rk4(X[:, k], U[:, k]))
e = X[:, N] - x_eq
opti.minimize(cost + ca.bilin(P, e, e))
opti.subject_to(X[:, 0] == x_now)
opti.subject_to(opti.bounded(-u_max, U, u_max))
opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes"})

x = np.array([0.0, np.pi + 0.3, 0.0, 0.0])  # the true system's state
# Start the first plan at the current state (IPOPT is a local solver: an initial
# guess of zeros, the pendulum hanging, leads it to swing the pendulum down).
opti.set_initial(X, np.tile(x[:, None], N + 1))
steps = 100  # 5 s
forces = []
for step in range(steps):
    opti.set_value(x_now, x)
    solution = opti.solve()
    u = float(solution.value(U)[0])
    forces.append(u)
    # warm start: the last plan shifted by one interval
    plan_x, plan_u = solution.value(X), np.atleast_1d(solution.value(U))
    opti.set_initial(X, np.hstack([plan_x[:, 1:], plan_x[:, -1:]]))
    opti.set_initial(U, np.append(plan_u[1:], plan_u[-1]))
    # apply u for one interval to the TRUE system (zero-order hold)
    x = system.simulate(x, [0.0, dt], np.full((2, 1), u))[-1]
final_error = abs(x[1] - np.pi)
print(f"MPC: {steps} steps of {dt} s, largest force {max(map(abs, forces)):.2f} N")
print(f"angle error: 0.30 rad at t=0, {final_error:.2e} rad at t={steps * dt:.1f} s")
print("stabilized:", bool(final_error < 0.01))
