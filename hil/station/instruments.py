"""Wiring real or simulated instruments into a Session, for every front end (the command line, the console).

Procedures see only the Robot and Tracker protocols; this module opens the robot and tracker driver plug-ins
the cell configuration names (`robot.driver`, `tracker.driver`; by default the UR driver on ur-rtde and the
emScon driver), opens the campaign store and picks the operator: a person at the console, or, on a simulated
cell, a script that moves the simulated SMR through the simulated cell plug-in's control channel.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from hil.data.campaign_lock import CampaignBusyError, Holder
from hil.data.campaigns import campaign_lock, open_campaign
from hil.data.store import Campaign
from hil.errors import SessionSetupError
from hil.instruments.plugins import (
    PluginError,
    RobotDriver,
    TrackerDriver,
    cell_simulator,
    robot_driver,
    tracker_driver,
)
from hil.runner.cell_config import CellConfig
from hil.runner.operator import ConsoleOperator, Operator, OperatorStep, ScriptedOperator
from hil.runner.progress import Progress
from hil.runner.session import Session


def simulated_operator(control_address: str | None) -> ScriptedOperator:
    """An operator whose hands are the simulated cell's control channel (place_smr, tracker.guide_beam),
    at the cell config's [simulator] control address."""
    if not control_address:
        raise ValueError(
            "the simulated operator needs [simulator] control in the cell config (hil sim --write-cell writes it)"
        )

    try:
        control = cell_simulator().connect_control(control_address)
    except PluginError as exc:
        raise SessionSetupError(exc.message, exc.remedy) from exc

    def place_smr(step: OperatorStep) -> None:
        location = step.location or ""
        if location == "face":
            control.call(
                "place_smr", smr_id=step.smr or 1, kind="face", point_m=list(step.face_point_m or (0.0, 0.0))
            )
            return
        kind = location.rstrip("0123456789")
        index = int(location[len(kind) :])
        control.call("place_smr", smr_id=step.smr or 1, kind=kind, index=index)

    def lock_beam(step: OperatorStep) -> None:
        control.call("tracker.guide_beam", smr_id=step.smr or 1)

    return ScriptedOperator(
        {
            "place_smr": place_smr,
            "lock_beam": lock_beam,
            "unmount_tool": lambda step: control.call("unmount_tool"),
            "mount_tool": lambda step: control.call("mount_tool"),
        },
        release=control.close,
    )


def choose_operator(config: CellConfig, kind: str) -> Operator:
    """'console' (a person), 'sim' (the simulated cell's scripted hands) or 'auto' (sim when the cell
    config names a simulator, else the console)."""
    if kind == "auto":
        kind = "sim" if config.simulator_control else "console"
    if kind == "sim":
        return simulated_operator(config.simulator_control)
    if not sys.stdin.isatty():
        raise ValueError(
            "the console operator needs a terminal: run interactively, or use --operator sim on a simulated cell"
        )
    return ConsoleOperator()


def drivers_of(config: CellConfig) -> tuple[RobotDriver, TrackerDriver]:
    """The robot and tracker driver plug-ins the cell configuration names; a missing one is a SessionSetupError
    that names it, before anything connects."""
    try:
        return robot_driver(config.robot_driver_name), tracker_driver(config.tracker_driver_name)
    except PluginError as exc:
        raise SessionSetupError(
            exc.message, f"{exc.remedy} (robot.driver / tracker.driver in {config.source})"
        ) from exc


def _cell_clock(config: CellConfig, stack: ExitStack) -> Callable[[], float] | None:
    """On a simulated cell its own clock (the same seed and commands give the same timestamps), over a
    control channel `stack` closes; else None: the tracker's timestamps, from the host's clock."""
    if not config.simulator_control:
        return None
    try:
        simulator = cell_simulator()
        control = simulator.connect_control(config.simulator_control)
    except PluginError as exc:
        raise SessionSetupError(exc.message, exc.remedy) from exc
    stack.callback(control.close)
    return simulator.clock(control)


def continuing_clock(cell_clock: Callable[[], float], store: Campaign) -> Callable[[], float]:
    """A simulated cell's clock, counted on from the campaign's latest measurement: a cell started again for
    the same campaign (a later stage of the demo, a resume) continues its times from there, so the campaign's
    `t_s` depends on the seed and the commands only, not on how long the machine took between two starts.
    A new campaign starts at the host's time (its `t_s` count from its first measurement)."""
    opened = cell_clock()
    last = store.last_timestamp_s
    base = time.time() if last is None else last
    return lambda: base + (cell_clock() - opened)


def open_session(
    config: CellConfig,
    campaign: str | Path,
    operator: Operator,
    stack: ExitStack,
    progress: bool | Progress | None = None,
    holder: str = "hil run",
    operator_name: str = "",
) -> Session:
    """Take the campaign (one driver at a time: `holder` says who, for the one refused), connect the robot
    and the tracker through their driver plug-ins, open the campaign store, and build the Session.

    The Session's close and the campaign's release are registered on `stack`; a failure half-way leaves
    nothing connected, and the campaign file is created only once both instruments answer (a failed start
    leaves no empty campaign). `progress`: a Progress to report to, or whether to draw one."""
    robots, trackers = drivers_of(config)
    try:
        lock = campaign_lock(campaign, Holder.this_process(holder), password_file=config.store_password_file)
        stack.enter_context(lock)
    except CampaignBusyError as exc:
        raise SessionSetupError(
            str(exc), "wait until it ends or stop it there, then run this again; nothing moved"
        ) from exc
    # the cell's clock first: its channel closes after the session's close, which stamps its last events
    cell_clock = _cell_clock(config, stack)
    with ExitStack() as opening:  # a failure half-way closes what was opened so far
        robot = robots.open(config.robot_mapping())
        opening.callback(robot.close)
        tracker = trackers.open(config.tracker_mapping())
        opening.callback(tracker.close)
        store = open_campaign(campaign, password_file=config.store_password_file)
        opening.callback(store.close)
        station = {
            "robot_controller_version": getattr(robot, "version", None),
            "robot_serial_number": getattr(robot, "serial_number", None),
            "robot_model_reported": getattr(robot, "model_name", None),
            "tracker": getattr(tracker, "tracker_info", {}),
            "cell_name": config.cell_name,
            "operator_name": operator_name or config.operator_name,
        }
        clock = None if cell_clock is None else continuing_clock(cell_clock, store)
        shown = progress if isinstance(progress, Progress) else Progress(enabled=progress)
        session = Session(config, robot, tracker, store, operator, shown, station=station, clock=clock)
        opening.pop_all()  # from here on the Session owns and releases them
    stack.callback(session.close)
    return session
