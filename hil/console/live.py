"""The console's live state of the run it drives: what the run's thread reports, what every page reads.

The run's thread changes it (progress, a prompt, the instruments' readings, the end); each change counts a
version and tells the listeners (a page's event stream), so every browser, a reloaded one too, sees the
same run. A prompt lives here, not in a page: a browser that disconnects finds it waiting.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from enum import StrEnum

from hil.runner.engine import StopRequested
from hil.runner.operator import Operator, OperatorAbortError, OperatorStep
from hil.runner.progress import Progress


class Phase(StrEnum):
    """Where the console's run stands."""

    IDLE = "idle"  # nothing started since the console started
    STARTING = "starting"  # connecting the instruments
    RUNNING = "running"
    PAUSED = "paused"  # held between two points; the robot stands still
    STOPPING = "stopping"  # an abort asked: the point in flight is recorded, then the robot stops
    FINISHED = "finished"
    STOPPED = "stopped"  # aborted or refused; every recorded point kept, resumable
    FAILED = "failed"


class Answer(StrEnum):
    DONE = "done"
    STOP = "stop"


@dataclass(frozen=True)
class Prompt:
    """A manual step waiting for the operator: its number (answers name it), the instruction, what it means."""

    id: int
    text: str
    action: str
    smr: int | None
    location: str | None
    drawing_svg: str | None = None  # where the step happens, drawn by the procedure (SVG), when it gives one


@dataclass(frozen=True)
class Instruments:
    """The instruments as last read by the run: robot mode and safety, the tracker's state in words, the air
    and arm temperatures at the last measurement (deg C), when the tracker last measured (UNIX s)."""

    robot_mode: str = "not connected"
    safety_mode: str = ""
    tracker: str = "not connected"
    air_c: float | None = None
    arm_c: float | None = None
    tracker_last_s: float | None = None


@dataclass(frozen=True)
class RunView:
    """What a page shows of the run: a snapshot of the live state (JSON as it is)."""

    version: int
    phase: Phase
    procedure: str | None
    campaign: str | None
    task: str
    done: int
    total: int
    eta_s: float | None
    prompt: Prompt | None
    instruments: Instruments
    message: str
    remedy: str
    controller: bool = False  # filled per browser: may this one press the buttons

    def as_json(self) -> dict:
        return asdict(self)


@dataclass
class _Counting:
    """The task being counted: done of total since `started_monotonic_s`, `first_done` done before it."""

    name: str = ""
    done: int = 0
    total: int = 0
    first_done: int = 0
    started_monotonic_s: float = field(default_factory=time.monotonic)

    def eta_s(self) -> float | None:
        elapsed = time.monotonic() - self.started_monotonic_s
        measured = self.done - self.first_done
        if self.total <= 0 or measured <= 0 or elapsed <= 0:
            return None
        return max(self.total - self.done, 0) * elapsed / measured


