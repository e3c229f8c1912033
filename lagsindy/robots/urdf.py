"""URDF files read into a kinematic tree of moving bodies.

The parser is the standard library's :mod:`xml.etree.ElementTree`: the part of URDF
that dynamics needs (links' ``<inertial>``, joints' ``<origin>``, ``<axis>``,
``<limit>``, ``<mimic>``, ``<dynamics>``) is a handful of elements and attributes, so a
dependency (``urdfdom``, ``yourdfpy``, which also load meshes) would buy nothing here and
would be one more package to install for every user. ``xacro`` files must be expanded
first (``xacro robot.urdf.xacro > robot.urdf``).

Reduction to moving bodies (the convention of pinocchio and of the robotics literature):

* every joint that moves (``revolute``, ``continuous``, ``prismatic``) and is one of the
  chosen coordinates starts a *body* whose frame is its child link's frame (the URDF
  joint frame after the joint's motion);
* ``fixed`` joints, and joints that are not coordinates (fingers, a gripper: *locked*
  at a given position), are merged: their child links ride on the body above them and
  their inertias are added to it, expressed in the body's frame;
* links that ride on the root (the base, a world link) do not move and are ignored.

Each body carries its 10 inertial parameters about its frame's origin in pinocchio's
order ``[m, m*cx, m*cy, m*cz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]``.
"""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

