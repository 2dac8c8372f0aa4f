"""Nominal robot models from robot definition files (TOML): the built-ins live in hil/geometry/robot_models/
(UR5, UR10, UR5e, UR10e, ABB IRB2600, KUKA KR 6 R900 in standard DH; FANUC LR Mate 200iD and ABB IRB 4600
in modified DH), and any other serial arm is one more such file.

A file holds `name`, `convention` and one `[[joint]]` table per joint, in the units an engineer reads off a
data sheet: `d_mm`, `a_mm`, `alpha_deg`, optional `theta_offset_deg` (0), `hayati_beta` (false) and
`limits_deg` ([-360, 360]). Optional `mass_kg` per joint: the mass of the link that joint moves, from the
maker's dynamics data (Universal Robots publish them; the other makers publish the arm's total mass only, so
their files leave it out). Given, it must be on every joint, positive and at most MAX_LINK_MASS_KG; the model
keeps them (`KinematicModel.link_masses_kg`) and the diagnosis computes each joint's gravity torque from them
(hil.model.effects.gravity_physics).
Optional `expansion_per_k` at the top: the links' coefficient of thermal expansion (their material, e.g.
2.3e-5 for aluminium, 1.2e-5 for steel), between 1e-6 and 5e-5 per K; the thermal term's prior.

`convention = "dh"` (standard Denavit-Hartenberg, the internal form of hil.geometry.kinematics): joint i is
Rz(θ_i) Tz(d_i) Tx(a_i) Rx(α_i) [Ry(β_i)], `hayati_beta` on a joint whose axis is parallel to the next.
`convention = "mdh"` (modified DH after Craig; "modified_dh" and "craig" are the same): row i is
Rx(α_{i-1}) Tx(a_{i-1}) [Ry(β_{i-1})] Rz(θ_i) Tz(d_i), so its `a_mm`, `alpha_deg` describe the link that
ends at axis i, and `hayati_beta` goes on the row between two parallel axes (its α is 0 or 180): the β
tilt about the y axis of the frame where that link's common normal meets axis i.

Conversion at load time, exact. Rx and Tx commute, so Craig's chain regroups as Π Rz(θ_i) Tz(d_i)
Tx(a_i) Rx(α_i) Ry(β_i) with the NEXT row's a, α, β: that is the internal joint i, β included unchanged;
the last joint gets a = α = β = 0 and the flange is frame n in both conventions. Craig's first prefix
Rx(α_0) Tx(a_0) would stand before joint 1, where the model has no fixed transform; it must be zero (base
frame on axis 1, as every maker defines it). Folding it into the identified base T_tracker_base would
keep calibration and the identification Jacobian right but silently move the base frame in which FK,
the safety envelope, gravity and compensated targets are expressed, so a non-zero prefix is refused.

A URDF (`arm.urdf`, or `arm.urdf#tool0` naming its flange link) is read the same way wherever a robot file
is: its chain from the root link to the flange becomes the same model (hil.geometry.urdf_import).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from hil.geometry.body import ArmBody, body_from_dh
from hil.geometry.coupling import JointCoupling, coupling_from_table
from hil.geometry.kinematics import KinematicModel
from hil.geometry.urdf_body import urdf_body
from hil.geometry.urdf_import import import_urdf
from hil.geometry.urdf_read import is_urdf_spec, split_spec

ROBOT_DIR = Path(__file__).with_name("robot_models")
ROBOT_NAMES: tuple[str, ...] = (
    "ur5", "ur10", "ur5e", "ur10e", "irb2600", "kr6r900", "lrmate200id", "irb4600",
)  # fmt: skip
_FILE_KEYS = {"name", "convention", "joint", "expansion_per_k", "capsule", "body_radius_mm", "coupling"}
_CAPSULE_KEYS = {"name", "frame", "from_mm", "to_mm", "radius_mm"}
# A body laid along the DH table when a file gives neither capsules nor body_radius_mm: this fraction of the
# arm's summed link lengths as every link's radius (a tenth of a UR10's 1.6 m is 160 mm: generous, so a
# file without figures refuses close poses rather than passing them).
DEFAULT_BODY_RADIUS_FRACTION = 0.1
EXPANSION_RANGE_PER_K = (1e-6, 5e-5)  # plausible materials: from carbon fibre / invar up to plastics
_JOINT_KEYS = {"d_mm", "a_mm", "alpha_deg", "theta_offset_deg", "hayati_beta", "limits_deg", "mass_kg"}
# Accepted spellings of `convention`, each mapped to "dh" or "mdh".
CONVENTIONS: dict[str, str] = {
    "dh": "dh", "standard_dh": "dh", "mdh": "mdh", "modified_dh": "mdh", "craig": "mdh",
}  # fmt: skip
# The heaviest link of the largest industrial arms weighs some hundreds of kg: a figure beyond is in grams or
# the whole arm's mass.
MAX_LINK_MASS_KG = 2000.0
_PARALLEL_TOL_DEG = 1.0  # a Hayati-beta joint's alpha must be within this of 0 or 180 deg


def is_robot_file(name: str) -> bool:
    """Whether `--robot` / `[robot] model` names a file (TOML or URDF) rather than a built-in."""
    return name.lower().endswith(".toml") or is_urdf_spec(name)


def robot_file_path(name: str) -> Path:
    """The file a robot spec names ('arm.urdf#tool0' -> arm.urdf)."""
    return Path(split_spec(name)[0])


def with_file_path(name: str, path: Path) -> str:
    """The spec naming another path to the same file and flange (a cell file's relative path resolved)."""
    flange = split_spec(name)[1]
    return str(path) if flange is None else f"{path}#{flange}"


def get_robot(name: str, use_beta: bool = True) -> KinematicModel:
    """Nominal model by built-in name or robot-definition file path; `use_beta=False` gives plain DH."""
    if is_robot_file(name):
        return load_robot_file(name, use_beta)
    key = name.lower().replace("-", "").replace("_", "").replace(" ", "")
    if key not in ROBOT_NAMES:
        raise ValueError(
            f"unknown robot '{name}'; choose one of {', '.join(ROBOT_NAMES)} or give a robot file (.toml, .urdf)"
        )
    return load_robot_file(ROBOT_DIR / f"{key}.toml", use_beta)


def load_robot_file(path: str | Path, use_beta: bool = True) -> KinematicModel:
    """Read and check a robot definition file (raises ValueError naming the file, the key and what to fix);
    a URDF's path may end in '#flange_link'."""
    source = str(path)
    path = robot_file_path(source)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError(f"robot file not found: {path}; check the path") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a valid TOML robot file ({exc}); fix its syntax") from None
    return robot_from_text(text, source, use_beta)


def robot_from_text(text: str, source: str | Path, use_beta: bool = True) -> KinematicModel:
    """A robot definition file's text, checked and read (e.g. the copy a campaign keeps); `source` names it
    in errors and gives the model's name when the text has none. A URDF (`source` ending in .urdf, or
    .urdf#flange_link) is converted (hil.geometry.urdf_import)."""
    if is_urdf_spec(str(source)):
        return _urdf_model(text, str(source), use_beta)
    path = Path(source)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not a valid TOML robot file ({exc}); fix its syntax") from None
    unknown = set(data) - _FILE_KEYS
    if unknown:
        raise ValueError(
            f"{path}: unknown key(s) {sorted(unknown)} at the top; keys are {', '.join(sorted(_FILE_KEYS))} "
            "(each joint's data goes in a [[joint]] table)"
        )
    convention = _convention(path, data.get("convention", "dh"))
    joints = data.get("joint")
    if not isinstance(joints, list) or not joints:
        raise ValueError(f"{path}: no [[joint]] tables; give one per joint (d_mm, a_mm, alpha_deg ...)")
    rows = [_joint_row(path, i, j, convention) for i, j in enumerate(joints, start=1)]
    theta, d, a, alpha, beta, limits = (list(col) for col in zip(*rows, strict=True))
    if convention == "mdh":
        a, alpha, beta = _craig_to_internal(path, a, alpha, beta)
    if "coupling" in data:  # checked with the rest of the file; read by robot_coupling
        coupling_from_table(data["coupling"], len(rows), str(path))
    return KinematicModel(
        name=str(data.get("name", path.stem)),
        theta=np.deg2rad(theta),
        d=np.array(d) / 1000.0,
        a=np.array(a) / 1000.0,
        alpha=np.deg2rad(alpha),
        beta=np.zeros(len(rows)),
        uses_beta=np.array(beta, bool) if use_beta else np.zeros(len(rows), bool),
        joint_limits=np.deg2rad(np.array(limits, float)),
        expansion_per_k=_expansion(path, data["expansion_per_k"]) if "expansion_per_k" in data else None,
        link_masses_kg=_link_masses(path, joints),
    )


def _urdf_model(text: str, source: str, use_beta: bool) -> KinematicModel:
    """A URDF's model, its link masses held to the robot files' bound."""
    model = import_urdf(text, source, use_beta).model
    heavy = [i for i, m in enumerate(model.link_masses_kg or (), start=1) if m > MAX_LINK_MASS_KG]
    if heavy:
        raise ValueError(
            f"{source}: joint(s) {heavy} move more than {MAX_LINK_MASS_KG:g} kg in the URDF's <inertial> "
            "masses; give them in kg (the links of an arm, not the whole machine)"
        )
    return model


def _link_masses(path: Path, joints: list[dict]) -> tuple[float, ...] | None:
    """Every joint's `mass_kg` (each checked by `_joint_row`), or None when the file gives none; a file that
    gives it on some joints only is refused (a torque from a partial table would be wrong, not smaller)."""
    given = [i for i, j in enumerate(joints, start=1) if "mass_kg" in j]
    if not given:
        return None
    if len(given) != len(joints):
        missing = [i for i in range(1, len(joints) + 1) if i not in given]
        raise ValueError(
            f"{path}: mass_kg is given on joint(s) {given} but not on {missing}; give every joint's link mass "
            "(kg, the maker's dynamics data) or none"
        )
    return tuple(float(j["mass_kg"]) for j in joints)


def _expansion(path: Path, value: Any) -> float:
    """The file's `expansion_per_k`, checked against EXPANSION_RANGE_PER_K."""
    alpha = _number(str(path), "expansion_per_k", value)
    lo, hi = EXPANSION_RANGE_PER_K
    if not lo <= alpha <= hi:
        raise ValueError(
            f"{path}: expansion_per_k = {alpha:g} is outside {lo:g}..{hi:g} per K; give the links' material "
            "coefficient per kelvin (2.3e-5 for aluminium, 1.2e-5 for steel), not ppm or per degree F"
        )
    return alpha


def _convention(path: Path, value: Any) -> str:
    """The file's convention as "dh" or "mdh"; any other spelling is named with the accepted ones."""
    key = value.strip().lower().replace("-", "_").replace(" ", "_") if isinstance(value, str) else None
    if key not in CONVENTIONS:
        raise ValueError(
            f"{path}: convention {value!r} is not supported; write convention = one of "
            f"{', '.join(repr(c) for c in CONVENTIONS)} (standard DH, or modified DH after Craig)"
        )
    return CONVENTIONS[key]


def _joint_row(path: Path, i: int, j: Any, convention: str) -> tuple:
    """One [[joint]] table checked: (theta_offset_deg, d_mm, a_mm, alpha_deg, hayati_beta, limits_deg)."""
    where = f"{path}: joint {i}"
    if not isinstance(j, dict):
        raise ValueError(f"{where}: not a table; write each joint as a [[joint]] table")
    unknown = set(j) - _JOINT_KEYS
    missing = {"d_mm", "a_mm", "alpha_deg"} - set(j)
    if unknown or missing:
        what = f"unknown key(s) {sorted(unknown)}" if unknown else f"missing {sorted(missing)}"
        raise ValueError(f"{where}: {what}; keys are {', '.join(sorted(_JOINT_KEYS))}")
    values = {k: _number(where, k, j[k]) for k in ("d_mm", "a_mm", "alpha_deg", "theta_offset_deg") if k in j}
    if "mass_kg" in j and not 0 < _number(where, "mass_kg", j["mass_kg"]) <= MAX_LINK_MASS_KG:
        raise ValueError(
            f"{where}: mass_kg = {j['mass_kg']:g} is outside 0..{MAX_LINK_MASS_KG:g}; give the mass in kg of the "
            "link this joint moves (not grams, not the whole arm), or leave it out on every joint if unknown"
        )
    beta = j.get("hayati_beta", False)
    if not isinstance(beta, bool):
        raise ValueError(f"{where}: hayati_beta must be true or false, got {beta!r}")
    limits = j.get("limits_deg", [-360.0, 360.0])
    if not isinstance(limits, list) or len(limits) != 2:
        raise ValueError(f"{where}: limits_deg must be [lower, upper] in degrees, got {limits!r}")
    lo, hi = (_number(where, "limits_deg", v) for v in limits)
    if not lo < hi:
        raise ValueError(f"{where}: limits_deg must be [lower, upper] with lower < upper")
    if beta:
        if convention == "mdh" and i == 1:
            raise ValueError(
                f"{where}: hayati_beta on the first row of a modified-DH table; in Craig's table put it on "
                "the row whose a_mm/alpha_deg join two parallel axes (axis i-1 and axis i)"
            )
        off = abs(math.remainder(values["alpha_deg"], 180.0))
        if off > _PARALLEL_TOL_DEG:
            between = "axes i-1 and i" if convention == "mdh" else "axes i and i+1"
            raise ValueError(
                f"{where}: hayati_beta = true but alpha_deg = {values['alpha_deg']:g}: beta is for parallel "
                f"{between} (alpha_deg 0 or 180); set hayati_beta = false or fix alpha_deg"
            )
    return (
        values.get("theta_offset_deg", 0.0),
        values["d_mm"],
        values["a_mm"],
        values["alpha_deg"],
        beta,
        [lo, hi],
    )


def _number(where: str, key: str, value: Any) -> float:
    """A finite number from the file, or an error naming the key."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _craig_to_internal(
    path: Path, a: list[float], alpha: list[float], beta: list[bool]
) -> tuple[list[float], list[float], list[bool]]:
    """Craig rows (a_{i-1}, alpha_{i-1}, beta_{i-1} on row i) -> internal joints (a_i, alpha_i, beta_i): shift
    by one row; the last joint gets 0. Craig's (a_0, alpha_0) must be 0 (see the module docstring)."""
    if a[0] != 0.0 or alpha[0] != 0.0:
        raise ValueError(
            f"{path}: joint 1: a_mm = {a[0]:g}, alpha_deg = {alpha[0]:g}; in a modified-DH table the first "
            "row's a_mm and alpha_deg (Craig's a_0, alpha_0) must be 0: put the base frame on joint 1's "
            "axis with z along it (its height goes in joint 1's d_mm); a tilted or offset mounting is "
            "the cell's base pose, which calibration identifies"
        )
    return a[1:] + [0.0], alpha[1:] + [0.0], beta[1:] + [False]


def robot_coupling(name: str, text: str | None = None) -> JointCoupling | None:
    """The joint coupling a built-in robot (by name) or a robot file (its path, or its `text`) declares in
    `[coupling]` (hil.geometry.coupling), None when its controller reports the kinematic joints (and for a URDF,
    which has no such table: its mimic joints are refused)."""
    if is_urdf_spec(name):
        return None
    if text is None:
        text = _robot_path(name).read_text()
    model = robot_from_text(text, name)
    table = tomllib.loads(text).get("coupling")
    return None if table is None else coupling_from_table(table, model.n_joints, name)


def _robot_path(name: str) -> Path:
    """A robot file's path, or the built-in file of a robot name."""
    if is_robot_file(name):
        return robot_file_path(name)
    return ROBOT_DIR / f"{name.lower().replace('-', '').replace('_', '').replace(' ', '')}.toml"


def robot_body(name: str, text: str | None = None) -> ArmBody:
    """The body of a built-in robot (by name) or of a robot file's text (`name` its path): its
    `[[capsule]]` tables (each: `frame` 0..n, `from_mm`, `to_mm` in that link frame, `radius_mm`, `name`),
    else a body along its DH table of `body_radius_mm`, else of DEFAULT_BODY_RADIUS_FRACTION of its size."""
    if text is None:
        path = _robot_path(name)
        text = path.read_text()
    else:
        path = Path(name)
    if is_urdf_spec(name):
        robot_from_text(text, name)  # the URDF's checks as a robot file's (link masses)
        imported = import_urdf(text, name)
        model = imported.model
        radius_m = DEFAULT_BODY_RADIUS_FRACTION * float(np.sum(np.abs(model.a)) + np.sum(np.abs(model.d)))
        return urdf_body(imported, radius_m, split_spec(name)[0])
    model = robot_from_text(text, path)
    data = tomllib.loads(text)
    capsules = data.get("capsule")
    if capsules is None:
        if "body_radius_mm" in data:
            radius_mm = _number(str(path), "body_radius_mm", data["body_radius_mm"])
            if not 5.0 <= radius_mm <= 1000.0:
                raise ValueError(f"{path}: body_radius_mm = {radius_mm:g} is outside 5..1000 mm")
            return body_from_dh(model, radius_mm / 1e3, f"links along the DH table, {radius_mm:g} mm radius")
        size_m = float(np.sum(np.abs(model.a)) + np.sum(np.abs(model.d)))
        radius_m = DEFAULT_BODY_RADIUS_FRACTION * size_m
        return body_from_dh(
            model,
            radius_m,
            f"links along the DH table, {radius_m * 1e3:.0f} mm radius (the file gives no body: "
            "add [[capsule]] tables from the maker's drawing)",
        )
    if not isinstance(capsules, list) or not capsules:
        raise ValueError(f"{path}: capsule must be [[capsule]] tables")
    rows = [_capsule_row(path, k, c, model.n_joints) for k, c in enumerate(capsules, start=1)]
    names, frames, ends_a, ends_b, radii = zip(*rows, strict=True)
    return ArmBody(
        tuple(names),
        np.array(frames, int),
        np.array(ends_a) / 1e3,
        np.array(ends_b) / 1e3,
        np.array(radii) / 1e3,
        "capsules of the robot file",
    )


def _capsule_row(path: Path, k: int, c: Any, n: int) -> tuple:
    """One [[capsule]] table checked: (name, frame, from_mm, to_mm, radius_mm)."""
    where = f"{path}: capsule {k}"
    if (
        not isinstance(c, dict)
        or set(c) - _CAPSULE_KEYS
        or {"frame", "from_mm", "to_mm", "radius_mm"} - set(c)
    ):
        raise ValueError(f"{where}: keys are {', '.join(sorted(_CAPSULE_KEYS))} (name optional)")
    frame = c["frame"]
    if isinstance(frame, bool) or not isinstance(frame, int) or not 0 <= frame <= n:
        raise ValueError(f"{where}: frame must be a link number 0..{n} (0 the base), got {frame!r}")
    ends = []
    for key in ("from_mm", "to_mm"):
        value = c[key]
        if not isinstance(value, list) or len(value) != 3:
            raise ValueError(f"{where}: {key} must be [x, y, z] in mm in link frame {frame}")
        ends.append([_number(where, key, v) for v in value])
    radius = _number(where, "radius_mm", c["radius_mm"])
    if not 1.0 <= radius <= 1000.0:
        raise ValueError(f"{where}: radius_mm = {radius:g} is outside 1..1000 mm")
    return str(c.get("name", f"capsule {k}")), frame, ends[0], ends[1], radius


def robot_arg(text: str) -> str:
    """argparse type of `--robot`: a built-in name or an existing robot file, checked before any work."""
    import argparse

    try:
        get_robot(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if is_urdf_spec(text):  # what the conversion decided for the user (a moved base frame, masses left out)
        import sys

        for note in import_urdf(robot_file_path(text).read_text(), text).notes:
            print(f"note: {text}: {note}", file=sys.stderr)
    return text
