"""A URDF's serial chain from its base to its flange, read and checked (the XML only; no meshes, no ROS).

A URDF describes a tree of links joined by joints. Calibration needs one serial chain: the joints from the
tree's root link to the flange link, each turning about a fixed axis. This module finds that chain and
refuses, with the reason in the user's terms, what such a model cannot hold:

- a prismatic, planar or floating joint on the chain (hil's model turns joints; it does not slide them);
- a mimic joint on the chain (it moves with another joint instead of reading its own encoder);
- a xacro file (macros, not a robot: it must be expanded by ROS's `xacro` tool first);
- a tree whose flange is not named and cannot be told (several leaves after the last joint).

Fixed joints are kept as transforms: those before the first moving joint place it in the root's frame,
those after the last lead to the flange, those between two moving joints join them rigidly. Mass and
centre of mass come from each link's `<inertial>` when given, its collision shapes from its `<collision>`
elements (cylinder, box, sphere, and the capsule some descriptions use; a mesh is named but not read).
Units as the URDF has them: metres, radians, kilograms.

A robot is named by the file and, optionally, its flange link: ``arm.urdf#tool0`` (`split_spec`). One
string then names the whole robot everywhere (`--robot`, `[robot] model`, a campaign's snapshot).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

URDF_SUFFIXES: tuple[str, ...] = (".urdf",)
XACRO_SUFFIXES: tuple[str, ...] = (".xacro",)
MOVING_KINDS = ("revolute", "continuous")
# ROS-Industrial names the flange frame every tool is given in `tool0`: the one to take when several leaves
# follow the last joint (a UR description's `tool0` beside its `ft_frame` or `ee_link`).
ROS_INDUSTRIAL_FLANGE = "tool0"
CONTINUOUS_LIMITS_RAD = (-2 * np.pi, 2 * np.pi)  # what a robot file's default [-360, 360] deg means


class UrdfError(ValueError):
    """A URDF that cannot give a calibration model; the message names the file, the element and the fix."""


COLLISION_SHAPES = ("cylinder", "box", "sphere", "capsule", "mesh")


@dataclass(frozen=True)
class UrdfShape:
    """One `<collision>` element of a link: its `<geometry>` kind, its pose in the link (`T_link_shape`)
    and its size (m): cylinder and capsule (radius, length) along the shape's z, box (x, y, z) edges, sphere
    (radius,); a mesh has no size here (its file is not read)."""

    kind: str
    T_link_shape: np.ndarray
    size_m: tuple[float, ...]


@dataclass(frozen=True)
class UrdfLink:
    """A link's name, its `<inertial>` mass (kg) and centre of mass (m, link frame), None when absent, and
    its `<collision>` shapes."""

    name: str
    mass_kg: float | None
    com_link_m: np.ndarray | None
    collisions: tuple[UrdfShape, ...] = ()


@dataclass(frozen=True)
class UrdfJoint:
    """A joint as the URDF gives it: the joint frame in its parent link (`T_parent_joint`), the axis in the
    joint frame (unit), limits (rad) for a revolute joint, the joint it mimics when it does."""

    name: str
    kind: str
    parent: str
    child: str
    T_parent_joint: np.ndarray
    axis: np.ndarray
    limits_rad: tuple[float, float] | None
    mimics: str | None


@dataclass(frozen=True)
class UrdfChain:
    """The serial chain of a URDF, root to flange. `joints` are the moving joints in order; `T_before[i]`
    is the rigid transform from the child link of moving joint i - 1 (the root for i = 0) to moving joint
    i's frame (its origin and every fixed joint between); `T_last_flange` from the last moving joint's child
    link to the flange link. `moved_links[i]` are the links moving joint i carries rigidly (its child and
    the links fixed to it, up to the next moving joint), each with its pose in the child link's frame; the
    inertial data of the links are in `links`. `base_links`: the root and the links fixed to it, each with
    its pose in the root's frame."""

    robot_name: str
    source: str
    root: str
    flange: str
    flange_named: bool
    joints: tuple[UrdfJoint, ...]
    T_before: tuple[np.ndarray, ...]
    T_last_flange: np.ndarray
    moved_links: tuple[tuple[tuple[str, np.ndarray], ...], ...]
    links: dict[str, UrdfLink]
    base_links: tuple[tuple[str, np.ndarray], ...] = ()


