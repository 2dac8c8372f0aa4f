"""The robot's edge for a controller that couples its joints (hil.geometry.coupling): the one place the runner
converts between the kinematic joints it plans in and the joints the controller takes and reports.

Inside the runner everything is kinematic: planners, the envelope and collision checks, inverse kinematics,
the procedures, the records they read back. The session wraps its robot driver (`ControllerJointsRobot`:
every joint target converted to the controller's before it is sent, every reading converted back) and its
campaign store (`ControllerJointsCampaign`: measurements written with the controller's joints, as issue 34
asks, datasets stay in the maker's joints, and read back kinematic), so no procedure knows the convention.
The campaign's snapshot says "controller"; the analysis commands read it with that convention.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hil.data.store import (
    MEASUREMENT_COLUMNS,
    Q_COLUMNS,
    Q_TARGET_COLUMNS,
    Campaign,
    MeasurementRecord,
    record_from_row,
    with_record_objects,
)
from hil.geometry.coupling import JointConvention, JointCoupling
from hil.instruments.robot import Robot, RobotState


def kinematic_robot(driver: Robot, coupling: JointCoupling | None) -> Robot:
    """The robot driver as the runner sees it: in kinematic joints (the driver itself when nothing couples)."""
    return driver if coupling is None else ControllerJointsRobot(driver, coupling)


def kinematic_campaign(store: Campaign, coupling: JointCoupling | None) -> Campaign:
    """A campaign as the runner sees it: its joints kinematic (the store itself when nothing couples). A
    procedure that opens its campaign outside a session (a dry run planning from what was measured) reads it
    through this, as the session does."""
    return store if coupling is None else ControllerJointsCampaign(store, coupling)


class ControllerJointsRobot:
    """A robot driver seen in kinematic joints: `move_joints` sends the controller's joints of its target,
    `joints` reports the controller's reading as kinematic joints. Cartesian moves and poses pass unchanged
    (the controller's own kinematics places the flange); optional readings (`temperature_c`) pass through."""

    def __init__(self, driver: Robot, coupling: JointCoupling):
        self.driver = driver
        self.coupling = coupling

    def move_joints(self, q: np.ndarray, speed: float | None = None, accel: float | None = None) -> None:
        self.driver.move_joints(self.coupling.to_controller(np.asarray(q, float)[None])[0], speed, accel)

    def joints(self) -> np.ndarray:
        return self.coupling.to_kinematic(np.asarray(self.driver.joints(), float)[None])[0]

    def move_linear(
        self, T_base_flange: np.ndarray, speed: float | None = None, accel: float | None = None
    ) -> None:
        self.driver.move_linear(T_base_flange, speed, accel)

    def move_path(
        self, T_base_flange: np.ndarray, speed: float | None = None, accel: float | None = None
    ) -> None:
        self.driver.move_path(T_base_flange, speed, accel)

    def flange_pose(self) -> np.ndarray:
        return self.driver.flange_pose()

    def wait_settled(self, dwell_s: float | None = None, timeout_s: float | None = None) -> None:
        self.driver.wait_settled(dwell_s, timeout_s)

    def stop(self) -> None:
        self.driver.stop()

    def state(self) -> RobotState:
        return self.driver.state()

    def recover(self) -> None:
        self.driver.recover()

    def close(self) -> None:
        self.driver.close()

    def __getattr__(self, name: str) -> Any:
        """What the Robot protocol leaves optional (a driver's `temperature_c`, ...), from the driver."""
        return getattr(self.driver, name)


class ControllerJointsCampaign:
    """A campaign store seen in kinematic joints: a measurement is written with the controller's joints (its
    commanded and its reported joints) and every read gives them back kinematic; the snapshots it hands back
    say so (`joint_convention` "kinematic"), so a dataset built from this view is not converted twice. The
    file keeps what was written: the controller's joints, its snapshot saying "controller"."""

    def __init__(self, store: Campaign, coupling: JointCoupling):
        self.store = store
        self.coupling = coupling

    @property
    def path(self) -> str | Path:
        return self.store.path

    def record_measurement(self, m: MeasurementRecord) -> int:
        to_controller = self.coupling.to_controller
        return self.store.record_measurement(
            dataclasses.replace(
                m,
                q_target_rad=to_controller(np.asarray(m.q_target_rad, float)[None])[0],
                q_rad=to_controller(np.asarray(m.q_rad, float)[None])[0],
            )
        )

    def measurement_columns(
        self, columns: Sequence[str], procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame:
        """The stored columns, joints converted to kinematic; the joint columns are read whole (a joint set
        converts together) and only those asked for are returned."""
        joint_sets = [cols for cols in (Q_TARGET_COLUMNS, Q_COLUMNS) if set(cols) & set(columns)]
        needed = list(dict.fromkeys([*columns, *(c for cols in joint_sets for c in cols)]))
        df = self.store.measurement_columns(needed, procedure, step)
        for cols in joint_sets:
            df[list(cols)] = self.coupling.to_kinematic(df[list(cols)].to_numpy(float))
        return df[["id", *columns]]

    def measurements(
        self, procedure: str | None = None, step: str | Sequence[str] | None = None
    ) -> pd.DataFrame:
        return with_record_objects(self.measurement_columns(MEASUREMENT_COLUMNS, procedure, step))

    def records(self, procedure: str | None = None, step: str | None = None) -> list[MeasurementRecord]:
        return [record_from_row(row) for row in self.measurements(procedure, step).to_dict("records")]

    def snapshots(self) -> list[dict]:
        kinematic = str(JointConvention.KINEMATIC)
        return [
            {**s, "joint_convention": kinematic} if isinstance(s, dict) and "joint_convention" in s else s
            for s in self.store.snapshots()
        ]

    def __enter__(self) -> ControllerJointsCampaign:
        self.store.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.store.__exit__(*exc)

    def __getattr__(self, name: str) -> Any:
        """Everything without joints (events, steps, outcomes, results, the log) from the store as it is."""
        return getattr(self.store, name)
