"""
Passive double pendulum (case III)
==================================

No input, one known term and one prior term. Without an input the Euler-Lagrange
equations are homogeneous, so the Lagrangian is only determined up to scale. Case III
fixes the coefficient of a term known to be present (here ``theta1_dot**2``, the first
link's kinetic energy) to 1. The paper also uses what is known from a constituent
system, the single pendulum: ``cos(theta1)`` is present, so it is left unpenalised
(``unpenalized``) and never thresholded. The systems carry both facts as
``system.fixed_term`` and ``system.prior_terms``.

Run: ``python examples/passive_case3.py`` (about 20 s).
"""

import os

import numpy as np

from lagsindy import LagrangianSINDy, rollout_error
from lagsindy.systems import double_pendulum, make_dataset

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"

system = double_pendulum()
print("fixed term:", system.fixed_term, " prior terms:", system.prior_terms)

data = make_dataset(
    system,
    n_trajectories=10 if QUICK else 40,
    excitation=None,
    noise=0.001,
    protocol="paper",
    random_state=0,
)
est = LagrangianSINDy(
    system.paper_library(),  # 89 candidates (the paper's separated construction)
    fixed_term=system.fixed_term,  # "theta1_dot**2"
    unpenalized=system.prior_terms,  # ["cos(theta1)"]
    verbose=1,
)
est.fit(data.X)  # no tau: passive data

# The true Lagrangian in the library's terms, scaled so that the fixed term is 1.
truth = system.true_coefficients(est.library_)
truth = truth / truth[est.library_.index(est.fixed_term_)]
print(f"\n{'term':<48}{'true':>9}{'learned':>10}")
for name, t, c in zip(est.term_names_, truth, est.coef_):
    if t != 0 or c != 0:
        print(f"{name:<48}{t:9.4f}{c:10.4f}")
print("structure correct:", bool(np.array_equal(truth != 0, est.coef_ != 0)))
print("learned:", est.equation())
print("R^2 of accelerations:", round(est.score(data.X), 5))

# The scale does not matter for the motion: integrate both from a new state.
t = np.linspace(0, 2, 201)
check = rollout_error(system, est.model_, [1.0, -0.5, 0.0, 0.0], t)
print(
    "2 s rollout from (1, -0.5): max |q_true - q_learned| = "
    f"{check['max_abs_q']:.2e} rad"
)
