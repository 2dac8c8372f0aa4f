"""Catalogue of nominal robot models: UR5, UR10, UR5e, UR10e (standard DH + beta on joints 2-3)
and ABB IRB2600 (grid paper), with joint limits and the flange convention (flange = last DH frame).
"""

from __future__ import annotations

import numpy as np

from hil.kinematics import KinematicModel

_UR_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])

# (d1, a2, a3, d4, d5, d6) in metres, methods.md section 5.
_UR_DH: dict[str, tuple[float, float, float, float, float, float]] = {
    "ur5": (0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823),
    "ur10": (0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922),
    "ur5e": (0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996),
    "ur10e": (0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655),
}

# UR joints 2, 3, 4 are parallel: the transforms of joints 2 and 3 get Hayati's beta.
_UR_USES_BETA = np.array([False, True, True, False, False, False])


def _ur(name: str, use_beta: bool) -> KinematicModel:
    d1, a2, a3, d4, d5, d6 = _UR_DH[name]
    limit = 2 * np.pi
    return KinematicModel(
        name=name,
        theta=np.zeros(6),
        d=np.array([d1, 0.0, 0.0, d4, d5, d6]),
        a=np.array([0.0, a2, a3, 0.0, 0.0, 0.0]),
        alpha=_UR_ALPHA.copy(),
        beta=np.zeros(6),
        uses_beta=_UR_USES_BETA.copy() if use_beta else np.zeros(6, bool),
        joint_limits=np.tile([-limit, limit], (6, 1)),
    )


def _irb2600(use_beta: bool) -> KinematicModel:
    deg = np.deg2rad
    # (alpha deg, a mm, d mm, theta offset deg) per joint, methods.md section 2d.
    table = np.array(
        [
            [-90, 150, 445, 0],
            [0, 700, 0, -90],
            [-90, 115, 0, 0],
            [90, 0, 795, 0],
            [90, 0, 0, 180],
            [0, 0, 85, 0],
        ],
        dtype=float,
    )
    limits_deg = np.array([[-180, 180], [-95, 155], [-180, 75], [-400, 400], [-120, 120], [-400, 400]])
    return KinematicModel(
        name="irb2600",
        theta=deg(table[:, 3]),
        d=table[:, 2] / 1000.0,
        a=table[:, 1] / 1000.0,
        alpha=deg(table[:, 0]),
        beta=np.zeros(6),
        # Joints 2 and 3 are parallel (alpha2 = 0): beta on joint 2.
        uses_beta=np.array([False, True, False, False, False, False]) if use_beta else np.zeros(6, bool),
        joint_limits=deg(limits_deg.astype(float)),
    )


ROBOT_NAMES: tuple[str, ...] = ("ur5", "ur10", "ur5e", "ur10e", "irb2600")


def get_robot(name: str, use_beta: bool = True) -> KinematicModel:
    """Nominal model by name; `use_beta=False` gives plain standard DH on every joint."""
    key = name.lower().replace("-", "").replace("_", "")
    if key in _UR_DH:
        return _ur(key, use_beta)
    if key == "irb2600":
        return _irb2600(use_beta)
    raise ValueError(f"unknown robot '{name}'; choose one of {', '.join(ROBOT_NAMES)}")
