"""What a fitted estimator is used for, as its methods: code, CasADi functions,
linearizations and URDF write-back (:class:`ModelUseMixin`).

The estimator inherits them, so ``est.export(...)`` and the functions of
:mod:`lagsindy.export` are one implementation; this layer sits below the estimator
and reads only its fitted state.
"""

from __future__ import annotations

from sklearn.utils.validation import check_is_fitted

from .casadi_model import to_casadi
from .files import export_model
from .linearization import linearize


class ModelUseMixin:
    """``export``, ``to_casadi``, ``linearize`` and ``to_urdf`` of a fitted
    :class:`~lagsindy.LagrangianSINDy`."""

    def export(self, path, format=None, *, input_matrix=None):
        """Write the model as standalone Python or C code (no lagsindy needed).

        See :func:`lagsindy.export.export_model`.
        """
        return export_model(self, path, format, input_matrix=input_matrix)

    def to_casadi(self, input_matrix=None):
        """CasADi functions of the model (see :func:`lagsindy.export.to_casadi`)."""
        return to_casadi(self, input_matrix)

    def linearize(self, x_eq, u_eq=None, dt=None, *, input_matrix=None):
        """A, B (and the discrete pair given ``dt``) at an equilibrium (see
        :func:`lagsindy.export.linearize`)."""
        return linearize(self, x_eq, u_eq, dt, input_matrix=input_matrix)

    def to_urdf(self, path):
        """Write a model fitted with a URDF library into a copy of its URDF: link
        parameters (a physically consistent representative of the fitted base
        parameters) and joint friction. See :func:`lagsindy.robots.fitted_to_urdf`.
        Returns the :class:`pathlib.Path` written."""
        check_is_fitted(self)
        from ..robots.report import fitted_to_urdf

        return fitted_to_urdf(self, path)
