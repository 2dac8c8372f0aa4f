"""The body of a robot given as a URDF: a capsule fitted around each of its links' collision shapes.

A URDF's `<collision>` elements give each link's shape for collision checks. Each primitive becomes the
smallest capsule of its axis that holds it whole, in the DH frame of the link that carries it (the root
and the links fixed to it: the base, frame 0):

- a cylinder of radius r and length L: the segment of length L along its axis, radius r (the capsule's
  round ends reach r beyond its flat faces);
- a capsule (radius, length of its straight part), as some descriptions give one: itself;
- a sphere: a segment of zero length, its radius;
- a box: the segment along its longest edge, as long as that edge, with the radius half the diagonal of
  the other two (every point of the box lies within it of that segment).

Meshes (`<mesh filename=...>`) are not read: hil reads the XML only. A moving link with no primitive (only
meshes, or no `<collision>` at all) is laid along the DH table like a robot file without `[[capsule]]`
tables (`body_from_dh` at the fallback radius), and the body's `source` says which links are.
"""

from __future__ import annotations

import numpy as np

from hil.geometry.body import ArmBody, body_from_dh
from hil.geometry.kinematics import link_frames
from hil.geometry.se3 import invert
from hil.geometry.urdf_import import ImportedRobot
from hil.geometry.urdf_read import UrdfShape


def shape_capsule(shape: UrdfShape) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The capsule (ends (3,) and (3,) in the shape's frame, radius) holding a primitive; None for a mesh."""
    z = np.array([0.0, 0.0, 1.0])
    if shape.kind in ("cylinder", "capsule"):
        radius, length = shape.size_m
        return -0.5 * length * z, 0.5 * length * z, radius
    if shape.kind == "sphere":
        return np.zeros(3), np.zeros(3), shape.size_m[0]
    if shape.kind == "box":
        size = np.asarray(shape.size_m, float)
        longest = int(np.argmax(size))
        axis = np.eye(3)[longest]
        others = np.delete(size, longest)
        return -0.5 * size[longest] * axis, 0.5 * size[longest] * axis, 0.5 * float(np.hypot(*others))
    return None


def urdf_body(robot: ImportedRobot, fallback_radius_m: float, source: str) -> ArmBody:
    """The arm's capsules from a URDF's collision shapes (see the module docstring); links without a
    primitive along the DH table at `fallback_radius_m`."""
    chain, model = robot.chain, robot.model
    T_root_frame = robot.T_root_base @ link_frames(model, np.zeros((1, model.n_joints)))[0]  # (n+1, 4, 4)
    groups: list[tuple[int, np.ndarray, tuple[tuple[str, np.ndarray], ...]]] = [
        (0, np.eye(4), chain.base_links)
    ]
    T_root_child = np.eye(4)
    for i, group in enumerate(chain.moved_links):
        T_root_child = T_root_child @ chain.T_before[i]  # joint i's child link at the zero pose
        groups.append((i + 1, T_root_child, group))
    names: list[str] = []
    frames: list[int] = []
    ends_a: list[np.ndarray] = []
    ends_b: list[np.ndarray] = []
    radii: list[float] = []
    meshes: list[str] = []
    bare: list[int] = []
    for frame, T_root_first, group in groups:
        T_frame_first = invert(T_root_frame[frame]) @ T_root_first
        found = 0
        for link_name, T_first_link in group:
            for shape in chain.links[link_name].collisions:
                capsule = shape_capsule(shape)
                if capsule is None:
                    meshes.append(link_name)
                    continue
                a, b, radius = capsule
                T = T_frame_first @ T_first_link @ shape.T_link_shape
                names.append(f"{link_name} ({shape.kind})")
                frames.append(frame)
                ends_a.append(T[:3, :3] @ a + T[:3, 3])
                ends_b.append(T[:3, :3] @ b + T[:3, 3])
                radii.append(radius)
                found += 1
        if not found and frame >= 1:
            bare.append(frame)
    along = body_from_dh(model, fallback_radius_m, "")
    for c in np.flatnonzero(np.isin(along.frame, bare)):
        names.append(along.names[c])
        frames.append(int(along.frame[c]))
        ends_a.append(along.a_m[c])
        ends_b.append(along.b_m[c])
        radii.append(float(along.radius_m[c]))
    fitted = len(names) - int(np.isin(along.frame, bare).sum())
    said = [
        f"{fitted} capsules around {source}'s collision shapes" if fitted else f"no primitives in {source}"
    ]
    if meshes:
        said.append(f"meshes not read ({', '.join(sorted(set(meshes)))})")
    if bare:
        joints = ", ".join(str(f) for f in bare)
        said.append(
            f"what joint(s) {joints} move has no primitive: along the DH table, "
            f"{fallback_radius_m * 1e3:.0f} mm radius"
        )
    count = len(names)
    return ArmBody(
        tuple(names),
        np.array(frames, int),
        np.array(ends_a, float).reshape(count, 3),
        np.array(ends_b, float).reshape(count, 3),
        np.array(radii, float),
        "; ".join(said),
    )
