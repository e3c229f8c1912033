"""Joint effects a URDF does not declare, as force kinds of :mod:`lagsindy.force_kinds`.

The registry's ``viscous``, ``coulomb`` (``tanh(qd/eps)``) and ``bias`` (a constant
offset) kinds are the classical per-joint friction model of robot identification
(Stribeck: the ``stribeck`` kind); this module adds

=============  =====================  ===============================================
kind           force for a unit       meaning
               coefficient
=============  =====================  ===============================================
``spring``     ``-q_i``               a torque proportional to the joint angle: a
                                      spring, a cable or a gravity compensator
                                      (with ``bias``: ``-k (q_i - q_rest)``)
=============  =====================  ===============================================

registered when :mod:`lagsindy.robots` is imported (not in ``diagnose``'s default
catalogue, which other systems share: name it, or pass :data:`ROBOT_CATALOGUE`).
"""

from __future__ import annotations

from .. import force_kinds

#: What :func:`lagsindy.diagnose` should try on a robot arm: an input delay per
#: driven joint (``"joint_delay"``: each drive may lag by its own amount; a delay
#: common to every joint is found as that delay on each), friction per joint, a
#: spring per joint and, for fits that hold the URDF's link parameters
#: (``inertia="urdf"``), a payload on the end body (``"payload"``; skipped with a
#: note for fits of base parameters, which a payload cannot add to).
ROBOT_CATALOGUE = ("joint_delay", "viscous", "coulomb", "bias", "spring", "payload")

#: The friction kinds a robot fit declares by default (``dissipation=``).
FRICTION_KINDS = ("viscous", "coulomb", "bias")


def _spring(q, qd):
    return (-q[0],), None


SPRING = force_kinds.ForceKind(
    "spring",
    _spring,
    dissipative=False,  # conservative: stores energy, either sign of q
    units="{F}/{q}",
    units_text="per unit of {0}",
    wording="spring (position-proportional torque)",
)


def register_kinds() -> None:
    """Register :data:`SPRING` unless a kind of that name exists already."""
    if "spring" not in force_kinds.names():
        force_kinds.register(SPRING)


register_kinds()
