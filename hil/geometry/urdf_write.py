"""A kinematic model written for other software: a URDF, the UR ROS description's kinematics file, a DH table.

The model's chain regroups exactly into URDF joint origins. Joint i turns the DH frame i-1 by
Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i); a URDF joint turns its child link about the
joint's axis AFTER its fixed origin. With every axis along the link's z, joint i's origin is

    Tx(a_{i-1}) Rx(alpha_{i-1}) Ry(beta_{i-1}) Rz(theta_i) Tz(d_i)

(the previous joint's a, alpha, beta, then this joint's offset and d: Rz and Tz commute with the joint's
own turn), and the flange hangs off the last link by Tx(a_n) Rx(alpha_n) Ry(beta_n) T_last_flange. The
forward kinematics of the file are the model's to rounding.

Two naming conventions:

- `ur`: the Universal Robots ROS description's (`base_link`, `base_link_inertia` turned half a turn about
  z, `shoulder_pan_joint` ... `wrist_3_joint` between `shoulder_link` ... `wrist_3_link`, `flange` with x
  out of the tool flange, `tool0` with z out of it, `base` beside `base_link` as the controller's base).
  The model's base frame is the controller's base (the built-in UR files, and every calibration from them);
  a model read from a UR URDF at `base_link` (theta_1 near half a turn) is placed accordingly.
- `generic`: `base_link` (the model's base frame), `joint_1` ... `joint_n` between `link_1` ... `link_n`,
  `tool0` (the model's flange frame: the frame the tool and the SMR nests are given in).

The UR kinematics file (`kinematics:` with `shoulder`, `upper_arm`, `forearm`, `wrist_1`, `wrist_2`,
`wrist_3`, each `x y z roll pitch yaw`, and a `hash`) is what the UR description reads for the six joint
origins, the format UR's calibration tools extract from a controller; the description fixes `flange` and
`tool0` on `wrist_3_link` itself, so the file can hold a model whose flange is `wrist_3_link`'s frame only.
"""

from __future__ import annotations

import hashlib
import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from hil.geometry.kinematics import KinematicModel
from hil.geometry.se3 import make_transform, rot_x, rot_y, rot_z

UR_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
UR_LINKS = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
UR_KINEMATICS_KEYS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
# The UR description's fixed frames, as rpy: base_link_inertia and base on base_link, flange on wrist_3_link
# (x out of the tool flange), tool0 on flange (back to wrist_3_link's axes: z out of the flange).
HALF_TURN_Z = (0.0, 0.0, math.pi)
UR_FLANGE_ON_WRIST_3 = (0.0, -math.pi / 2, -math.pi / 2)
# Where the flange may differ from wrist_3_link's frame for the UR kinematics file (m, rad).
UR_FLANGE_TOL = 1e-9
# The model's base is the controller's base when theta_1 is within this of 0; base_link's when of pi (rad).
UR_BASE_TOL_RAD = 0.2


class ExportError(ValueError):
    """A model the asked format cannot hold; the message says why and what can be written instead."""


@dataclass(frozen=True)
class Segments:
    """A model regrouped as URDF joint origins: `origins[i]` is joint i+1's origin in its parent link,
    `T_last_flange` the flange in the last link (both 4x4)."""

    origins: tuple[np.ndarray, ...]
    T_last_flange: np.ndarray


def segments(model: KinematicModel, T_base_chain: np.ndarray | None = None) -> Segments:
    """The model's joint origins and flange as the URDF product (module docstring); `T_base_chain`: where
    the chain's base frame sits in the frame the file is written in (the first joint's origin carries it)."""
    n = model.n_joints
    after = [make_transform(np.eye(3), np.zeros(3))]  # Tx(a) Rx(alpha) Ry(beta) of the joint before (none)
    for i in range(n):
        R = rot_x(float(model.alpha[i])) @ rot_y(float(model.beta[i]))
        after.append(make_transform(R, np.array([float(model.a[i]), 0.0, 0.0])))
    origins = tuple(
        after[i] @ make_transform(rot_z(float(model.theta[i])), np.array([0.0, 0.0, float(model.d[i])]))
        for i in range(n)
    )
    if T_base_chain is not None:
        origins = (np.asarray(T_base_chain, float) @ origins[0], *origins[1:])
    return Segments(origins, after[n] @ np.asarray(model.T_last_flange, float))


