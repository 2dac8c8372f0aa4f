"""The operator: a person at the console (Enter to go on, q to stop) or a script; the same steps."""

from __future__ import annotations

import io

import pytest

from hil.runner.operator import ConsoleOperator, OperatorAbortError, OperatorStep, ScriptedOperator

STEP = OperatorStep("Seat SMR 1 in flange hole 3.", "place_smr", smr=1, location="hole3")


def test_console_operator_waits_for_enter_and_stops_on_q():
    out = io.StringIO()
    ConsoleOperator(io.StringIO("\n"), out).perform(STEP)
    assert "Seat SMR 1 in flange hole 3." in out.getvalue() and "press Enter" in out.getvalue()
    with pytest.raises(OperatorAbortError, match="flange hole 3"):
        ConsoleOperator(io.StringIO("q\n"), io.StringIO()).perform(STEP)
    with pytest.raises(OperatorAbortError):  # end of input: nobody there to answer
        ConsoleOperator(io.StringIO(""), io.StringIO()).perform(STEP)


def test_scripted_operator_does_each_action_and_refuses_what_it_cannot():
    done = []
    operator = ScriptedOperator({"place_smr": done.append})
    operator.perform(STEP)
    operator.perform(OperatorStep("Check the cell is clear."))  # a plain confirmation needs no action
    assert done == [STEP] and len(operator.transcript) == 2
    with pytest.raises(OperatorAbortError, match="lock_beam"):
        operator.perform(OperatorStep("Guide the beam onto SMR 1.", "lock_beam", smr=1))
