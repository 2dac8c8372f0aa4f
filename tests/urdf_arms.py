"""URDFs of three arm families, written for the tests in the style of the makers' ROS descriptions (joint
origins as xyz/rpy in the parent link, axes along the link's x, y or z), each describing the geometry of a
built-in robot file with the same joint zeros and directions:

- `ur10`: a UR-like arm (joints 2, 3, 4 parallel; the shoulder, elbow and wrist offsets across the arm, a
  `base` frame turned 180 deg beside `base_link`, `tool0` and `ee_link` both after the last joint);
- `kr6r900`: a six-axis arm with an offset wrist (KUKA-like; joints 2 and 3 parallel, wrist axes along x);
- `lrmate200id`: a FANUC-like arm (joints 2 and 3 parallel) standing on a `world` link away from its base
  and turned on it, so the fixed transform before joint 1 cannot go into joint 1 alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HALF_PI = np.pi / 2
# The flange frame of the KUKA- and FANUC-like arms in the last link: z out of the flange along the last axis
# (the link's x), x along the link's z: roll half a turn, pitch a quarter turn back.
RPY_FLANGE_ALONG_X = (np.pi, -HALF_PI, 0.0)


@dataclass(frozen=True)
class Joint:
    name: str
    parent: str
    child: str
    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] | None = (0.0, 0.0, 1.0)  # None: a fixed joint
    limits: tuple[float, float] | None = (-2 * np.pi, 2 * np.pi)
    kind: str | None = None  # overrides revolute / fixed
    mimic: str | None = None


def urdf_text(name: str, joints: list[Joint], masses: dict[str, tuple[float, tuple]] | None = None) -> str:
    """A URDF of these joints; `masses`: link -> (kg, centre of mass xyz in the link)."""
    masses = masses or {}
    links = dict.fromkeys([joints[0].parent] + [j.child for j in joints])
    out = [f'<?xml version="1.0"?>\n<robot name="{name}">']
    for link in links:
        if link in masses:
            kg, com = masses[link]
            out.append(
                f'  <link name="{link}"><inertial><origin xyz="{_v(com)}" rpy="0 0 0"/><mass value="{kg}"/>'
                '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>'
            )
        else:
            out.append(f'  <link name="{link}"/>')
    for j in joints:
        kind = j.kind or ("fixed" if j.axis is None else "revolute")
        body = [
            f'    <parent link="{j.parent}"/>',
            f'    <child link="{j.child}"/>',
            f'    <origin xyz="{_v(j.xyz)}" rpy="{_v(j.rpy)}"/>',
        ]
        if j.axis is not None:
            body.append(f'    <axis xyz="{_v(j.axis)}"/>')
        if kind in ("revolute", "prismatic") and j.limits is not None:
            body.append(
                f'    <limit lower="{j.limits[0]!r}" upper="{j.limits[1]!r}" effort="100" velocity="2"/>'
            )
        if j.mimic is not None:
            body.append(f'    <mimic joint="{j.mimic}" multiplier="-1"/>')
        out.append(f'  <joint name="{j.name}" type="{kind}">\n' + "\n".join(body) + "\n  </joint>")
    out.append("</robot>\n")
    return "\n".join(out)


def _v(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def ur10_joints() -> list[Joint]:
    """A UR10 in the layout of the ROS-Industrial description: the upper arm and forearm along the parent's
    z after a quarter turn about y, the shoulder (220.941 mm), elbow (171.9 mm) and wrist (114.9 mm) offsets
    along y, `tool0` 92.2 mm out along wrist 3's y."""
    return [
        Joint("base_link-base_fixed_joint", "base_link", "base", rpy=(0, 0, np.pi), axis=None),
        Joint("shoulder_pan_joint", "base_link", "shoulder_link", xyz=(0, 0, 0.1273)),
        Joint(
            "shoulder_lift_joint",
            "shoulder_link",
            "upper_arm_link",
            (0, 0.220941, 0),
            (0, HALF_PI, 0),
            (0, 1, 0),
        ),
        Joint("elbow_joint", "upper_arm_link", "forearm_link", (0, -0.1719, 0.612), axis=(0, 1, 0)),
        Joint("wrist_1_joint", "forearm_link", "wrist_1_link", (0, 0, 0.5723), (0, HALF_PI, 0), (0, 1, 0)),
        Joint("wrist_2_joint", "wrist_1_link", "wrist_2_link", (0, 0.1149, 0), axis=(0, 0, 1)),
        Joint("wrist_3_joint", "wrist_2_link", "wrist_3_link", (0, 0, 0.1157), axis=(0, 1, 0)),
        Joint("ee_fixed_joint", "wrist_3_link", "ee_link", (0, 0.0922, 0), (0, 0, HALF_PI), axis=None),
        Joint(
            "wrist_3_link-tool0_fixed_joint",
            "wrist_3_link",
            "tool0",
            (0, 0.0922, 0),
            (-HALF_PI, 0, 0),
            axis=None,
        ),
    ]