def ur_base_turn(model: KinematicModel) -> float:
    """The turn about z (0 or pi) from the UR description's base_link_inertia to the model's base frame:
    0 for the controller's base (theta_1 near 0), pi for base_link (a UR URDF read at its root)."""
    t1 = float(model.theta[0])
    for turn in (0.0, math.pi):
        if abs(math.remainder(t1 - turn, 2 * math.pi)) < UR_BASE_TOL_RAD:
            return turn
    raise ExportError(
        f"{model.name}: joint 1's offset is {math.degrees(t1):.1f} deg, neither near 0 (a UR's controller base) "
        "nor near 180 (its ROS base_link); the UR conventions cannot place this base frame: write "
        "--urdf with the generic names"
    )


def is_ur(model: KinematicModel) -> bool:
    """A Universal Robots arm by name: the built-in UR files and models calibrated from them."""
    return model.n_joints == 6 and model.name.lower().startswith("ur")


def urdf_text(model: KinematicModel, names: str = "generic", T_base_chain: np.ndarray | None = None) -> str:
    """The model as a URDF (names `ur` or `generic`, module docstring), its base frame `base_link` (`ur`:
    `base`) with the chain's base at `T_base_chain` in it: kinematics and limits only."""
    seg = segments(model, T_base_chain)
    lines = [
        '<?xml version="1.0"?>',
        f"<!-- {model.name}: written by hil model export -->",
        f'<robot name="{model.name}">',
    ]
    fixed: list[tuple[str, str, str, np.ndarray]] = []  # (joint, parent, child, origin)
    origins = list(seg.origins)
    links: tuple[str, ...]
    joints: tuple[str, ...]
    if names == "ur":
        turn = ur_base_turn(model)
        root, links, joints, first_parent = "base_link", UR_LINKS, UR_JOINTS, "base_link_inertia"
        inertia = _rpy_transform(HALF_TURN_Z)
        fixed.append(("base_link-base_link_inertia", "base_link", "base_link_inertia", inertia))
        fixed.append(("base_link-base_fixed_joint", "base_link", "base", _rpy_transform(HALF_TURN_Z)))
        origins[0] = make_transform(rot_z(-turn), np.zeros(3)) @ origins[0]  # in base_link_inertia
        flange = _rpy_transform(UR_FLANGE_ON_WRIST_3)
        fixed.append(("wrist_3-flange", UR_LINKS[-1], "flange", seg.T_last_flange @ flange))
        fixed.append(("flange-tool0", "flange", "tool0", np.linalg.inv(flange)))
    elif names == "generic":
        n = model.n_joints
        root, first_parent = "base_link", "base_link"
        links = tuple(f"link_{i}" for i in range(1, n + 1))
        joints = tuple(f"joint_{i}" for i in range(1, n + 1))
        fixed.append((f"link_{n}-tool0", links[-1], "tool0", seg.T_last_flange))
    else:
        raise ValueError(f"unknown names {names!r}; use 'ur' or 'generic'")
    all_links = [
        root,
        *(c for _, p, c, _ in fixed if p == root),
        *links,
        *(c for _, p, c, _ in fixed if p != root),
    ]
    lines += [f'  <link name="{name}"/>' for name in all_links]
    for k, (joint, origin) in enumerate(zip(joints, origins, strict=True)):
        parent = first_parent if k == 0 else links[k - 1]
        lo, hi = (float(v) for v in model.joint_limits[k])
        lines += [
            f'  <joint name="{joint}" type="revolute">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{links[k]}"/>',
            f"    {_origin(origin)}",
            '    <axis xyz="0 0 1"/>',
            f'    <limit lower="{lo!r}" upper="{hi!r}" effort="0" velocity="0"/>',
            "  </joint>",
        ]
    for joint, parent, child, origin in fixed:
        lines += [
            f'  <joint name="{joint}" type="fixed">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{child}"/>',
            f"    {_origin(origin)}",
            "  </joint>",
        ]
    return "\n".join([*lines, "</robot>", ""])


