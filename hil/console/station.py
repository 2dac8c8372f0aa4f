"""The console's station: one cell, one campaigns folder, at most one run at a time, one controlling browser.

A run is checked as `hil run` checks it (the same parameter messages, the same plan and envelope check,
before anything connects), then driven in a worker thread through the same `open_session` and engine:
pause and resume hold between two points; abort takes the engine's stop path (Ctrl-C's): the point in
flight is recorded, the robot stopped, every recorded point kept, and the same start (here or `hil run`)
resumes. The campaign is held for the run (hil.data.campaign_lock), so a `hil run` on it is refused with
who holds it, and the reverse.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hil.console.live import Answer, Instruments, Live, PageOperator, PageProgress, Phase
from hil.data.campaign_lock import current_holder
from hil.data.store import ARM_TEMPERATURE_KEYS
from hil.errors import SessionSetupError
from hil.instruments.tracker import TrackerState
from hil.runner.cell_config import CellConfig
from hil.runner.engine import CampaignStopped, Engine, StopRequested
from hil.runner.envelope import EnvelopeError
from hil.runner.operator import OperatorAbortError
from hil.runner.plan import Plan
from hil.runner.procedure import ParameterError, Procedure, ProcedureFormError, from_user_values
from hil.runner.registry import UnknownProcedureError, load
from hil.runner.session import Session
from hil.station.instruments import open_session, simulated_operator

CONTROL_LAPSE_S = 30.0  # a controlling page gone this long (no event stream) gives control to the next to ask


class RequestRefusedError(ValueError):
    """A request the console refuses before anything moves; `message` and `remedy` for the page."""

    def __init__(self, message: str, remedy: str = "") -> None:
        super().__init__(message)
        self.message, self.remedy = message, remedy


@dataclass(frozen=True)
class RunRequest:
    """A procedure to run: its name, the campaign file's name in the folder, the parameter values as the page
    sends them (the user's units, by the parameter's SI keyword; text as typed, blank for the default)."""

    procedure: str
    campaign: str
    values: dict[str, Any]


@dataclass(frozen=True)
class CheckedRun:
    """A request checked: its declaration, SI values, campaign path and the plan built once."""

    procedure: Procedure
    values_si: dict[str, Any]
    campaign: Path
    plan: Plan


class Station:
    """The cell and campaigns folder of a console, its live state and its run."""

    def __init__(
        self,
        config: CellConfig,
        campaigns: Path,
        address: str = "",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config, self.campaigns, self.address = config, campaigns, address
        self.live = Live()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._engine: Engine | None = None
        self._stop_reason: str | None = None
        self.controller: str | None = None  # the browser that may press the buttons (its client id)
        self._controller_seen_s = 0.0
        self._clock = clock

    # ------------------------------------------------------------------ control
    def claim(self, client: str) -> bool:
        """Give `client` control when nobody has it, or when the controller's page has been gone for
        CONTROL_LAPSE_S (a closed laptop must not lock the cell out); True when it has control now."""
        with self._lock:
            now = self._clock()
            if self.controller is None or now - self._controller_seen_s > CONTROL_LAPSE_S:
                self.controller = client
            if self.controller == client:
                self._controller_seen_s = now
            return self.controller == client

    def seen(self, client: str | None) -> None:
        """The client's page is still there (its event stream sends), or was until now (its stream closed)."""
        with self._lock:
            if client is not None and client == self.controller:
                self._controller_seen_s = self._clock()

    def controls(self, client: str | None) -> bool:
        return client is not None and client == self.controller

    def controlled_by_another(self, client: str | None) -> bool:
        """Another browser holds control and its page is there (recently)."""
        with self._lock:
            if self.controller is None or client == self.controller:
                return False
            return self._clock() - self._controller_seen_s <= CONTROL_LAPSE_S

    def release(self, client: str) -> None:
        with self._lock:
            if self.controller == client:
                self.controller = None

    # ------------------------------------------------------------------ checks (nothing moves)
    def check(self, request: RunRequest) -> CheckedRun:
        """The request as `hil run` would check it: the procedure, its values (the same messages), the
        campaign name, the plan and the envelope and collision check of every pose."""
        try:
            procedure = load(request.procedure)
            values = from_user_values(procedure, user_values(procedure, request.values))
        except (UnknownProcedureError, ParameterError, ProcedureFormError) as exc:
            raise RequestRefusedError(str(exc), "change the value named; nothing moved") from exc
        campaign = self.campaign_path(request.campaign)
        try:
            plan = procedure.make_plan(self.config, campaign=campaign, **values)
            self.config.envelope.check_poses(
                self.config.nominal,
                plan.joints(),
                self.config.nests_flange_m,
                [p.point_id for p in plan.poses],
            )
        except (ValueError, EnvelopeError) as exc:
            raise RequestRefusedError(
                str(exc), "change the options or the cell config; nothing moved"
            ) from exc
        return CheckedRun(procedure, values, campaign, plan)

    def campaign_path(self, name: str) -> Path:
        """A campaign file in the folder by its name; a path elsewhere is refused."""
        name = name.strip()
        if not name or Path(name).name != name or name.startswith("."):
            raise RequestRefusedError(
                f"campaign {name!r}: give a file name in {self.campaigns}", "e.g. cell-2026-11.sqlite"
            )
        return self.campaigns / name

    # ------------------------------------------------------------------ the run
    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, request: RunRequest) -> CheckedRun:
        """Check the request and start it in the worker thread; refused while a run is on, or while another
        program holds the campaign."""
        checked = self.check(request)
        with self._lock:
            if self.running:
                raise RequestRefusedError("a run is on already", "wait until it ends, or abort it")
            holder = current_holder(checked.campaign)
            if holder is not None:
                raise RequestRefusedError(
                    f"campaign {checked.campaign.name} is driven by {holder.describe()}",
                    "wait until it ends or stop it there; nothing moved",
                )
            self._stop_reason, self._engine = None, None
            self.live.begin(checked.procedure.name, checked.campaign.name)
            self._thread = threading.Thread(
                target=self._run, args=(checked,), name="hil-console-run", daemon=True
            )
            self._thread.start()
        return checked

    def pause(self) -> None:
        engine = self._engine
        if engine is None or self.live.phase is not Phase.RUNNING:
            raise RequestRefusedError("nothing runs to pause")
        engine.request_pause()
        self.live.set_phase(Phase.PAUSED, "pausing: the robot holds before the next point")

    def resume(self) -> None:
        engine = self._engine
        if engine is None or self.live.phase is not Phase.PAUSED:
            raise RequestRefusedError("nothing is paused")
        engine.resume()
        self.live.set_phase(Phase.RUNNING, "running")

    def abort(self, reason: str = "aborted from the console") -> None:
        """The engine's stop path (Ctrl-C's): the point in flight is recorded, the robot stopped."""
        if not self.running:
            raise RequestRefusedError("nothing runs to abort")
        self._stop_reason = reason
        if self._engine is not None:
            self._engine.request_stop(reason)
        self.live.set_phase(Phase.STOPPING, "stopping: the point in flight is recorded, then the robot stops")
        self.live.wake()

    def answer(self, prompt_id: int, answer: Answer) -> None:
        if not self.live.answer(prompt_id, answer):
            raise RequestRefusedError("that prompt is not waiting any more (answered already?)")

    def join(self, timeout_s: float) -> None:
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)

    def _stopped(self) -> str | None:
        return self._stop_reason

    def _run(self, checked: CheckedRun) -> None:
        """The worker thread: open the session as `hil run` does and run the procedure on it."""
        live = self.live
        try:
            control = self.config.simulator_control
            hands = simulated_operator(control) if control else None
            operator = PageOperator(live, self._stopped, hands)
            with ExitStack() as stack:
                session = open_session(
                    self.config, checked.campaign, operator, stack, progress=PageProgress(live),
                    holder=f"hil serve {checked.procedure.name} at {self.address or 'this console'}",
                )  # fmt: skip
                assert isinstance(session.progress, PageProgress)
                session.progress.after_point = lambda: live.read_instruments(read_instruments(session))
                self._engine = session.engine
                if self._stop_reason is not None:
                    session.engine.request_stop(self._stop_reason)
                live.read_instruments(read_instruments(session))
                if self._stop_reason is None:  # an abort while connecting keeps saying it stops
                    live.set_phase(Phase.RUNNING, "running")
                with session:
                    result = checked.procedure(session, planned=checked.plan, **checked.values_si)
            live.set_phase(Phase.FINISHED, checked.procedure.summary(result))
        except StopRequested as exc:
            live.set_phase(
                Phase.STOPPED,
                f"{exc.args[0] if exc.args else 'stopped'}: the robot stopped, every recorded point is kept",
                "start the same procedure on the same campaign to resume (here or with hil run)",
            )
        except SessionSetupError as exc:
            live.set_phase(Phase.STOPPED, exc.message, exc.remedy)
        except CampaignStopped as exc:
            live.set_phase(Phase.STOPPED, exc.message, exc.remedy)
        except OperatorAbortError as exc:
            live.set_phase(Phase.STOPPED, str(exc), "start it again to resume; recorded points are kept")
        except EnvelopeError as exc:
            live.set_phase(Phase.STOPPED, str(exc), "nothing moved")
        except Exception as exc:  # noqa: BLE001 - the page must say why the run ended
            live.set_phase(Phase.FAILED, f"{type(exc).__name__}: {exc}", "see the campaign's log")
        finally:
            self._engine = None
            live.note_instruments(robot_mode="not connected", safety_mode="", tracker="not connected")


