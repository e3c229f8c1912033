"""
Choosing lam and alpha by cross-validation
==========================================

Choose ``lam`` (the L1 weight) and ``alpha`` (the step size) by cross-validation over
trajectories. Rows of ``X`` are self-contained samples, so any scikit-learn splitter
works; ``GroupKFold`` with the trajectory index as ``groups`` keeps each trajectory
within one fold, so the score measures prediction on trajectories the fit has not
seen. With forces the score is R^2 of the predicted forces; for passive data
(``fit(X)`` without ``tau``) ``score`` is R^2 of the accelerations, so
``GridSearchCV(...).fit(X, groups=...)`` ranks those models too.

What to expect: too large a ``lam`` removes true terms and the cross-validated score
drops; ``alpha`` is the step of the proximal gradient and changes the speed, not the
answer, once FISTA converges (``None``: 1/L from the Lipschitz constant).

Run: ``python examples/gridsearch.py`` (about 40 s).
"""

import os
import warnings

import pandas as pd
from sklearn.model_selection import GridSearchCV, GroupKFold

from lagsindy import LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset

QUICK = os.environ.get("LAGSINDY_EXAMPLE_QUICK") == "1"
# Candidates with too large a lam lose kinetic terms; their (expected) warnings about
# a singular mass matrix would only clutter the output here.
warnings.filterwarnings("ignore", message="the learned mass matrix")

system = cart_pendulum()
data = make_dataset(
    system,
    n_trajectories=12 if QUICK else 30,
    excitation="sincos",
    noise=0.02,
    protocol="paper",
    random_state=1,
)

grid = {
    "lam": [1e-3, 1e-1] if QUICK else [1e-4, 1e-3, 1e-2, 1e-1, 0.3],
    "alpha": [None] if QUICK else [None, 0.5],
}
search = GridSearchCV(
    LagrangianSINDy(system.paper_library()),
    grid,
    cv=GroupKFold(n_splits=3),
    n_jobs=1,
)
search.fit(data.X, data.tau, groups=data.groups)

results = pd.DataFrame(search.cv_results_)[
    ["param_lam", "param_alpha", "mean_test_score", "std_test_score", "rank_test_score"]
]
print(results.sort_values("rank_test_score").to_string(index=False))
print("best:", search.best_params_)
best = search.best_estimator_
print("learned:", best.equation())
print("true:   ", system.equation())
