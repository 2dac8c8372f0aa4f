"""Registration: where is the robot's base in the tracker's frame?

Shop-floor instruction: put the SMR in tool nest 1 and guide the tracker's beam onto it. The robot then
visits a dozen poses spread over the working volume, each keeping the SMR facing the tracker, and the
tracker measures the SMR at each. The rigid transform that best maps the nominal tool-point positions
(robot base frame) onto the measured ones (tracker frame) is the registration; poses that do not fit
(a bumped SMR, a wrong lock) are set aside by RANSAC and reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.geometry.kinematics import tool_points
from hil.geometry.rigid_fit import RigidFit, ransac_rigid
from hil.geometry.se3 import fit_rigid, transform_points
from hil.runner.cell_config import CellConfig
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.planners import Box, facing_poses, plan_joints, workspace_box
from hil.runner.session import CampaignStopped, Session

PROCEDURE = "registration"


@dataclass(frozen=True)
class RegistrationResult:
    fit: RigidFit
    poses_measured: int


def plan(config: CellConfig, *, poses: int = 12, nest: int = 1, seed: int = 0) -> Plan:
    """The registration poses: the corners and centre of the working box, then random points in it,
    each with the SMR in `nest` facing the tracker; unreachable, singular or out-of-envelope ones dropped."""
    if poses < 6:
        raise ValueError("registration needs at least 6 poses (--poses): 3 fix the transform, the rest check it")
    if not 1 <= nest <= len(config.nests_flange_m):
        raise ValueError(f"--nest {nest}: the tool has nests 1..{len(config.nests_flange_m)}")
    rng = np.random.default_rng(seed)
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    shrunk = Box(box.centre_m, 0.8 * box.axes_m)
    candidates = np.vstack([shrunk.centre_m, shrunk.corners(), shrunk.centre_m + rng.uniform(-1, 1, (3 * poses, 3)) @ shrunk.axes_m.T])
    T = facing_poses(candidates, config.p_base_tracker_m, rng, tilt_deg=15.0, roll_deg=60.0)
    joints = plan_joints(config.nominal, T, config.nests_flange_m[nest - 1], q_near=config.q_home_rad)
    usable = joints.usable & ~config.envelope.outside(config.nominal, joints.q, config.nests_flange_m)
    q = joints.q[usable][:poses]
    if len(q) < 6:
        raise ValueError(
            f"only {len(q)} registration poses are reachable inside the envelope; widen [envelope] or check "
            "tracker.position_base_mm"
        )
    steps = [PlannedPose(f"r{k + 1:02d}", PROCEDURE, "poses", qk, f"nest{nest}") for k, qk in enumerate(q)]
    return Plan(PROCEDURE, steps, config, operator_steps=2)


def run(session: Session, *, poses: int = 12, nest: int = 1, seed: int = 0, inlier_mm: float = 3.0) -> RegistrationResult:
    """Register the tracker to the robot base (see the module docstring for the shop-floor steps)."""
    the_plan = plan(session.config, poses=poses, nest=nest, seed=seed)
    session.check_poses(np.array([p.q_rad for p in the_plan.poses]), [p.point_id for p in the_plan.poses])
    p_nest = session.config.nests_flange_m[nest - 1]
    pending = [p for p in the_plan.poses if not session.recorded(PROCEDURE, "poses", p.point_id)]
    if pending:
        session.ask(OperatorStep(f"Put SMR 1 in tool nest {nest}.", "place_smr", smr=1, location=f"nest{nest}"))
        session.move_joints(pending[0].q_rad, label=pending[0].point_id)
        session.settle()

        def lock_beam() -> None:
            session.ask(OperatorStep("Guide the tracker's beam onto SMR 1 on the tool until it locks.", "lock_beam", smr=1))

        def reaim() -> None:
            """Aim where an interim fit of the points so far puts the SMR; ask the operator before there are 4."""
            so_far = session.recorded_points(PROCEDURE, "poses")
            if len(so_far.point_id) < 4:
                lock_beam()
                return
            T, _ = fit_rigid(tool_points(session.nominal, so_far.q_rad, p_nest), so_far.p_tracker_m)
            q_now = session.robot.joints()
            session.tracker.point_at(transform_points(T, tool_points(session.nominal, q_now[None], p_nest))[0])

        lock_beam()
        total, done = len(the_plan.poses), len(the_plan.poses) - len(pending)
        with session.progress.task("registration", total=total, done=done) as advance:
            for pose in pending:
                session.measure_point(PROCEDURE, "poses", pose.point_id, pose.q_rad, smr=1, location=f"nest{nest}", reaim=reaim)
                advance()
    records = session.recorded_points(PROCEDURE, "poses")
    if len(records.point_id) < 6:
        raise CampaignStopped(f"only {len(records.point_id)} registration points recorded", "re-run registration to measure the rest")
    p_base = tool_points(session.nominal, records.q_rad, p_nest)
    fit = ransac_rigid(p_base, records.p_tracker_m, inlier_m=inlier_mm / 1e3, seed=seed)
    session.finish_step(PROCEDURE, "fit", fit.as_result(records.point_id))
    session.log.info(
        "registration: %d of %d points fit, RMS %.3f mm, max %.3f mm",
        int(fit.inliers.sum()), len(fit.inliers), fit.rms_m * 1e3, fit.max_m * 1e3,
    )
    return RegistrationResult(fit, len(records.point_id))