class Live:
    """The live state; every method is safe from any thread."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._version = 0
        self._phase = Phase.IDLE
        self._procedure: str | None = None
        self._campaign: str | None = None
        self._counting = _Counting()
        self._prompt: Prompt | None = None
        self._answer: Answer | None = None
        self._prompt_ids = itertools.count(1)
        self._instruments = Instruments()
        self._message = ""
        self._remedy = ""
        self._listeners: list[Callable[[], None]] = []

    # ------------------------------------------------------------------ reading
    def view(self) -> RunView:
        with self._changed:
            c = self._counting
            return RunView(
                self._version, self._phase, self._procedure, self._campaign, c.name, c.done, c.total,
                c.eta_s(), self._prompt, self._instruments, self._message, self._remedy,
            )  # fmt: skip

    @property
    def phase(self) -> Phase:
        return self._phase

    def listen(self, on_change: Callable[[], None]) -> Callable[[], None]:
        """Call `on_change` (from the changing thread; it must be quick) after every change; returns the
        call that stops it (a page's event stream wakes its event loop this way, holding no thread)."""
        with self._changed:
            self._listeners.append(on_change)

        def stop() -> None:
            with self._changed:
                self._listeners.remove(on_change)

        return stop

    def _bump(self) -> None:  # under the condition
        self._version += 1
        self._changed.notify_all()
        for on_change in self._listeners:
            on_change()

    # ------------------------------------------------------------------ the run's side
    def begin(self, procedure: str, campaign: str) -> None:
        with self._changed:
            self._phase, self._procedure, self._campaign = Phase.STARTING, procedure, campaign
            self._counting, self._prompt, self._answer = _Counting(), None, None
            self._message, self._remedy = "connecting the robot and the tracker", ""
            self._bump()

    def set_phase(self, phase: Phase, message: str = "", remedy: str = "") -> None:
        with self._changed:
            self._phase, self._message, self._remedy = phase, message, remedy
            if phase in (Phase.FINISHED, Phase.STOPPED, Phase.FAILED):
                self._prompt = None
            self._bump()

    def count(self, name: str, done: int, total: int) -> None:
        with self._changed:
            if name != self._counting.name:
                self._counting = _Counting(name, done, total, first_done=done)
            else:
                self._counting.done, self._counting.total = done, total
            self._bump()

    def read_instruments(self, instruments: Instruments) -> None:
        with self._changed:
            self._instruments = instruments
            self._bump()

    def note_instruments(self, **changes: object) -> None:
        with self._changed:
            self._instruments = replace(self._instruments, **changes)  # type: ignore[arg-type]
            self._bump()

    def ask(self, step: OperatorStep, stopped: Callable[[], str | None]) -> Answer:
        """Show the step and wait for its answer (or a stop: then StopRequested, the way Ctrl-C leaves)."""
        with self._changed:
            self._prompt = Prompt(
                next(self._prompt_ids), step.text, step.action, step.smr, step.location, step.drawing_svg
            )
            self._answer = None
            self._bump()
            self._changed.wait_for(lambda: self._answer is not None or stopped() is not None)
            answer, self._prompt, self._answer = self._answer, None, None
            self._bump()
        why = stopped()
        if why is not None:
            raise StopRequested(why)
        assert answer is not None
        return answer

    # ------------------------------------------------------------------ the page's side
    def answer(self, prompt_id: int, answer: Answer) -> bool:
        """Answer the waiting prompt `prompt_id`; False when it is not the one waiting (already answered)."""
        with self._changed:
            if self._prompt is None or self._prompt.id != prompt_id:
                return False
            self._answer = answer
            self._changed.notify_all()
            return True

    def wake(self) -> None:
        """Let a waiting prompt see a stop, and every page a change it cannot see here (who controls)."""
        with self._changed:
            self._bump()


class PageOperator(Operator):
    """The operator at the page: each manual step is a prompt there; on a simulated cell the simulator's
    hands (`hands`) then do what the person confirmed, as a person would have at a real cell."""

    def __init__(self, live: Live, stopped: Callable[[], str | None], hands: Operator | None = None) -> None:
        self.live, self.stopped, self.hands = live, stopped, hands

    def perform(self, step: OperatorStep) -> None:
        if self.live.ask(step, self.stopped) is Answer.STOP:
            raise OperatorAbortError(f"the operator stopped at: {step.text}")
        if self.hands is not None:
            self.hands.perform(step)

    def close(self) -> None:
        if self.hands is not None:
            self.hands.close()


class PageProgress(Progress):
    """The engine's progress, counted into the live state (and read the instruments after each point)."""

    def __init__(self, live: Live, after_point: Callable[[], None] = lambda: None) -> None:
        super().__init__(enabled=False)
        self.live, self.after_point = live, after_point

    @contextmanager
    def task(self, description: str, total: int, done: int = 0) -> Iterator[Callable[..., None]]:
        counted = [done]
        self.live.count(description, done, total)

        def advance(n: int = 1) -> None:
            counted[0] += n
            self.live.count(description, counted[0], total)
            self.after_point()

        yield advance

    @contextmanager
    def phases(self) -> Iterator[Callable[[str, int, int], None]]:
        def update(phase: str, done: int, total: int) -> None:
            self.live.count(phase, done, total)
            self.after_point()

        yield update