MOVING = ("revolute", "continuous", "prismatic")
PARAMETER_KINDS = ("m", "mx", "my", "mz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


# ----------------------------------------------------------------------- raw URDF
@dataclasses.dataclass
class URDFJoint:
    """One ``<joint>`` element as written in the file."""

    name: str
    type: str
    parent: str
    child: str
    xyz: np.ndarray
    rpy: np.ndarray
    axis: np.ndarray
    lower: float
    upper: float
    mimic: tuple[str, float, float] | None  # (joint, multiplier, offset)
    damping: float
    friction: float


def _floats(text, default, n=3, what=""):
    if text is None:
        return np.array(default, dtype=float)
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        raise ValueError(f"URDF: cannot read numbers from {text!r} ({what})") from None
    if len(values) != n:
        raise ValueError(f"URDF: expected {n} numbers in {text!r} ({what})")
    return np.array(values, dtype=float)


def _origin(element, what):
    origin = element.find("origin") if element is not None else None
    if origin is None:
        return np.zeros(3), np.zeros(3)
    return (
        _floats(origin.get("xyz"), [0, 0, 0], what=f"{what} origin xyz"),
        _floats(origin.get("rpy"), [0, 0, 0], what=f"{what} origin rpy"),
    )


def rpy_matrix(rpy) -> np.ndarray:
    """Rotation of URDF roll-pitch-yaw angles: ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp_, cy, sy = (
        math.cos(r),
        math.sin(r),
        math.cos(p),
        math.sin(p),
        math.cos(y),
        math.sin(y),
    )
    return np.array(
        [
            [cy * cp, cy * sp_ * sr - sy * cr, cy * sp_ * cr + sy * sr],
            [sy * cp, sy * sp_ * sr + cy * cr, sy * sp_ * cr - cy * sr],
            [-sp_, cp * sr, cp * cr],
        ]
    )


def _skew(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def axis_rotation(axis, angle) -> np.ndarray:
    """Rotation by ``angle`` about the unit vector ``axis`` (Rodrigues)."""
    k = _skew(axis)
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def inertia_matrix(params) -> np.ndarray:
    """The 3x3 rotational inertia of a 10-vector (about the frame origin)."""
    _, _, _, _, ixx, ixy, iyy, ixz, iyz, izz = params
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def pack(mass, first_moment, inertia_origin) -> np.ndarray:
    """``[m, h, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]`` from mass, ``m*c`` and inertia at origin."""
    i = inertia_origin
    return np.array(
        [mass, *first_moment, i[0, 0], i[0, 1], i[1, 1], i[0, 2], i[1, 2], i[2, 2]],
        dtype=float,
    )


def transform_parameters(params, rotation, translation) -> np.ndarray:
    """Inertial 10-vector of a body moved into another frame.

    ``rotation`` and ``translation`` give the body's frame in the new frame
    (``x_new = R x + p``). Linear in ``params``:
    ``h' = R h + m p`` and ``I' = R I R^T - [R h][p] - [p][R h] - m [p]^2`` with
    ``[.]`` the cross-product matrix.
    """
    m = params[0]
    h = rotation @ np.asarray(params[1:4], dtype=float)
    p = np.asarray(translation, dtype=float)
    sp_, sh = _skew(p), _skew(h)
    i = (
        rotation @ inertia_matrix(params) @ rotation.T
        - sh @ sp_
        - sp_ @ sh
        - m * (sp_ @ sp_)
    )
    return pack(m, h + m * p, i)


def link_parameters(link_element) -> np.ndarray:
    """10-vector of a ``<link>``'s ``<inertial>`` about the link frame's origin."""
    inertial = link_element.find("inertial")
    if inertial is None:
        return np.zeros(10)
    name = link_element.get("name")
    mass_el = inertial.find("mass")
    mass = float(mass_el.get("value", 0.0)) if mass_el is not None else 0.0
    xyz, rpy = _origin(inertial, f"link {name!r} inertial")
    el = inertial.find("inertia")
    get = (lambda k: float(el.get(k, 0.0))) if el is not None else (lambda k: 0.0)
    ic = np.array(
        [
            [get("ixx"), get("ixy"), get("ixz")],
            [get("ixy"), get("iyy"), get("iyz")],
            [get("ixz"), get("iyz"), get("izz")],
        ]
    )
    at_com = pack(mass, np.zeros(3), ic)  # in the inertial frame, about the COM
    return transform_parameters(at_com, rpy_matrix(rpy), xyz)


def read_urdf(path):
    """Parse a URDF file: ``(robot name, links {name: element}, joints in file order)``."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ValueError(f"{path} is not a readable URDF (XML) file: {exc}") from None
    if root.tag != "robot":
        raise ValueError(f"{path}: the root element is <{root.tag}>, not <robot>")
    links = {el.get("name"): el for el in root.findall("link")}
    joints = []
    for el in root.findall("joint"):
        name, kind = el.get("name"), el.get("type")
        parent, child = el.find("parent"), el.find("child")
        if parent is None or child is None:
            raise ValueError(f"{path}: joint {name!r} lacks <parent> or <child>")
        xyz, rpy = _origin(el, f"joint {name!r}")
        axis_el = el.find("axis")
        axis = _floats(
            axis_el.get("xyz") if axis_el is not None else None,
            [1, 0, 0],
            what=f"joint {name!r} axis",
        )
        limit = el.find("limit")
        lower = float(limit.get("lower", -math.inf)) if limit is not None else -math.inf
        upper = float(limit.get("upper", math.inf)) if limit is not None else math.inf
        if kind == "continuous":
            lower, upper = -math.inf, math.inf
        mimic_el = el.find("mimic")
        mimic = None
        if mimic_el is not None:
            mimic = (
                mimic_el.get("joint"),
                float(mimic_el.get("multiplier", 1.0)),
                float(mimic_el.get("offset", 0.0)),
            )
        dyn = el.find("dynamics")
        joints.append(
            URDFJoint(
                name=name,
                type=kind,
                parent=parent.get("link"),
                child=child.get("link"),
                xyz=xyz,
                rpy=rpy,
                axis=axis,
                lower=lower,
                upper=upper,
                mimic=mimic,
                damping=float(dyn.get("damping", 0.0)) if dyn is not None else 0.0,
                friction=float(dyn.get("friction", 0.0)) if dyn is not None else 0.0,
            )
        )
    return root.get("name", path.stem), links, joints


# ------------------------------------------------------------------- reduced tree
@dataclasses.dataclass
class Body:
    """A moving body: the links carried by one coordinate joint, merged.

    ``rotation``/``translation`` place the joint frame (before its motion) in the
    parent body's frame; ``parent`` is the parent body's index, -1 for the fixed base.
    """

    name: str  # the joint's child link
    joint: str
    type: str  # "revolute" or "prismatic" ("continuous" is revolute)
    parent: int
    coordinate: int
    rotation: np.ndarray
    translation: np.ndarray
    axis: np.ndarray
    parameters: np.ndarray  # 10-vector about the body frame's origin
    links: list[str]  # the URDF links merged into this body (its own first)


@dataclasses.dataclass
class RobotTree:
    """A URDF reduced to the moving bodies of the chosen joints.

    Attributes
    ----------
    name : str
        The robot's name in the file.
    coordinates : list of str
        The coordinate joints, in the order of ``q``.
    bodies : list of Body
        Moving bodies in tree order (a parent before its children).
    locked : dict of str to float
        The position of every moving joint that is not a coordinate.
    lower, upper : ndarray of shape (n_dof,)
        Joint limits of the coordinates (infinite for continuous joints).
    damping, friction : ndarray of shape (n_dof,)
        The URDF ``<dynamics>`` values of the coordinates (0 when absent).
    path : Path
        The file read.
    """

    name: str
    coordinates: list[str]
    bodies: list[Body]
    locked: dict[str, float]
    lower: np.ndarray
    upper: np.ndarray
    damping: np.ndarray
    friction: np.ndarray
    path: Path

    @property
    def n_dof(self) -> int:
        return len(self.coordinates)

    def parameters(self) -> np.ndarray:
        """The bodies' inertial parameters from the file, stacked: (10 * n_bodies,)."""
        return np.concatenate([b.parameters for b in self.bodies])


def _locked_positions(joints, coordinates, locked):
    """Position of every non-coordinate moving joint (mimic joints resolved)."""
    by_name = {j.name: j for j in joints}
    out = {}

    def value(name, seen):
        if name in out:
            return out[name]
        j = by_name[name]
        if j.mimic is not None:
            target = j.mimic[0]
            if target not in by_name:
                raise ValueError(
                    f"joint {name!r} mimics {target!r}, which is not a joint"
                )
            if target in coordinates:
                raise ValueError(
                    f"joint {name!r} mimics {target!r}, which is a coordinate; mimic "
                    "joints that follow a coordinate are not supported: leave "
                    f"{target!r} out of joints= (it and {name!r} are then locked, "
                    "see locked=)"
                )
            if name in seen:
                raise ValueError(f"mimic joints form a cycle through {name!r}")
            if name in locked:
                raise ValueError(
                    f"joint {name!r} mimics {target!r}: lock {target!r} instead"
                )
            v = j.mimic[1] * value(target, seen | {name}) + j.mimic[2]
        elif name in locked:
            v = float(locked[name])
        elif j.type in MOVING:
            v = float(np.clip(0.0, j.lower, j.upper))
        else:
            v = 0.0
        out[name] = v
        return v

    for j in joints:
        if j.type in MOVING and j.name not in coordinates:
            value(j.name, frozenset())
    return out


def build_tree(
    path,
    joints: Sequence[str] | None = None,
    locked: Mapping[str, float] | None = None,
) -> RobotTree:
    """Read a URDF and reduce it to the moving bodies of the chosen joints.

    Parameters
    ----------
    path : str or Path
        The URDF file.
    joints : list of str, default=None
        Coordinate joints, in the order of ``q``. ``None``: every revolute, continuous
        and prismatic joint that is not a mimic joint, in file order.
    locked : dict of str to float, default=None
        Positions of moving joints that are not coordinates (fingers). A joint left
        out is locked at 0 clipped into its limits; a mimic joint follows the joint
        it mimics.

    Returns
    -------
    RobotTree
    """
    name, links, urdf_joints = read_urdf(path)
    by_name = {j.name: j for j in urdf_joints}
    for j in urdf_joints:
        if j.type not in (*MOVING, "fixed"):
            raise ValueError(
                f"joint {j.name!r} has type {j.type!r}; only revolute, continuous, "
                "prismatic and fixed joints are supported (a floating base is not)"
            )
        for link in (j.parent, j.child):
            if link not in links:
                raise ValueError(
                    f"joint {j.name!r} names link {link!r}, which is not defined"
                )
    if joints is None:
        coordinates = [
            j.name for j in urdf_joints if j.type in MOVING and j.mimic is None
        ]
    else:
        coordinates = [joints] if isinstance(joints, str) else list(joints)
        for c in coordinates:
            if c not in by_name:
                raise ValueError(
                    f"joint {c!r} is not in {Path(path).name}; its moving joints are "
                    f"{[j.name for j in urdf_joints if j.type in MOVING]}"
                )
            if by_name[c].type not in MOVING:
                raise ValueError(
                    f"joint {c!r} is {by_name[c].type}; it cannot be a coordinate"
                )
            if by_name[c].mimic is not None:
                raise ValueError(
                    f"joint {c!r} mimics {by_name[c].mimic[0]!r}; a mimic joint cannot be "
                    "a coordinate"
                )
        if len(set(coordinates)) != len(coordinates):
            raise ValueError(f"joints lists a joint twice: {coordinates}")
    if not coordinates:
        raise ValueError(
            f"{Path(path).name} has no moving joint to use as a coordinate"
        )
    locked = dict(locked or {})
    for k in locked:
        if k not in by_name or by_name[k].type not in MOVING:
            raise ValueError(
                f"locked names {k!r}, which is not a moving joint of the URDF"
            )
        if k in coordinates:
            raise ValueError(f"joint {k!r} is both a coordinate and locked")
    positions = _locked_positions(urdf_joints, coordinates, locked)

    children: dict[str, list[URDFJoint]] = {}
    for j in urdf_joints:
        children.setdefault(j.parent, []).append(j)
    child_links = {j.child for j in urdf_joints}
    roots = [n for n in links if n not in child_links]
    if len(roots) != 1:
        raise ValueError(f"a URDF needs exactly one root link, found {roots}")

    bodies: list[Body] = []

    def visit(link, body, rot, trans):
        """Depth first, children in file order (a parent body before its children)."""
        for j in children.get(link, []):
            jrot = rot @ rpy_matrix(j.rpy)
            jtrans = trans + rot @ j.xyz
            if j.type in MOVING and not np.linalg.norm(j.axis) > 0:
                raise ValueError(
                    f"joint {j.name!r} has a zero axis; give <axis xyz=...>"
                )
            axis = j.axis / np.linalg.norm(j.axis) if j.type in MOVING else j.axis
            if j.name in coordinates:
                bodies.append(
                    Body(
                        name=j.child,
                        joint=j.name,
                        type="prismatic" if j.type == "prismatic" else "revolute",
                        parent=body,
                        coordinate=coordinates.index(j.name),
                        rotation=jrot,
                        translation=jtrans,
                        axis=axis,
                        parameters=link_parameters(links[j.child]),
                        links=[j.child],
                    )
                )
                visit(j.child, len(bodies) - 1, np.eye(3), np.zeros(3))
                continue
            if j.type in MOVING:
                v = positions[j.name]
                if j.type == "prismatic":
                    jtrans = jtrans + jrot @ (axis * v)
                else:
                    jrot = jrot @ axis_rotation(axis, v)
            if body >= 0:
                bodies[body].parameters = bodies[
                    body
                ].parameters + transform_parameters(
                    link_parameters(links[j.child]), jrot, jtrans
                )
                bodies[body].links.append(j.child)
            visit(j.child, body, jrot, jtrans)

    visit(roots[0], -1, np.eye(3), np.zeros(3))
    found = {b.joint for b in bodies}
    missing = [c for c in coordinates if c not in found]
    if missing:
        raise ValueError(
            f"joints {missing} are not reachable from the root link {roots[0]!r}"
        )
    idx = [by_name[c] for c in coordinates]
    return RobotTree(
        name=name,
        coordinates=coordinates,
        bodies=bodies,
        locked=positions,
        lower=np.array([j.lower for j in idx]),
        upper=np.array([j.upper for j in idx]),
        damping=np.array([j.damping for j in idx]),
        friction=np.array([j.friction for j in idx]),
        path=Path(path),
    )