# The UR10's published link masses (kg) on the links each joint moves, with centres of mass off the origins.
UR10_MASSES = {
    "base_link": (4.0, (0, 0, 0.05)),
    "shoulder_link": (7.1, (0, 0, 0)),
    "upper_arm_link": (12.7, (0, 0, 0.306)),
    "forearm_link": (4.27, (0, 0, 0.28615)),
    "wrist_1_link": (2.0, (0, 0, 0)),
    "wrist_2_link": (2.0, (0, 0, 0)),
    "wrist_3_link": (0.365, (0, 0, 0)),
}


def kr6_joints() -> list[Joint]:
    """A KR 6 R900-like arm as ROS-Industrial lays out KUKA arms: joint 1 400 mm up, the shoulder 25 mm
    forward, the upper arm 455 mm along x, the elbow offset 35 mm up, the forearm 420 mm, the flange 80 mm;
    joints 2, 3 and 5 about y, joints 4 and 6 about x."""
    return [
        Joint("joint_a1", "base_link", "link_1", (0, 0, 0.4), limits=(-2.967, 2.967)),
        Joint("joint_a2", "link_1", "link_2", (0.025, 0, 0), axis=(0, 1, 0), limits=(-3.316, 0.785)),
        Joint("joint_a3", "link_2", "link_3", (0.455, 0, 0), axis=(0, 1, 0), limits=(-2.094, 2.722)),
        Joint("joint_a4", "link_3", "link_4", (0, 0, 0.035), axis=(1, 0, 0), limits=(-3.228, 3.228)),
        Joint("joint_a5", "link_4", "link_5", (0.42, 0, 0), axis=(0, 1, 0), limits=(-2.094, 2.094)),
        Joint("joint_a6", "link_5", "link_6", (0.08, 0, 0), axis=(1, 0, 0), limits=(-6.108, 6.108)),
        Joint("joint_a6-flange", "link_6", "flange", axis=None),
        Joint("flange-tool0", "flange", "tool0", rpy=RPY_FLANGE_ALONG_X, axis=None),
    ]


# Where the FANUC-like arm stands on its `world` link: 400 mm forward, 250 mm to the side, turned 0.3 rad.
LRMATE_WORLD_XYZ = (0.4, -0.25, 0.02)
LRMATE_WORLD_YAW = 0.3


def lrmate_joints() -> list[Joint]:
    """An LR Mate 200iD-like arm (joint 2 50 mm forward of joint 1, upper arm 330 mm up, elbow offset 35 mm,
    forearm 335 mm, flange 80 mm) on a `world` link, in the built-in file's joint zeros and directions."""
    return [
        Joint("world-base_link", "world", "base_link", LRMATE_WORLD_XYZ, (0, 0, LRMATE_WORLD_YAW), axis=None),
        Joint("joint_1", "base_link", "link_1", (0, 0, 0.33), limits=(-2.967, 2.967)),
        Joint("joint_2", "link_1", "link_2", (0.05, 0, 0), axis=(0, 1, 0), limits=(-1.745, 2.531)),
        Joint("joint_3", "link_2", "link_3", (0, 0, 0.33), axis=(0, 1, 0), limits=(-2.792, 3.316)),
        Joint("joint_4", "link_3", "link_4", (0, 0, 0.035), axis=(1, 0, 0), limits=(-3.316, 3.316)),
        Joint("joint_5", "link_4", "link_5", (0.335, 0, 0), axis=(0, 1, 0), limits=(-2.182, 2.182)),
        Joint("joint_6", "link_5", "link_6", (0.08, 0, 0), axis=(1, 0, 0)),
        Joint("joint_6-tool0", "link_6", "tool0", rpy=RPY_FLANGE_ALONG_X, axis=None),
    ]


FAMILIES = {
    "ur10": (ur10_joints, UR10_MASSES),
    "kr6r900": (kr6_joints, None),
    "lrmate200id": (lrmate_joints, None),
}


def family_urdf(robot: str) -> str:
    joints, masses = FAMILIES[robot]
    return urdf_text(f"{robot}_urdf", joints(), masses)