def split_spec(spec: str) -> tuple[str, str | None]:
    """'arm.urdf#tool0' -> ('arm.urdf', 'tool0'); a spec without '#' names no flange."""
    path, sep, flange = str(spec).partition("#")
    return path, (flange or None) if sep else None


def is_urdf_spec(spec: str) -> bool:
    """Whether a robot spec names a URDF or a xacro file (the fragment after '#' aside)."""
    path = split_spec(spec)[0].lower()
    return path.endswith(URDF_SUFFIXES + XACRO_SUFFIXES)


def xacro_advice(source: str) -> str:
    """What to do with a xacro file: expand it with ROS's tool into a plain URDF."""
    stem = Path(split_spec(source)[0]).name
    out = stem.removesuffix(".xacro").removesuffix(".urdf") + ".urdf"
    return (
        f"{source}: a xacro file (macros that generate a URDF) is not read; expand it first with ROS's xacro "
        f"tool (`xacro {stem} > {out}`, with the arguments the robot's launch files give it; outside ROS: "
        f"`pip install xacro`) and give {out}"
    )


def read_chain(text: str, source: str) -> UrdfChain:
    """The chain from the root link to the flange (`source`'s '#link' when given, else the chain's last
    link) of a URDF's text, checked; raises UrdfError naming what to change."""
    path, flange = split_spec(source)
    if path.lower().endswith(XACRO_SUFFIXES) or "xmlns:xacro" in text or "<xacro:" in text:
        raise UrdfError(xacro_advice(source))
    try:
        root_el = ET.fromstring(text)
    except ET.ParseError as exc:
        raise UrdfError(f"{path}: not valid XML ({exc}); give the URDF file (a <robot> element)") from None
    if root_el.tag != "robot":
        raise UrdfError(f"{path}: the top element is <{root_el.tag}>, not <robot>; give a URDF file")
    links = {lk.name: lk for lk in (_link(path, el) for el in root_el.findall("link"))}
    joints = [_joint(path, el) for el in root_el.findall("joint")]
    by_child = {j.child: j for j in joints}
    root = _root(path, links, joints)
    if flange is None:
        flange = _last_link(path, root, joints)
    elif flange not in links:
        raise UrdfError(
            f"{path}: no link named {flange!r} (the flange after '#'); its links are {', '.join(sorted(links))}"
        )
    path_joints = _path(by_child, root, flange)
    return _chain(source, root_el.get("name", Path(path).stem), root, flange, path_joints, joints, links)


def _chain(
    source: str,
    name: str,
    root: str,
    flange: str,
    path_joints: list[UrdfJoint],
    joints: list[UrdfJoint],
    links: dict[str, UrdfLink],
) -> UrdfChain:
    """Fold the path's fixed joints into the transforms between moving joints; refuse what cannot move."""
    path = split_spec(source)[0]
    moving: list[UrdfJoint] = []
    before: list[np.ndarray] = []
    T = np.eye(4)
    for j in path_joints:
        if j.kind == "fixed":
            T = T @ j.T_parent_joint
            continue
        if j.kind not in MOVING_KINDS:
            raise UrdfError(_refusal(path, j))
        if j.mimics is not None:
            raise UrdfError(
                f"{path}: joint {j.name!r} mimics joint {j.mimics!r} (it moves with it, not on its own encoder); "
                "hil's model has one reading per joint: give a URDF without the coupling, or name a flange "
                f"before it ({split_spec(source)[0]}#LINK)"
            )
        before.append(T @ j.T_parent_joint)
        moving.append(j)
        T = np.eye(4)
    if not moving:
        raise UrdfError(f"{path}: no revolute joint between {root!r} and {flange!r}; name the flange link")
    children: dict[str, list[UrdfJoint]] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    carried = tuple(tuple(_fixed_group(j.child, children)) for j in moving)
    return UrdfChain(
        name,
        path,
        root,
        flange,
        split_spec(source)[1] is not None,
        tuple(moving),
        tuple(before),
        T,
        carried,
        links,
        tuple(_fixed_group(root, children)),
    )


