"""A URScript program compensated: each constant pose target becomes the joints the calibrated model says
put the TCP on it, written back into the program's text in its place.

The program's poses are read in the robot's base frame as the calibrated model places it (`T_tracker_base`).
Each target is solved as a full pose (the TCP's position and the flange's orientation): the SMR point the
model knows stands for the TCP, so a TCP elsewhere on the flange needs the flange's orientation from the
model (three SMR nests or a 6-DoF probe) and is refused without it. Each target's joints lie on the branch
the original program would take: the closed-form solution nearest get_inverse_kin's qnear when the program
gives one, else nearest the previous motion's joints (a joint list resets it). Approach directions
(backlash) follow from the motion order: a first pass gives the joints, the second compensates each target
for the side every joint arrives from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.compensation.model_based import CompensationOptions, CompensationResult, TargetConditions, compensate
from hil.compensation.urscript import JointTarget, PoseTarget, ProgramError, ProgramMotions
from hil.geometry.ik import branches_along_path, default_home, is_ur_like
from hil.geometry.se3 import invert, transform_points
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import approach_signs

TCP_AT_SMR_M = 0.002  # a TCP this close to the model's SMR point is the measured point itself
JOINT_DIGITS = 10  # decimals of the joint lists written into the program (1e-10 rad)


@dataclass(frozen=True)
class ProgramOptions:
    """How a program is compensated: the SMR nest whose point the model knows, loop settings, temperature."""

    smr: int | None = None
    threshold_m: float = 1e-5
    max_iter: int = 10
    temperature_c: float | None = None
    q_start: np.ndarray | None = None  # joints before the program's first motion (default: the IK's home)


@dataclass(frozen=True)
class CompensatedProgram:
    """The rewritten text and, per pose target (text order), its joints and predicted remaining errors."""

    text: str
    targets: list[PoseTarget]
    result: CompensationResult | None  # None: the program has no constant pose target


def orientation_known(model: CalibratedModel) -> bool:
    """True when the model fixes the flange's orientation: three or more SMR nests, or a 6-DoF probe."""
    return bool(model.probes) or len(model.tools) >= 3


def compensate_program(
    model: CalibratedModel, motions: ProgramMotions, options: ProgramOptions = ProgramOptions()
) -> CompensatedProgram:
    """Joints for every constant pose target of `motions` and the program text with them written in."""
    targets = motions.pose_targets
    if not targets:
        return CompensatedProgram("\n".join(motions.lines) + "\n", [], None)
    smr = sorted(model.tools)[0] if options.smr is None else int(options.smr)
    if smr not in model.tools:
        raise ProgramError(f"the model has tool points for SMR nests {sorted(model.tools)}, not {smr}")
    p_flange_smr = np.asarray(model.tools[smr], float)
    _check_tcp(model, targets, p_flange_smr)
    T_base_tcp = np.array([t.T_base_tcp for t in targets])
    T_base_flange = T_base_tcp @ invert(np.array([t.T_flange_tcp for t in targets]))  # each PoseTarget's
    T_target = smr_targets(model, T_base_flange, p_flange_smr)
    seeds = _branch_seeds(model, motions, T_base_flange, options.q_start)
    payload = np.array([t.payload_kg for t in targets])  # finite: a run-time payload is a run-time target
    temperature = None if options.temperature_c is None else np.full(len(targets), options.temperature_c)
    result = _solve(model, T_target, seeds, smr, options, temperature, payload, approach=None)
    if has_backlash(model):  # a target left without joints stands in the order at its seed
        visited = np.where(np.isfinite(result.q), result.q, seeds)
        approach = _approach_in_order(motions, visited, options.q_start)
        result = _solve(model, T_target, result.q, smr, options, temperature, payload, approach)
    return CompensatedProgram(_rewrite(motions, targets, result.q), targets, result)


def smr_targets(model: CalibratedModel, T_base_flange: np.ndarray, p_flange_smr: np.ndarray) -> np.ndarray:
    """What compensation aims at for flange poses (..., 4, 4) in the base frame: the flange's orientation and
    the SMR's point, in the tracker frame the model places the base in."""
    T_tracker_base = np.asarray(model.T_tracker_base, float)
    T_target = T_tracker_base @ T_base_flange
    T_target[..., :3, 3] = transform_points(T_tracker_base, transform_points(T_base_flange, p_flange_smr))
    return T_target


def tcp_off_the_smr(T_flange_tcp: np.ndarray, p_flange_smr: np.ndarray) -> bool:
    """A TCP away from the measured SMR point: reaching it needs the flange's orientation from the model."""
    return bool(np.linalg.norm(np.asarray(T_flange_tcp)[:3, 3] - p_flange_smr) > TCP_AT_SMR_M)


