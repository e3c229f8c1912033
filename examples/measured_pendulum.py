"""
Real recordings: the MultiArm single pendulum
=============================================

A Lagrangian from real recordings. Data: encoder recordings of a physical pendulum
swinging freely (1 kHz), from Kaheman et al., "The Experimental Multi-Arm Pendulum on a
Cart", arXiv:2205.06231 (MIT license), shipped with lagsindy
(``lagsindy/data/multiarm_pendulum/``). There is no input, so this is case III: the fit
fixes the Lagrangian's scale (here by the mean trace of the mass matrix, reported with
``phi_dot**2``'s coefficient set to 1) and the answer is the ratio of the potential to
the kinetic term, which for a rigid pendulum is 2 m g a / (I + m a^2) (a simple
pendulum of length l: 2 g / l). The free swing decays, so the conservative model
leaves a residual; ``diagnose`` finds what explains it.

Angles: the recording's zero is the upright position, so pi means hanging straight
down. We fit in ``phi = theta - pi``, so the potential is ``+c cos(phi)`` with c > 0 and
the library's low-order polynomial terms in ``phi`` are small near the rest position.
In the original angle ``cos(phi) = -cos(theta)``: the ratio
``cos(theta)/theta_dot**2`` is minus the one printed for ``phi``.

Differentiation: the encoder steps make accelerations from the raw 1 kHz record very
noisy. We thin the record to 100 Hz first and let the P-spline (smoothing chosen by
generalized cross-validation) estimate velocities and accelerations per segment.

Run: ``python examples/measured_pendulum.py`` (about 15 s). The full study of both
recordings: ``python -m benchmarks.measured``.
"""

import os

import numpy as np
import pandas as pd

from lagsindy import CandidateLibrary, LagrangianSINDy, diagnose
from lagsindy.differentiation import derivatives
from lagsindy.io import load_multiarm_parameters, load_multiarm_pendulum

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"


def to_X(frame, step=10):
    """Every `step`-th sample (1 kHz -> 100 Hz), offset angle, derivatives."""
    frame = frame.iloc[::step]
    phi = frame["theta"].to_numpy() - np.pi  # 0 = hanging down
    X = derivatives(
        phi[:, None], frame["t"].to_numpy(), groups=frame["trajectory"].to_numpy()
    )
    return pd.DataFrame(X, columns=["phi", "phi_dot", "phi_ddot"]), frame


# The recordings ship with lagsindy ($LAGSINDY_MULTIARM_DIR overrides the folder).
train = load_multiarm_pendulum(which="single", split="id")
valid = load_multiarm_pendulum(which="single", split="vad")
print(
    f"identification: {train.trajectory.nunique()} segments, "
    f"{len(train)} samples at 1 kHz"
)
X_train, thinned = to_X(train, step=20 if QUICK else 10)
X_valid, _ = to_X(valid, step=20 if QUICK else 10)

# Our velocity estimate against the authors' filtered velocity (a sanity check).
diff = X_train["phi_dot"].to_numpy() - thinned["theta_dot_filtered"].to_numpy()
print(
    f"velocity estimate vs authors' filtered velocity: RMS difference "
    f"{np.sqrt(np.mean(diff**2)):.3f} rad/s (signal RMS "
    f"{np.sqrt(np.mean(X_train['phi_dot'] ** 2)):.2f} rad/s)"
)

# A small pendulum library: degree 2 over {phi, phi_dot, sin phi, cos phi}.
library = CandidateLibrary.polynomial(
    ["phi"], angles=["phi"], degree=2, raw_angles=True
)
groups = thinned["trajectory"].to_numpy()
est = LagrangianSINDy(library, fixed_term="mass").fit(X_train, groups=groups)
coef = est.coef_table().set_index("term")["coefficient"]
ratio = coef["cos(phi)"] / coef["phi_dot**2"]
print("learned:", est.equation())
print(
    f"ratio cos(phi)/phi_dot**2 = {ratio:.2f}  "
    f"(in the recording's angle: cos(theta)/theta_dot**2 = {-ratio:.2f})"
)
print(f"equivalent simple pendulum length 2 g / ratio = {2 * 9.81 / ratio:.4f} m")

# The authors' own estimate for comparison.
authors = load_multiarm_parameters("single")
a1, m1, i1, g = (authors[k] for k in ("a1", "m1", "I1", "g"))
print(
    "authors' parameters give 2 m g a / (I + m a^2) = "
    f"{2 * m1 * g * a1 / (i1 + m1 * a1**2):.2f}"
)
print(
    f"R^2 of accelerations: identification {est.score(X_train):.5f}, "
    f"validation {est.score(X_valid):.5f}"
)

# Close the loop: what does the conservative model leave unexplained?
report = diagnose(est, X_train, groups=groups, max_effects=1 if QUICK else 3)
print(report)
print(f"validation R^2 after the diagnosis: {report.final.score(X_valid):.5f}")
