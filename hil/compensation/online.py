"""A robot whose moves to base-frame poses land where they are meant: the driver wrapped with a calibrated model.

A shop-floor script in Python asks for TCP poses in the robot's base frame (as the model places it,
`T_tracker_base`); `CompensatedRobot` turns each into the joints the model says put the TCP there, one
compensation per move, and hands them to the robot as a joint move (or a linear move to the pose the
controller believes those joints give, which ends at the same joints). The branch is the one nearest the
joints the arm stands at now, and the approach direction of every joint (backlash) is the one this move
gives it. A robot whose controller couples its joints (the model keeps its robot file's coupling) is read
and commanded in the controller's joints, converted here, so the script sees kinematic joints nowhere.

It wraps the `Robot` protocol, not a driver: this module imports neither a driver nor ur-rtde, so the core's
layers hold (compensation stands on the model and the instrument protocols). The script that uses it opens
its robot through the driver plug-in the cell names (`hil.instruments.plugins.robot_driver`), as hil's own
commands do: docs/examples/compensated_moves.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil.compensation.model_based import CompensationOptions, CompensationResult, TargetConditions, compensate
from hil.compensation.program import has_backlash, orientation_known, smr_targets, tcp_off_the_smr
from hil.geometry.ik import branches_along_path, is_ur_like
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import invert
from hil.instruments.robot import Robot
from hil.model.calibrated_model import CalibratedModel
from hil.model.coupled_model import model_coupling
from hil.model.effects import approach_signs


class CompensationError(ValueError):
    """A pose the model cannot compensate (out of reach, the loop above its threshold): nothing moved."""


@dataclass(frozen=True)
class OnlineOptions:
    """The TCP the script's poses name (flange frame), the loop's threshold, the cell temperature."""

    T_flange_tcp: np.ndarray | None = None  # None: the model's SMR point, flange axes
    threshold_m: float = 1e-5
    temperature_c: float | None = None
    payload_kg: float = 0.0


class CompensatedRobot:
    """`robot` with `move_to(T_base_tcp)`: each pose compensated by `model` before the robot moves."""

    def __init__(self, robot: Robot, model: CalibratedModel, options: OnlineOptions = OnlineOptions()):
        self.robot, self.model, self.options = robot, model, options
        self.smr = sorted(model.tools)[0]
        p_smr = np.asarray(model.tools[self.smr], float)
        if options.T_flange_tcp is None:
            self.T_flange_tcp = np.eye(4)
            self.T_flange_tcp[:3, 3] = p_smr
        else:
            self.T_flange_tcp = np.asarray(options.T_flange_tcp, float)
        if tcp_off_the_smr(self.T_flange_tcp, p_smr) and not orientation_known(model):
            raise CompensationError(
                "the TCP is not the measured SMR point and the model does not know the flange's orientation: "
                "calibrate on a campaign with three SMR nests or a 6-DoF probe, or use the SMR nest as TCP"
            )
        self.last: CompensationResult | None = None
        coupling = model_coupling(model)
        self.coupling = coupling if coupling is not None and coupling.coupled_rows() else None

    def joints_for(self, T_base_tcp: np.ndarray) -> np.ndarray:
        """The compensated kinematic joints (6,) for a TCP pose in the base frame, from where the arm stands now."""
        T_base_flange = np.asarray(T_base_tcp, float) @ invert(self.T_flange_tcp)
        T_target = smr_targets(self.model, T_base_flange, np.asarray(self.model.tools[self.smr], float))
        q_now = self._kinematic(np.asarray(self.robot.joints(), float))
        kin = self.model.kinematic
        # a UR-shaped arm: the closed-form branch nearest the arm's; another arm: the IK from where it stands
        seed = branches_along_path(kin, T_base_flange[None], q_now) if is_ur_like(kin) else q_now[None]
        result = self._compensate(T_target[None], seed, None)
        if has_backlash(self.model) and np.all(np.isfinite(result.q)):
            approach = approach_signs(np.array([q_now, result.q[0]]))[1:]
            result = self._compensate(T_target[None], result.q, approach)
        self.last = result
        if not result.ok[0]:
            raise CompensationError(f"the pose cannot be compensated: {result.status[0]}; nothing moved")
        return np.asarray(result.q[0], float)

    def _kinematic(self, q_controller: np.ndarray) -> np.ndarray:
        """The robot's reading (its controller's joints) as the model's kinematic joints."""
        return q_controller if self.coupling is None else self.coupling.to_kinematic(q_controller[None])[0]

    def _controller(self, q_kinematic: np.ndarray) -> np.ndarray:
        """The model's kinematic joints as the controller takes them."""
        return q_kinematic if self.coupling is None else self.coupling.to_controller(q_kinematic[None])[0]

    def _compensate(
        self, T_target: np.ndarray, q_seed: np.ndarray, approach: np.ndarray | None
    ) -> CompensationResult:
        """The one call of the pseudo-target loop (one place to adapt when its signature changes)."""
        o = self.options
        conditions = TargetConditions(
            smr=self.smr,
            temperature_c=None if o.temperature_c is None else np.array([o.temperature_c]),
            approach=approach,
            payload_kg=np.array([o.payload_kg]),
        )
        return compensate(
            self.model,
            T_target,
            CompensationOptions(threshold_m=o.threshold_m),
            q_seed=q_seed,
            conditions=conditions,
        )

    def move_to(
        self,
        T_base_tcp: np.ndarray,
        speed: float | None = None,
        accel: float | None = None,
        linear: bool = False,
    ) -> np.ndarray:
        """Move so the TCP lands on T_base_tcp (4, 4), base frame, m: a joint move, or with `linear` a straight
        line to the pose the controller believes the compensated joints give. Returns the joints commanded (the controller's, for a robot that couples its joints)."""
        q = self.joints_for(T_base_tcp)
        if linear:
            T_believed = forward_kinematics(self.model.nominal, q[None])[0]
            self.robot.move_linear(T_believed, speed, accel)
            return self._controller(q)
        commanded = self._controller(q)
        self.robot.move_joints(commanded, speed, accel)
        return commanded
