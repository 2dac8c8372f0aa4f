"""The tracker's scale against the links' growth as an open question: raised when the model carries a
temperature-driven growth and no tracker scale over a temperature span that can show either, planned like
any rival (poses measured now, where the two move the SMR differently) and decided by the longer campaign."""

import numpy as np
import pandas as pd
import pytest
from sim_campaigns import grid_joints

from fakes.campaign import simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.analysis.design.plan import propose
from hil.analysis.diagnosis.evidence import DECISIVE_Z
from hil.analysis.diagnosis.pipeline import run_diagnosis
from hil.analysis.diagnosis.questions import MIN_TEMPERATURE_SPAN_K, ThermalRivals, thermal_questions
from hil.model.effects import make_effect
from hil.report.text import question_text

pytestmark = pytest.mark.timeout(240)


def _growth(family: str = "thermal_expansion"):
    eff = make_effect(family)
    eff.state = {"driver": "temperature_c", "reference": 21.0}
    return eff


def test_the_question_needs_a_growth_without_a_tracker_scale_and_a_span():
    df = pd.DataFrame({"temperature_c": np.linspace(20.0, 22.0, 10)})
    (q,) = thermal_questions(df, [_growth()])
    assert isinstance(q, ThermalRivals) and q.plannable and q.span_k == pytest.approx(2.0)
    assert "tracker's scale" in question_text(q)
    assert thermal_questions(df, [_growth(), _growth("tracker_scale")]) == []  # the model has both
    assert thermal_questions(df, []) == []  # no growth in the model: nothing for the scale to hide in
    flat = pd.DataFrame({"temperature_c": np.linspace(20.0, 20.0 + 0.5 * MIN_TEMPERATURE_SPAN_K, 10)})
    assert thermal_questions(flat, [_growth()]) == []  # temperature_not_spanned says it
    assert thermal_questions(df.drop(columns="temperature_c"), [_growth()]) == []


def test_a_short_warm_campaign_leaves_it_open_and_the_loop_decides_it():
    """45 poses over 2 K, the tracker 4 m away reading a fixed air temperature: the growth may hold the
    tracker's stretch (evidence below the threshold); the plan serves the question and the campaign with the
    plan's poses (measured as the hall keeps warming) decides it."""
    cell = SimulatedCell(
        SimCellConfig(
            robot="ur10", seed=0, thermal=True, tracker_air_c=20.0, tracker_distance_m=4.0, warmup_k=15.0
        )
    )
    train = simulate_campaign(cell, grid_joints(cell, step_m=0.2, seed=0))
    assert np.ptp(train["temperature_c"]) > MIN_TEMPERATURE_SPAN_K
    report = run_diagnosis(train, "ur10")
    # the stuck air reading puts the scale in the model, but its prior carries it: the question stays open
    assert report.tracker_air is not None and report.tracker_air["standing"] == "assumed"
    (open_q,) = [q for q in report.undecided if isinstance(q, ThermalRivals)]
    assert open_q.evidence_z is not None and open_q.evidence_z < DECISIVE_Z
    sigma = float(np.sqrt(np.mean(report.noise.sigma_axis_m**2)))
    plan = propose(train, report.model, report.undecided, 100, sigma, seed=0)
    served = [g for g in plan.groups if isinstance(g["question"], ThermalRivals)]
    assert served and served[0]["evidence_z_after"] >= DECISIVE_Z  # the round's rows together decide it
    longer = pd.concat([train, simulate_campaign(cell, plan.q)], ignore_index=True)
    again = run_diagnosis(longer, "ur10", previous_effects=report.effects_added)
    assert not [q for q in again.undecided if isinstance(q, ThermalRivals)]
