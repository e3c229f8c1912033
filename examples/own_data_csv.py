"""
Your own recordings: a CSV of positions
=======================================

Fit your own recordings: a CSV of positions (and inputs), derivatives estimated. A
real data set has sampled positions q(t) (encoders, motion capture) and, when the
system is driven, the generalized forces. This example first writes such a file (a
simulated cart-pendulum with sensor noise on the positions only), then does what a
user does with their own file: read it, estimate velocities and accelerations per
trajectory, build ``X = [q, q_dot, q_ddot]`` with named columns, and fit.

The same from the command line::

    lagsindy fit positions.csv --coordinates x,theta --angles theta \\
        --library poly3 --out model.json

Run: ``python examples/own_data_csv.py`` (about 15 s).
"""

import os
import tempfile
from pathlib import Path

import pandas as pd

from lagsindy import LagrangianSINDy
from lagsindy.differentiation import derivatives
from lagsindy.library import CandidateLibrary
from lagsindy.systems import cart_pendulum, make_dataset

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"
# Everything is written into a temporary folder that is removed at the end.
workspace = tempfile.TemporaryDirectory(prefix="lagsindy_")
folder = Path(workspace.name)
csv = folder / "positions.csv"

# --- 1. a stand-in for your recordings: trajectory, t, x, theta, tau_x, tau_theta
data = make_dataset(
    cart_pendulum(),
    n_trajectories=15 if QUICK else 40,
    excitation="sincos",
    noise=1e-5,
    protocol="sensor",
    random_state=2,
)
frame = data.to_frame()
frame[["trajectory", "t", "x", "theta", "tau_x", "tau_theta"]].to_csv(csv, index=False)
print(f"wrote {csv} ({len(frame)} rows)")

# --- 2. what you do with your own file
df = pd.read_csv(csv)
coordinates = ["x", "theta"]
q = df[coordinates].to_numpy()
# Derivatives never cross trajectory boundaries (groups); the Savitzky-Golay filter
# smooths q as it differentiates. Sort by trajectory and time first if needed.
X = derivatives(
    q, df["t"].to_numpy(), groups=df["trajectory"].to_numpy(), method="savgol"
)
X = pd.DataFrame(
    X, columns=["x", "theta", "x_dot", "theta_dot", "x_ddot", "theta_ddot"]
)
tau = df[["tau_x", "tau_theta"]].to_numpy()

# All monomials of degree 1..3 over {x, x_dot, theta_dot, sin(theta), cos(theta)}.
library = CandidateLibrary.polynomial(coordinates, angles=["theta"], degree=3)
est = LagrangianSINDy(library).fit(X, tau)  # DataFrame columns give the names
print("learned:", est.equation())
print("true:   ", cart_pendulum().equation())
print("R^2 of the forces:", round(est.score(X, tau), 5))
print(est.predict(X.head(3)))  # DataFrame in, named columns out
est.save(folder / "model.json")
print("saved", folder / "model.json", "(a temporary folder, removed now)")
workspace.cleanup()
