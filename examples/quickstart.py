"""Quick start: discover the cart-pendulum's Lagrangian from forced, noisy trajectories."""

from lagsindy import LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset

system = cart_pendulum()
print("true:", system.equation())

# 100 trajectories x 5 s at 100 Hz; tau = a sin(wt) + b cos(wt) on the cart;
# independent Gaussian noise (sigma = 0.01) on q, q_dot and q_ddot.
data = make_dataset(system, excitation="sincos", noise=0.01, protocol="paper", random_state=0)

est = LagrangianSINDy(system.paper_library(), verbose=1)
est.fit(data.X, data.tau)
print("learned:", est.equation())
print("R^2 of the forces:", round(est.score(data.X, data.tau), 5))
