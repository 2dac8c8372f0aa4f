"""Coupled joints: how a robot controller's joint readings map to the kinematic joints of the model.

Some makers report a joint against another link than the one before it: FANUC's pendant shows J3, the
forearm, against the horizontal, so J3 moves when J2 turns though the elbow does not (the J2/J3 interaction),
and the kinematic elbow angle is a sum of the two readings. A robot file declares this as a linear map,
q_kinematic = M q_controller (`[coupling] kinematic_from_controller`, one row per kinematic joint, one column
per controller reading), and the interaction's limits as linear inequalities on the controller's readings
(`[[coupling.limit]]`: `controller` coefficients of J1..Jn and `range_deg`), which a box on each joint
cannot express. Datasets, campaigns, plans and programs stay in the controller's joints (what the pendant
shows and the controller takes); the analysis works in kinematic joints, so every command converts at its
edge. A dataset of a coupled robot states which convention its joints are in; none is assumed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np

# The coupling matrix must be invertible well enough that commands converted back to the controller keep
# their precision: a condition number beyond this is a typing error, not an arm.
MAX_CONDITION = 1e6


class JointConvention(StrEnum):
    """Which joints a dataset's q columns hold."""

    CONTROLLER = "controller"  # as the robot's controller and pendant report them
    KINEMATIC = "kinematic"  # the model's joints (each the angle of its link against the one before)


@dataclass(frozen=True)
class CouplingLimit:
    """lower <= coefficients . q_controller <= upper (rad): one interaction limit of the controller's joints."""

    coefficients: np.ndarray  # (n,) per controller reading
    lower_rad: float
    upper_rad: float

    def describe(self) -> str:
        """The limit as a maker writes it, e.g. '-70 <= J2 + J3 <= 200 deg'."""
        return (
            f"{math.degrees(self.lower_rad):g} <= {_linear_text(self.coefficients, 'J')} "
            f"<= {math.degrees(self.upper_rad):g} deg"
        )


@dataclass(frozen=True)
class JointCoupling:
    """q_kinematic = kinematic_from_controller @ q_controller, and the controller joints' interaction limits."""

    kinematic_from_controller: np.ndarray  # (n, n)
    limits: tuple[CouplingLimit, ...] = ()

    @property
    def n_joints(self) -> int:
        return len(self.kinematic_from_controller)

    def to_kinematic(self, q_controller: np.ndarray) -> np.ndarray:
        """Kinematic joints (N, n) from the controller's readings (N, n)."""
        return np.asarray(q_controller, float) @ self.kinematic_from_controller.T

    def to_controller(self, q_kinematic: np.ndarray) -> np.ndarray:
        """The controller's joints (N, n) that put the arm at the kinematic joints (N, n)."""
        return np.linalg.solve(self.kinematic_from_controller, np.asarray(q_kinematic, float).T).T

    def within_limits(self, q_controller: np.ndarray, tol_rad: float = 0.0) -> np.ndarray:
        """Bool (N,): whether the controller's joints keep every interaction limit (within `tol_rad`)."""
        q = np.atleast_2d(np.asarray(q_controller, float))
        ok = np.ones(len(q), bool)
        for limit in self.limits:
            v = q @ limit.coefficients
            ok &= (v >= limit.lower_rad - tol_rad) & (v <= limit.upper_rad + tol_rad)
        return ok

    def coupled_rows(self) -> list[int]:
        """The kinematic joints (0-based) that are not simply their own controller reading."""
        eye = np.eye(self.n_joints)
        return [i for i in range(self.n_joints) if not np.allclose(self.kinematic_from_controller[i], eye[i])]

    def describe(self) -> str:
        """The coupled joints in words, e.g. 'kinematic q3 = -J2 - J3'."""
        rows = self.coupled_rows()
        if not rows:
            return "no coupling (the kinematic joints are the controller's readings)"
        return "; ".join(
            f"kinematic q{i + 1} = {_linear_text(self.kinematic_from_controller[i], 'J')}" for i in rows
        )


