r"""Close the loop: find what a fitted Lagrangian leaves unexplained, and add it.

:func:`diagnose` takes a fitted :class:`~lagsindy.LagrangianSINDy` and data and looks
for missing effects in a catalogue: viscous damping, relative (joint) damping,
quadratic drag and Coulomb friction on every coordinate, a constant offset force, an
input gain error (when several coordinates are driven) and missing conservative terms
(a spring ``q**2`` on every coordinate, ``cos``/``sin`` of angles, or terms you pass)
and, for forced data, a delay between the recorded input and the positions.

The loop
--------
1. **Revise the Lagrangian jointly with the effects.** A conservative fit of damped
   data absorbs the damping into wrong Lagrangian terms; adding effects on top of it
   cannot undo that. So the sparse search is first run again over the Lagrangian
   library *and* the dissipative catalogue together; the dissipative terms it keeps
   are pruned one by one while removing them does not worsen the held-out criterion,
   and the Lagrangian's sparse search is run once more with the survivors as known
   (unpenalized) terms.
2. **Add effects one at a time.** The remaining candidates are ranked by how much of
   the held-out criterion they explain when added to the current support (least
   squares refit on the other folds); the best is kept only if it improves every
   fold and, after the Lagrangian's sparse search is rerun with it, the new model
   improves the held-out criterion by at least ``min_improvement``.
   Then each accepted dissipative effect is tried against the other candidates of
   the same coordinates (a swap, e.g. quadratic drag for viscous damping), and a
   swap is kept when the refitted model improves the held-out criterion by
   ``min_improvement``.
3. **Never make things worse.** The final model is compared with the starting one on
   the same held-out criterion; if it is not better, the starting model is kept.

The criterion: held-out trajectory prediction
---------------------------------------------
Small damping changes trajectories over seconds but is a tiny share of the
pointwise acceleration residual, where differentiation noise dominates. The
criterion is therefore the **integrated (weak-form) residual**: the Euler-Lagrange
equations integrated against smooth bump functions over windows of the held-out
trajectories (integration by parts removes the accelerations; see
:meth:`lagsindy.euler_lagrange.EulerLagrangeOperator.weak_gram`). Each model's
coefficients are refitted by least squares on the other folds (with the weak form's
noise correction), and the residual of the held-out fold is measured. Damping and
Coulomb coefficients are kept non-negative in these refits (active-set least
squares). The pointwise (strong-form) criterion is computed the same way and
reported beside it. When the rows are not time-ordered trajectories long enough for
the windows, the pointwise criterion is used (the report says so).

Every coordinate counts: each equation is weighted by the inverse energy of the
starting model's force contributions on that coordinate (the sum of the magnitudes
of its terms, or the measured force when larger), not by its residual or its
measured force alone, so an undriven coordinate whose forces nearly cancel does
not drown the others, nor is it drowned.

Folds are whole trajectories (``groups``); with fewer trajectories than
``n_splits`` each trajectory is cut into ``n_splits`` contiguous time blocks. A fold
whose refit has a singular or indefinite mass matrix on its held-out samples cannot
predict accelerations there; it is excluded from that model's score and listed in
the report. A model whose full-data mass matrix is singular or indefinite is never
accepted.

The package: :mod:`.catalogue` (the candidate effects), :mod:`.scoring` (held-out
scores and refits), :mod:`.search` (:func:`diagnose`) and :mod:`.report` (what it
returns).
"""

from .catalogue import DEFAULT_CATALOGUE, velocity_eps
from .report import Candidate, DiagnosisReport, Step
from .search import diagnose

__all__ = [
    "DEFAULT_CATALOGUE",
    "Candidate",
    "DiagnosisReport",
    "Step",
    "diagnose",
    "velocity_eps",
]
