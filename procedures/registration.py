"""Registration: where is the robot's base in the tracker's frame?

Shop-floor instruction: put the SMR in tool nest 1 and guide the tracker's beam onto it. The robot then
visits a dozen poses spread over the working volume, each keeping the SMR facing the tracker, and the
tracker measures the SMR at each. The rigid transform that best maps the nominal tool-point positions
(robot base frame) onto the measured ones (tracker frame) is the registration; poses that do not fit
(a bumped SMR, a wrong lock) are set aside by RANSAC and reported.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from hil.geometry.kinematics import tool_points
from hil.geometry.rigid_fit import RigidFit, ransac_rigid
from hil.geometry.se3 import fit_rigid, transform_points
from hil.runner.cell_config import CellConfig
from hil.runner.clear_joints import plan_clear_joints
from hil.runner.engine import CampaignStopped
from hil.runner.operator import OperatorStep
from hil.runner.plan import NO_SAFE_PATH, Plan, PlannedPose
from hil.runner.planners import Box, facing_poses, workspace_box
from hil.runner.procedure import Parameter, Procedure, Role
from hil.runner.session import Session

NAME = "registration"


@dataclass(frozen=True)
class RegistrationOptions:
    """The declared parameters, SI."""

    poses: int
    nest: int
    inlier_m: float
    seed: int


@dataclass(frozen=True)
class RegistrationResult:
    fit: RigidFit
    poses_measured: int


def plan(config: CellConfig, options: RegistrationOptions) -> Plan:
    """The registration poses: the corners and centre of the working box, then random points in it,
    each with the SMR in `nest` facing the tracker; unreachable, singular or out-of-envelope ones dropped."""
    poses, nest, seed = options.poses, options.nest, options.seed
    if not 1 <= nest <= len(config.nests_flange_m):
        raise ValueError(f"--nest {nest}: the tool has nests 1..{len(config.nests_flange_m)}")
    rng = np.random.default_rng(seed)
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    shrunk = Box(box.centre_m, 0.8 * box.axes_m)
    candidates = np.vstack(
        [
            shrunk.centre_m,
            shrunk.corners(),
            shrunk.centre_m + rng.uniform(-1, 1, (3 * poses, 3)) @ shrunk.axes_m.T,
        ]
    )
    T = facing_poses(candidates, config.p_base_tracker_m, rng, tilt_deg=15.0, roll_deg=60.0)
    joints = plan_clear_joints(
        config.nominal,
        config.envelope,
        T,
        config.nests_flange_m[nest - 1],
        config.nests_flange_m,
        config.q_home_rad,
    )
    place = OperatorStep(f"Put SMR 1 in tool nest {nest}.", "place_smr", smr=1, location=f"nest{nest}")
    lock = OperatorStep("Guide the tracker's beam onto SMR 1 on the tool until it locks.", "lock_beam", smr=1)
    reachable = [
        PlannedPose(f"r{k + 1:02d}", NAME, "poses", qk, f"nest{nest}", setup=(place,), at_pose=(lock,))
        for k, qk in enumerate(joints.q[joints.usable])
    ]
    # the first `poses` of them that a safe move reaches from the one before (or home), in their order
    safe = Plan(NAME, reachable, config, operator_steps=2).without_unsafe_moves()
    chosen = safe.poses[:poses]
    if len(chosen) < 6:
        raise ValueError(
            f"only {len(chosen)} registration poses are reachable inside the envelope by a safe move; widen "
            "[envelope] or check tracker.position_base_mm"
        )
    examined = reachable.index(chosen[-1]) + 1
    dropped = {NO_SAFE_PATH: examined - len(chosen)} if examined > len(chosen) else {}
    steps = [replace(pose, point_id=f"r{k + 1:02d}") for k, pose in enumerate(chosen)]
    return Plan(NAME, steps, config, operator_steps=2, dropped=dropped)


def register(session: Session, options: RegistrationOptions, the_plan: Plan) -> RegistrationResult:
    """Measure the poses with the SMR in its nest, then fit the tracker-to-base transform with RANSAC."""
    p_nest = session.config.nests_flange_m[options.nest - 1]

    def reaim() -> None:
        """Aim where an interim fit of the points so far puts the SMR; ask the operator before there are 4."""
        so_far = session.recorded_points(NAME, "poses")
        if len(so_far.point_id) < 4:
            for step in the_plan.poses[0].at_pose:
                session.ask(step)
            return
        T, _ = fit_rigid(tool_points(session.nominal, so_far.q_rad, p_nest), so_far.p_tracker_m)
        q_now = session.robot.joints()
        session.tracker.point_at(transform_points(T, tool_points(session.nominal, q_now[None], p_nest))[0])

    session.engine.visit(the_plan, aim=False, reaim=reaim)
    records = session.recorded_points(NAME, "poses")
    if len(records.point_id) < 6:
        raise CampaignStopped(
            f"only {len(records.point_id)} registration points recorded",
            "re-run registration to measure the rest",
        )
    p_base = tool_points(session.nominal, records.q_rad, p_nest)
    fit = ransac_rigid(p_base, records.p_tracker_m, inlier_m=options.inlier_m, seed=options.seed)
    session.finish_step(NAME, "fit", fit.as_result(records.point_id))
    session.log.info(
        "registration: %d of %d points fit, RMS %.3f mm, max %.3f mm",
        int(fit.inliers.sum()),
        len(fit.inliers),
        fit.rms_m * 1e3,
        fit.max_m * 1e3,
    )
    return RegistrationResult(fit, len(records.point_id))


def summary(result: RegistrationResult) -> str:
    fit = result.fit
    return (
        f"registration: {int(fit.inliers.sum())} of {len(fit.inliers)} points agree; RMS {fit.rms_m * 1e3:.3f} mm, "
        f"max {fit.max_m * 1e3:.3f} mm (the robot's uncompensated error)"
    )


PROCEDURE = Procedure(
    name=NAME,
    purpose="where is the robot's base in the tracker's frame (SMR in a tool nest, a dozen poses, RANSAC fit)",
    instruction=__doc__ or "",
    parameters=(
        Parameter("poses", "poses to measure (3 fix the transform, the rest check it)", 12, int, minimum=6),
        Parameter("nest", "tool nest holding the SMR", 1, int, minimum=1),
        Parameter("inlier", "RANSAC inlier distance", 3.0, float, unit="mm", minimum=0.01, maximum=100.0),
        Parameter("seed", "seed of the random poses", 0, int, minimum=0),
    ),
    plan=plan,
    body=register,
    steps=("poses", "fit"),
    summary=summary,
    publishes=((Role.REGISTRATION, "fit"),),
    options=RegistrationOptions,
)
