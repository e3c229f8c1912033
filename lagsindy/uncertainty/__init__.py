"""How sure is each term? Bootstrap intervals, inclusion probabilities, library bagging.

* :func:`bootstrap` (:mod:`~lagsindy.uncertainty.bootstrap`): intervals and
  inclusion probabilities from resamples of whole trajectories or time blocks;
* :class:`LibraryBaggingLagrangianSINDy` (:mod:`~lagsindy.uncertainty.bagging`):
  library bagging (Ensemble-SINDy) for large candidate libraries.
"""

from .bagging import LibraryBaggingLagrangianSINDy
from .bootstrap import BootstrapReport, bootstrap

__all__ = ["BootstrapReport", "LibraryBaggingLagrangianSINDy", "bootstrap"]