def _refusal(path: str, j: UrdfJoint) -> str:
    """Why a joint on the chain that does not turn is refused, in the user's terms."""
    if j.kind == "prismatic":
        return (
            f"{path}: joint {j.name!r} is prismatic (it slides); hil's model turns every joint (a linear axis, "
            "a track or a gantry, is not calibrated): give the arm's URDF without it, or name a flange "
            "link before it (FILE.urdf#LINK)"
        )
    return (
        f"{path}: joint {j.name!r} is {j.kind}; only revolute, continuous and fixed joints can be calibrated"
    )


def _fixed_group(
    link: str, children: dict[str, list[UrdfJoint]], T_link: np.ndarray | None = None
) -> list[tuple[str, np.ndarray]]:
    """A link and every link fixed to it, depth first, each with its pose in the first link's frame."""
    T = np.eye(4) if T_link is None else T_link
    out = [(link, T)]
    for j in children.get(link, []):
        if j.kind == "fixed":
            out.extend(_fixed_group(j.child, children, T @ j.T_parent_joint))
    return out


def _root(path: str, links: dict[str, UrdfLink], joints: list[UrdfJoint]) -> str:
    """The one link that is no joint's child."""
    children = {j.child for j in joints}
    roots = sorted(set(links) - children)
    if len(roots) != 1:
        raise UrdfError(
            f"{path}: {'no' if not roots else len(roots)} root link(s) {roots}; a URDF is one tree of links"
        )
    return roots[0]


def _path(by_child: dict[str, UrdfJoint], root: str, link: str) -> list[UrdfJoint]:
    """The joints from the root to a link, in order."""
    out: list[UrdfJoint] = []
    while link != root:
        j = by_child[link]
        out.append(j)
        link = j.parent
    return out[::-1]


def _last_link(path: str, root: str, joints: list[UrdfJoint]) -> str:
    """The chain's last link when the flange is not named: the leaf after the most joints that turn, the
    ROS-Industrial `tool0` among equals; refused naming the candidates when it cannot be told."""
    by_child = {j.child: j for j in joints}
    parents = {j.parent for j in joints}
    leaves = sorted(set(by_child) - parents) or [root]
    moving = {leaf: sum(j.kind != "fixed" for j in _path(by_child, root, leaf)) for leaf in leaves}
    most = max(moving.values())
    best = [leaf for leaf in leaves if moving[leaf] == most]
    if len(best) == 1:
        return best[0]
    if ROS_INDUSTRIAL_FLANGE in best:
        return ROS_INDUSTRIAL_FLANGE
    raise UrdfError(
        f"{path}: the chain ends in several links ({', '.join(best)}); name the flange: "
        f"{path}#{best[0]} (the link whose frame the tool is given in)"
    )


def _link(path: str, el: ET.Element) -> UrdfLink:
    name = _name(path, el, "link")
    shapes = tuple(_collision(path, name, c) for c in el.findall("collision"))
    inertial = el.find("inertial")
    if inertial is None:
        return UrdfLink(name, None, None, shapes)
    mass_el = inertial.find("mass")
    mass = None if mass_el is None else _float(path, f"link {name!r} <mass value>", mass_el.get("value"))
    origin = inertial.find("origin")
    com = _vector(
        path, f"link {name!r} <inertial><origin xyz>", origin.get("xyz") if origin is not None else None
    )
    return UrdfLink(name, mass, com, shapes)