def user_values(procedure: Procedure, sent: dict[str, Any]) -> dict[str, Any]:
    """The page's values (text as typed, lists for several values, booleans for switches) in the types the
    command line's parser gives; blank fields are left out (the default). A value that is not a number
    where one is wanted is refused naming the flag, as the command line does."""
    values: dict[str, Any] = {}
    for p in procedure.parameters:
        if p.keyword not in sent:
            continue
        raw = sent[p.keyword]
        if p.type is bool:
            values[p.keyword] = bool(raw)
            continue
        items = raw if isinstance(raw, list) else str(raw).split() if p.count > 1 else [raw]
        items = [str(v).strip() for v in items if str(v).strip() != ""]
        if not items:
            continue
        try:
            converted = [p.type(v) for v in items]
        except ValueError:
            raise ParameterError(
                f"{p.flag}: invalid {p.type.__name__} value: {' '.join(items)!r} (allowed {p.allowed()})"
            ) from None
        if p.count > 1 and len(converted) != p.count:
            raise ParameterError(f"{p.flag} takes {p.count} values, got {len(converted)}")
        values[p.keyword] = tuple(converted) if p.count > 1 else converted[0]
    return values


def read_instruments(session: Session) -> Instruments:
    """The robot's mode, the tracker's state and the last measurement's temperatures, read in the run's
    thread between points (the drivers are the run's: no other thread calls them)."""
    try:
        state = session.robot.state()
        mode, safety = state.robot_mode, state.safety_mode
    except Exception as exc:  # noqa: BLE001 - a reading for the page, never a reason to stop
        mode, safety = f"unreadable ({type(exc).__name__})", ""
    try:
        tracker = _tracker_words(session.tracker.state())
    except Exception as exc:  # noqa: BLE001 - as above
        tracker = f"unreadable ({type(exc).__name__})"
    last = session.store.measurement_columns(("temperature_c", "extra", "timestamp_s")).tail(1)
    air = arm = when = None
    if len(last):
        row = last.iloc[0]
        air = _finite(row["temperature_c"])
        when = _finite(row["timestamp_s"])
        extra = json.loads(row["extra"] or "{}")
        arm = next((_finite(extra[k]) for k in ARM_TEMPERATURE_KEYS if k in extra), None)
    return Instruments(mode, safety, tracker, air, arm, when)


def _tracker_words(state: TrackerState) -> str:
    if not state.connected:
        return "not connected"
    if state.last_error:
        return f"error: {state.last_error}"
    if not state.initialized:
        return "connected, not initialized"
    return "locked on the SMR" if state.target_locked else "connected, no target locked"


def _finite(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None
