"""Nominal robot models from robot definition files (TOML): the built-ins live in hil/robot_models/
(UR5, UR10, UR5e, UR10e, ABB IRB2600, KUKA KR 6 R900), and any other serial arm is one more such file.

A file holds `name`, `convention = "dh"` and one `[[joint]]` table per joint, in the units an engineer
reads off a data sheet: `d_mm`, `a_mm`, `alpha_deg`, optional `theta_offset_deg` (0), `hayati_beta`
(false; true on a joint whose axis is parallel to the next one) and `limits_deg` ([-360, 360]). Optional
`mass_kg` per joint is accepted (gravity data, for the reader). The flange is the last DH frame.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from hil.kinematics import KinematicModel

ROBOT_DIR = Path(__file__).with_name("robot_models")
ROBOT_NAMES: tuple[str, ...] = ("ur5", "ur10", "ur5e", "ur10e", "irb2600", "kr6r900")
_JOINT_KEYS = {"d_mm", "a_mm", "alpha_deg", "theta_offset_deg", "hayati_beta", "limits_deg", "mass_kg"}


def is_robot_file(name: str) -> bool:
    return name.lower().endswith(".toml")


def get_robot(name: str, use_beta: bool = True) -> KinematicModel:
    """Nominal model by built-in name or robot-definition file path; `use_beta=False` gives plain DH."""
    if is_robot_file(name):
        return load_robot_file(name, use_beta)
    key = name.lower().replace("-", "").replace("_", "").replace(" ", "")
    if key not in ROBOT_NAMES:
        raise ValueError(
            f"unknown robot '{name}'; choose one of {', '.join(ROBOT_NAMES)} or give a robot file (.toml)"
        )
    return load_robot_file(ROBOT_DIR / f"{key}.toml", use_beta)


def load_robot_file(path: str | Path, use_beta: bool = True) -> KinematicModel:
    """Read and check a robot definition file (raises ValueError naming the file and what to fix)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"robot file not found: {path}; check the path") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a valid TOML robot file ({exc}); fix its syntax") from None
    convention = data.get("convention", "dh")
    if convention != "dh":
        raise ValueError(
            f"{path}: convention '{convention}' is not supported; give the standard DH table "
            '(convention = "dh", Hayati beta on parallel joints)'
        )
    joints = data.get("joint")
    if not isinstance(joints, list) or not joints:
        raise ValueError(f"{path}: no [[joint]] tables; give one per joint (d_mm, a_mm, alpha_deg ...)")
    rows = []
    for i, j in enumerate(joints, start=1):
        unknown = set(j) - _JOINT_KEYS
        missing = {"d_mm", "a_mm", "alpha_deg"} - set(j)
        if unknown or missing:
            what = f"unknown key(s) {sorted(unknown)}" if unknown else f"missing {sorted(missing)}"
            raise ValueError(f"{path}: joint {i}: {what}; keys are {', '.join(sorted(_JOINT_KEYS))}")
        limits = j.get("limits_deg", [-360.0, 360.0])
        if len(limits) != 2 or not limits[0] < limits[1]:
            raise ValueError(f"{path}: joint {i}: limits_deg must be [lower, upper] with lower < upper")
        rows.append(
            (
                float(j.get("theta_offset_deg", 0.0)),
                float(j["d_mm"]),
                float(j["a_mm"]),
                float(j["alpha_deg"]),
                bool(j.get("hayati_beta", False)),
                limits,
            )
        )
    theta, d, a, alpha, beta, limits = zip(*rows, strict=True)
    return KinematicModel(
        name=str(data.get("name", path.stem)),
        theta=np.deg2rad(theta),
        d=np.array(d) / 1000.0,
        a=np.array(a) / 1000.0,
        alpha=np.deg2rad(alpha),
        beta=np.zeros(len(rows)),
        uses_beta=np.array(beta, bool) if use_beta else np.zeros(len(rows), bool),
        joint_limits=np.deg2rad(np.array(limits, float)),
    )


def robot_arg(text: str) -> str:
    """argparse type of `--robot`: a built-in name or an existing robot file, checked before any work."""
    import argparse

    try:
        get_robot(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text