def _collision(path: str, link: str, el: ET.Element) -> UrdfShape:
    """A `<collision>` element: its origin and the one shape of its `<geometry>`, sizes checked positive."""
    where = f"link {link!r} <collision>"
    geometry = el.find("geometry")
    shape = None if geometry is None else next(iter(geometry), None)
    if shape is None or shape.tag not in COLLISION_SHAPES:
        found = "nothing" if shape is None else f"<{shape.tag}>"
        raise UrdfError(
            f"{path}: {where} <geometry> holds {found}; give one of {', '.join(COLLISION_SHAPES)}"
        )
    origin = el.find("origin")
    T = _origin(path, where, origin)
    keys = {"cylinder": ("radius", "length"), "capsule": ("radius", "length"), "sphere": ("radius",)}
    if shape.tag == "box":
        size = tuple(float(v) for v in _vector(path, f"{where} <box size>", shape.get("size")))
    else:
        size = tuple(
            _float(path, f"{where} <{shape.tag} {key}>", shape.get(key)) for key in keys.get(shape.tag, ())
        )
    if any(not v > 0 for v in size) or (shape.tag == "box" and shape.get("size") is None):
        raise UrdfError(f"{path}: {where} <{shape.tag}> needs positive sizes, got {size}")
    return UrdfShape(shape.tag, T, size)


def _origin(path: str, where: str, origin: ET.Element | None) -> np.ndarray:
    """An `<origin xyz rpy>` as a transform (the identity when absent)."""
    xyz = _vector(path, f"{where} <origin xyz>", origin.get("xyz") if origin is not None else None)
    rpy = _vector(path, f"{where} <origin rpy>", origin.get("rpy") if origin is not None else None)
    T = np.eye(4)
    from scipy.spatial.transform import Rotation  # imported here: hil.geometry.se3 says why

    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF: fixed-axis roll, pitch, yaw
    T[:3, 3] = xyz
    return T


def _joint(path: str, el: ET.Element) -> UrdfJoint:
    name = _name(path, el, "joint")
    kind = el.get("type", "")
    where = f"joint {name!r}"
    parent, child = el.find("parent"), el.find("child")
    if parent is None or child is None or not parent.get("link") or not child.get("link"):
        raise UrdfError(f"{path}: {where} needs <parent link=...> and <child link=...>")
    T = _origin(path, where, el.find("origin"))
    axis_el = el.find("axis")
    axis = (
        np.array([1.0, 0.0, 0.0])
        if axis_el is None
        else _vector(path, f"{where} <axis xyz>", axis_el.get("xyz"))
    )
    if kind != "fixed" and not np.linalg.norm(axis) > 1e-9:
        raise UrdfError(f"{path}: {where} has a zero <axis xyz>; give its axis of rotation")
    limits = None
    if kind == "revolute":
        limit = el.find("limit")
        if limit is not None and limit.get("lower") is not None and limit.get("upper") is not None:
            limits = (
                _float(path, f"{where} <limit lower>", limit.get("lower")),
                _float(path, f"{where} <limit upper>", limit.get("upper")),
            )
            if not limits[0] < limits[1]:
                raise UrdfError(f"{path}: {where} <limit>: lower must be below upper, got {limits}")
    mimic = el.find("mimic")
    return UrdfJoint(
        name,
        kind,
        str(parent.get("link")),
        str(child.get("link")),
        T,
        axis / max(float(np.linalg.norm(axis)), 1e-300),
        limits,
        None if mimic is None else str(mimic.get("joint")),
    )


def _name(path: str, el: ET.Element, tag: str) -> str:
    name = el.get("name")
    if not name:
        raise UrdfError(f"{path}: a <{tag}> without a name")
    return name


def _float(path: str, where: str, text: str | None) -> float:
    try:
        value = float(str(text))
    except ValueError:
        raise UrdfError(f"{path}: {where} must be a number, got {text!r}") from None
    if not np.isfinite(value):
        raise UrdfError(f"{path}: {where} must be finite, got {text!r}")
    return value


def _vector(path: str, where: str, text: str | None) -> np.ndarray:
    """Three numbers separated by spaces (URDF's default 0 0 0 when absent)."""
    if text is None:
        return np.zeros(3)
    parts = text.split()
    if len(parts) != 3:
        raise UrdfError(f"{path}: {where} must be three numbers, got {text!r}")
    return np.array([_float(path, where, p) for p in parts])