def _solve(
    model: CalibratedModel,
    T_target: np.ndarray,
    q_seed: np.ndarray,
    smr: int,
    options: ProgramOptions,
    temperature_c: np.ndarray | None,
    payload_kg: np.ndarray,
    approach: np.ndarray | None,
) -> CompensationResult:
    """The one call of the pseudo-target loop (one place to adapt when its signature changes)."""
    loop = CompensationOptions(threshold_m=options.threshold_m, max_iter=options.max_iter)
    conditions = TargetConditions(
        smr=smr, temperature_c=temperature_c, approach=approach, payload_kg=payload_kg
    )
    return compensate(model, T_target, loop, q_seed=q_seed, conditions=conditions)


def _check_tcp(model: CalibratedModel, targets: list[PoseTarget], p_flange_smr: np.ndarray) -> None:
    """Refuse a TCP away from the SMR point when the model does not know the flange's orientation."""
    off = [t for t in targets if tcp_off_the_smr(t.T_flange_tcp, p_flange_smr)]
    if off and not orientation_known(model):
        tcp_mm = off[0].T_flange_tcp[:3, 3] * 1e3
        raise ProgramError(
            f"line {off[0].line}: the TCP ({tcp_mm[0]:.1f}, {tcp_mm[1]:.1f}, {tcp_mm[2]:.1f}) mm is not the "
            f"measured SMR point ({', '.join(f'{v * 1e3:.1f}' for v in p_flange_smr)}) mm, and the model "
            "does not know the flange's orientation: calibrate on a campaign with three SMR nests or a "
            "6-DoF probe, or set the program's TCP to the SMR nest"
        )


def _branch_seeds(
    model: CalibratedModel, motions: ProgramMotions, T_base_flange: np.ndarray, q_start: np.ndarray | None
) -> np.ndarray:
    """Per pose target (its flange pose in `T_base_flange`, in order), the closed-form joints nearest its
    qnear, else nearest the previous motion's."""
    kin = model.kinematic
    if not is_ur_like(kin):
        raise ProgramError(f"programs are compensated for UR-shaped arms; {kin.name} is not")
    start = default_home(kin) if q_start is None else np.asarray(q_start, float)
    refs = []
    taught = None  # a joint position moved to since the previous pose target
    for m in motions.motions:
        if isinstance(m, JointTarget):
            taught = m.q
            continue
        ref = m.q_near if m.q_near is not None else taught
        refs.append(np.full(kin.n_joints, np.nan) if ref is None else ref)
        taught = None
    return branches_along_path(kin, T_base_flange, start, np.array(refs))


def _approach_in_order(motions: ProgramMotions, q_pose: np.ndarray, q_start: np.ndarray | None) -> np.ndarray:
    """Approach signs (N, n) of the pose targets from the joints every motion visits, in the program's order,
    from `q_start` when known (else the first motion's approach is unknown: sign 0)."""
    sequence = [] if q_start is None else [np.asarray(q_start, float)]
    rows = []
    k = 0
    for m in motions.motions:
        if isinstance(m, JointTarget):
            sequence.append(m.q)
        else:
            sequence.append(q_pose[k])
            rows.append(len(sequence) - 1)
            k += 1
    return approach_signs(np.array(sequence))[rows]


def payload_unmodelled(model: CalibratedModel, motions: ProgramMotions) -> bool:
    """True when the program carries a payload the model cannot weigh: its gravity yield is not the torque form
    from link masses (or it has none), so the payload's sag is not compensated."""
    loaded = any(t.payload_kg > 0 for t in motions.pose_targets)
    weighed = any(e.family == "gravity_compliance" and "masses_kg" in e.state for e in model.effects)
    return loaded and not weighed


def has_backlash(model: CalibratedModel) -> bool:
    """True when the model holds a backlash effect: the side each joint arrives from moves the arm."""
    return any(e.family == "backlash" for e in model.effects)


def _rewrite(motions: ProgramMotions, targets: list[PoseTarget], q: np.ndarray) -> str:
    """The program's lines with each pose target's argument replaced by its joint list (failed ones kept)."""
    lines = list(motions.lines)
    by_line: dict[int, list[tuple[PoseTarget, np.ndarray]]] = {}
    for t, qk in zip(targets, q, strict=True):
        if np.all(np.isfinite(qk)):
            by_line.setdefault(t.line, []).append((t, qk))
    for number, items in by_line.items():
        line = lines[number - 1]
        for t, qk in sorted(items, key=lambda item: -item[0].span[0]):  # right to left: spans stay valid
            joints = "[" + ", ".join([f"%.{JOINT_DIGITS}f"] * len(qk)) % tuple(qk) + "]"
            line = line[: t.span[0]] + joints + line[t.span[1] :]
        lines[number - 1] = line
    return "\n".join(lines) + "\n"
