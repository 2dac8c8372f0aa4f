"""A URDF's collision shapes become the arm's capsules for the collision checks (`--robot arm.urdf`): each
primitive inside the capsule fitted around it in every pose, a link given only as a mesh laid along the DH
table and said so, and a pose that drives one primitive into another refused with both named."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hil.geometry.body import segment_distance
from hil.geometry.collision import CellBodies
from hil.geometry.kinematics import link_frames
from hil.geometry.robots import robot_body
from hil.geometry.se3 import invert
from hil.geometry.urdf_import import import_urdf

# A three-joint arm: a column on a round base, an upper arm and a forearm, a ball on the flange. The column
# is given as a mesh only; the forearm's cylinder lies along its x (turned a quarter about y).
ARM_URDF = """<?xml version="1.0"?>
<robot name="capsule_test_arm">
  <link name="base_link">
    <collision><origin xyz="0 0 0.075"/><geometry><cylinder radius="0.08" length="0.15"/></geometry></collision>
  </link>
  <link name="column">
    <collision><geometry><mesh filename="package://arm/column.stl"/></geometry></collision>
  </link>
  <link name="upper_arm">
    <collision><origin xyz="0.275 0 0"/><geometry><box size="0.45 0.08 0.06"/></geometry></collision>
  </link>
  <link name="forearm">
    <collision>
      <origin xyz="0.2 0 0" rpy="0 1.5707963267948966 0"/>
      <geometry><cylinder radius="0.04" length="0.4"/></geometry>
    </collision>
  </link>
  <link name="tool0">
    <collision><geometry><sphere radius="0.03"/></geometry></collision>
  </link>
  <joint name="j1" type="revolute">
    <parent link="base_link"/><child link="column"/><origin xyz="0 0 0.2"/><axis xyz="0 0 1"/>
    <limit lower="-3.14" upper="3.14" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="revolute">
    <parent link="column"/><child link="upper_arm"/><origin xyz="0 0 0.1"/><axis xyz="0 1 0"/>
    <limit lower="-3.14" upper="3.14" effort="1" velocity="1"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="upper_arm"/><child link="forearm"/><origin xyz="0.5 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-3.14" upper="3.14" effort="1" velocity="1"/>
  </joint>
  <joint name="flange" type="fixed">
    <parent link="forearm"/><child link="tool0"/><origin xyz="0.4 0 0"/>
  </joint>
</robot>
"""
SOURCE = "arm.urdf"


@pytest.fixture(scope="module")
def arm():
    return import_urdf(ARM_URDF, SOURCE), robot_body(SOURCE, ARM_URDF)


def _shape_points(kind: str, size: tuple[float, ...]) -> np.ndarray:
    """Points on a primitive's surface in its own frame: a box's corners, a cylinder's rims, a sphere's poles
    and equator."""
    if kind == "box":
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T
        return 0.5 * signs * np.asarray(size)
    if kind == "cylinder":
        radius, length = size
        turn = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        rim = np.column_stack([radius * np.cos(turn), radius * np.sin(turn), np.zeros(12)])
        return np.vstack([rim + [0, 0, -length / 2], rim + [0, 0, length / 2]])
    radius = size[0]
    return radius * np.vstack([np.eye(3), -np.eye(3)])


def _link_poses_root(imported, q: np.ndarray) -> dict[str, np.ndarray]:
    """Every link's pose in the URDF's root frame at joints q, by the URDF's own chain (not the DH model)."""
    chain = imported.chain
    poses = {name: T for name, T in chain.base_links}
    T = np.eye(4)
    for i, joint in enumerate(chain.joints):
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec(joint.axis * q[i]).as_matrix()
        T = T @ chain.T_before[i] @ turn
        for name, T_child_link in chain.moved_links[i]:
            poses[name] = T @ T_child_link
    return poses


def test_every_primitive_lies_inside_its_capsule_in_every_pose(arm):
    imported, body = arm
    model = imported.model
    q = np.random.default_rng(1).uniform(-np.pi, np.pi, (20, model.n_joints))
    a, b = body.segments(link_frames(model, q))
    T_base_root = invert(imported.T_root_base)
    checked = 0
    for k, qk in enumerate(q):
        poses = _link_poses_root(imported, qk)
        for name, link in imported.chain.links.items():
            for shape in link.collisions:
                if shape.kind == "mesh":
                    continue
                c = body.names.index(f"{name} ({shape.kind})")
                T = T_base_root @ poses[name] @ shape.T_link_shape
                p = _shape_points(shape.kind, shape.size_m) @ T[:3, :3].T + T[:3, 3]
                distance = segment_distance(p, p, a[k, c], b[k, c])
                assert np.all(distance <= body.radius_m[c] + 1e-9), (name, shape.kind)
                # and fitted closely: some point of the primitive's surface lies on the capsule's surface
                assert distance.max() > body.radius_m[c] - 1e-9
                checked += 1
    assert checked == 20 * 4


def test_a_link_given_as_a_mesh_is_laid_along_the_dh_table_and_said_so(arm):
    _, body = arm
    assert "4 capsules around arm.urdf's collision shapes" in body.source
    assert "meshes not read (column)" in body.source and "joint(s) 1 move" in body.source
    column = [name for name, frame in zip(body.names, body.frame, strict=True) if frame == 1]
    assert column and all(name.startswith("link 1") for name in column)


def test_a_pose_that_drives_the_upper_arm_into_the_base_is_refused_naming_both(arm):
    imported, body = arm
    model = imported.model
    bodies = CellBodies(body, margin_m=0.05, self_margin_m=0.01)
    reaching = np.zeros(model.n_joints)  # the upper arm level, the forearm straight on
    down = reaching.copy()
    down[1] = np.pi / 2  # the upper arm pitched down through the base
    assert list(bodies.collides(model, np.stack([reaching, down]))) == [False, True]
    problem = bodies.pose_problems(model, down[None])[0]
    assert problem is not None and "base_link (cylinder) and upper_arm (box) collide" in problem