def ur_kinematics_yaml(model: KinematicModel, T_base_chain: np.ndarray | None = None) -> str:
    """The UR description's kinematics file for a UR model (module docstring; `T_base_chain` as for
    `urdf_text`); refused when the model's flange is not wrist_3_link's frame (the description fixes tool0
    there)."""
    if not is_ur(model):
        raise ExportError(
            f"{model.name}: the UR kinematics file is read by the Universal Robots description only; write "
            "--urdf for this arm"
        )
    seg = segments(model, T_base_chain)
    off = float(np.max(np.abs(seg.T_last_flange - np.eye(4))))
    if off > UR_FLANGE_TOL:
        raise ExportError(
            f"{model.name}: the flange sits {off:.3g} (m or rad) off wrist_3_link's frame, which the UR "
            "description fixes as tool0; write --urdf, which carries it"
        )
    origins = list(seg.origins)
    # The shoulder's origin is given in base_link_inertia (base_link turned half a turn, the controller's base).
    origins[0] = make_transform(rot_z(-ur_base_turn(model)), np.zeros(3)) @ origins[0]
    lines = ["kinematics:"]
    values = []
    for key, T in zip(UR_KINEMATICS_KEYS, origins, strict=True):
        xyz, rpy = T[:3, 3], _rpy(T[:3, :3])
        lines.append(f"  {key}:")
        for name, v in zip(("x", "y", "z", "roll", "pitch", "yaw"), (*xyz, *rpy), strict=True):
            lines.append(f"    {name}: {float(v)!r}")
            values.append(float(v))
    digest = hashlib.sha256(repr(values).encode()).digest()
    lines.append(f"  hash: calib_{int.from_bytes(digest[:8], 'big')}")
    return "\n".join([*lines, ""])


DH_COLUMNS = (
    "joint", "theta_offset_deg", "d_mm", "a_mm", "alpha_deg", "beta_deg", "hayati_beta", "lower_deg", "upper_deg",
)  # fmt: skip


def dh_table_csv(model: KinematicModel) -> str:
    """The model's DH table (standard DH with Hayati's beta, the order of hil.geometry.kinematics), one row
    per joint, mm and degrees."""
    rows = [",".join(DH_COLUMNS)]
    for i in range(model.n_joints):
        values = (
            math.degrees(model.theta[i]),
            model.d[i] * 1e3,
            model.a[i] * 1e3,
            math.degrees(model.alpha[i]),
            math.degrees(model.beta[i]),
        )
        lo, hi = np.degrees(model.joint_limits[i])
        rows.append(
            ",".join(
                [str(i + 1), *(f"{float(v):.9f}" for v in values), str(bool(model.uses_beta[i])).lower()]
            )
            + f",{lo:.6f},{hi:.6f}"
        )
    return "\n".join([*rows, ""])


def _rpy(R: np.ndarray) -> np.ndarray:
    """URDF roll, pitch, yaw (fixed axes x, y, z) of a rotation; at pitch +-90 deg any split of roll and yaw
    that gives the same rotation (scipy's, its gimbal-lock warning silenced)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        rpy = Rotation.from_matrix(R).as_euler("xyz")
    assert np.allclose(Rotation.from_euler("xyz", rpy).as_matrix(), R, atol=1e-12)
    return rpy


def _rpy_transform(rpy: tuple[float, float, float]) -> np.ndarray:
    return make_transform(Rotation.from_euler("xyz", rpy).as_matrix(), np.zeros(3))


def _origin(T: np.ndarray) -> str:
    xyz = " ".join(repr(float(v)) for v in T[:3, 3])
    rpy = " ".join(repr(float(v)) for v in _rpy(T[:3, :3]))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'
