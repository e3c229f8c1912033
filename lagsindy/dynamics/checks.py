"""Mass-matrix checks of mechanical models: singular or indefinite mass matrices."""

from __future__ import annotations

import numpy as np

# A mass matrix whose eigenvalues differ in sign, or whose smallest magnitude
# eigenvalue is below this fraction of the largest, is treated as singular.
MASS_MATRIX_RCOND = 1e-10
# After a failed integration, a mass matrix whose smallest eigenvalue fell below this
# fraction of its initial size is named as the cause.
NEAR_SINGULAR = 1e-3


class SingularMassMatrixError(ValueError):
    """The mass matrix of a model is singular or indefinite at some state.

    A Lagrangian is only a valid mechanical model where its mass matrix
    ``d2L/dqdot2`` is definite (positive, or negative for a Lagrangian learned up to
    a negative scale from passive data). Attributes ``t``, ``q``, ``qd`` and
    ``eigenvalues`` locate the failure.
    """

    def __init__(self, message, *, t=None, q=None, qd=None, eigenvalues=None):
        super().__init__(message)
        self.t, self.q, self.qd, self.eigenvalues = t, q, qd, eigenvalues


def check_mass(model, mass, q, qd, t=None, reference=None):
    """Raise where ``mass`` of ``model`` is indefinite or (relative to ``reference``)
    singular.

    ``reference`` is a typical eigenvalue magnitude per sample (e.g. at the start of
    a simulation); without it only the spread within each matrix is used.
    """
    eig = np.linalg.eigvalsh(mass)
    big = np.abs(eig).max(axis=1)
    if reference is not None:
        big = np.maximum(big, reference)
    bad = ~(
        (
            np.all(eig > MASS_MATRIX_RCOND * big[:, None], axis=1)
            | np.all(eig < -MASS_MATRIX_RCOND * big[:, None], axis=1)
        )
        & (big > 0)
    )
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        when = ""
        if t is not None:
            tt = np.broadcast_to(np.asarray(t, dtype=float), (q.shape[0],))[i]
            when = f" at t={tt:.6g}"
        state = ", ".join(
            f"{n}={a:.6g}, {n}_dot={b:.6g}"
            for n, a, b in zip(model.coordinates, q[i], qd[i])
        )
        raise SingularMassMatrixError(
            f"the mass matrix of {model.name} is singular or indefinite{when} "
            f"(sample {i}: {state}; eigenvalues "
            f"{np.array2string(eig[i], precision=4)}); "
            "the Lagrangian is not a valid mechanical model at this state. "
            "Check the learned terms (lower lam, more data or a wider library), "
            "or start the simulation elsewhere.",
            t=None if t is None else float(np.broadcast_to(t, (q.shape[0],))[i]),
            q=q[i].copy(),
            qd=qd[i].copy(),
            eigenvalues=eig[i].copy(),
        )


def diagnose_failure(model, last, reference, message):
    """After a failed integration: blame a nearly singular mass matrix if there is
    one (else a RuntimeError with the integrator's ``message``)."""
    n = model.n_dof
    if "x" in last:
        x = last["x"]
        mass, _ = model._mass_and_rest(x[:, :n], x[:, n:])
        small = np.abs(np.linalg.eigvalsh(mass)).min(axis=1) / np.maximum(
            reference, 1e-300
        )
        i = int(np.argmin(small))
        if small[i] < NEAR_SINGULAR:
            state = ", ".join(
                f"{nm}={a:.6g}, {nm}_dot={b:.6g}"
                for nm, a, b in zip(model.coordinates, x[i, :n], x[i, n:])
            )
            raise SingularMassMatrixError(
                f"the mass matrix of {model.name} became nearly singular at "
                f"t={last['t']:.6g} (trajectory {i}: {state}; smallest eigenvalue "
                f"{small[i]:.2g} of its value at the start), so the accelerations blow "
                f"up and the integrator stopped ({message}). The Lagrangian is not a "
                "valid mechanical model there.",
                t=float(last["t"]),
                q=x[i, :n].copy(),
                qd=x[i, n:].copy(),
                eigenvalues=np.linalg.eigvalsh(mass[i]),
            )
    raise RuntimeError(f"integration of {model.name} failed: {message}")