def _linear_text(coefficients: np.ndarray, name: str) -> str:
    """'-J2 - J3', '0.5 J2 + J3': a linear form of named joints."""
    text = ""
    for k, c in enumerate(np.asarray(coefficients, float)):
        if c == 0:
            continue
        size = "" if abs(c) == 1 else f"{abs(c):g} "
        if not text:
            text = f"{'-' if c < 0 else ''}{size}{name}{k + 1}"
        else:
            text += f" {'-' if c < 0 else '+'} {size}{name}{k + 1}"
    return text or "0"


def coupling_from_table(table: Any, n_joints: int, where: str) -> JointCoupling:
    """A robot file's `[coupling]` table, checked (ValueError naming `where`, the key and what to write)."""
    if not isinstance(table, dict) or set(table) - {"kinematic_from_controller", "limit"}:
        raise ValueError(
            f"{where}: [coupling] holds kinematic_from_controller (a {n_joints}x{n_joints} matrix: row i gives "
            "kinematic joint i from the controller's J1..Jn) and optional [[coupling.limit]] tables"
        )
    matrix = _matrix(table.get("kinematic_from_controller"), n_joints, where)
    limits = table.get("limit", [])
    if not isinstance(limits, list):
        raise ValueError(f"{where}: coupling.limit must be [[coupling.limit]] tables")
    return JointCoupling(matrix, tuple(_limit(lim, n_joints, f"{where}: coupling limit {k}")
                                       for k, lim in enumerate(limits, start=1)))  # fmt: skip


def coupling_table(coupling: JointCoupling) -> dict:
    """The coupling as the `[coupling]` table `coupling_from_table` reads (a calibrated model keeps it in its
    JSON, so the commands that use the model convert as the robot file did)."""
    return {
        "kinematic_from_controller": coupling.kinematic_from_controller.tolist(),
        "limit": [
            {
                "controller": lim.coefficients.tolist(),
                "range_deg": np.rad2deg([lim.lower_rad, lim.upper_rad]).tolist(),
            }
            for lim in coupling.limits
        ],
    }


def _matrix(value: Any, n: int, where: str) -> np.ndarray:
    rows = value if isinstance(value, list) else []
    if len(rows) != n or any(not isinstance(r, list) or len(r) != n for r in rows):
        raise ValueError(
            f"{where}: coupling.kinematic_from_controller must be {n} rows of {n} numbers (row i: kinematic "
            "joint i as a sum of the controller's readings, e.g. FANUC's elbow row [0, -1, -1, 0, 0, 0])"
        )
    if any(isinstance(v, bool) or not isinstance(v, int | float) for r in rows for v in r):
        raise ValueError(f"{where}: coupling.kinematic_from_controller must hold numbers only")
    matrix = np.array(rows, float)
    if not np.all(np.isfinite(matrix)) or np.linalg.cond(matrix) > MAX_CONDITION:
        raise ValueError(
            f"{where}: coupling.kinematic_from_controller is singular: two kinematic joints would be the same "
            "reading; each row must add something the others do not"
        )
    return matrix


def _limit(value: Any, n: int, where: str) -> CouplingLimit:
    if not isinstance(value, dict) or set(value) != {"controller", "range_deg"}:
        raise ValueError(
            f"{where}: give controller (coefficients of J1..J{n}) and range_deg ([lower, upper]), e.g. "
            "controller = [0, 1, 1, 0, 0, 0] and range_deg = [-70, 200] for lower <= J2 + J3 <= upper"
        )
    coefficients, bounds = value["controller"], value["range_deg"]
    numbers = isinstance(coefficients, list) and isinstance(bounds, list)
    numbers = numbers and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in [*coefficients, *bounds]
    )
    if not numbers or len(coefficients) != n or len(bounds) != 2:
        raise ValueError(f"{where}: controller must be {n} numbers and range_deg [lower, upper] in degrees")
    c = np.array(coefficients, float)
    lo, hi = np.deg2rad(np.array(bounds, float))
    if not np.any(c) or not lo < hi:
        raise ValueError(f"{where}: a limit needs a non-zero coefficient and range_deg with lower < upper")
    return CouplingLimit(c, float(lo), float(hi))
