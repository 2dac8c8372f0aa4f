"""The batched candidate screening (one shared factorisation per round) against the per-candidate refit it
replaces: the same candidates pass, the same effects are selected, the held-out scores agree to rounding."""

import numpy as np
import pytest
from calib_data import cell_datasets

from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis
from hil.data.dataset import make_dataset

pytestmark = pytest.mark.timeout(180)


def _rounds(report):
    """Every screened candidate of every round, in order."""
    return [c for step in report.steps for c in step.candidates] + list(report.final_round)


def _same_screening(fast, slow):
    assert fast.effects_added and fast.effects_added == slow.effects_added
    a, b = _rounds(fast), _rounds(slow)
    assert [(c.name, c.joint, c.n_params, c.passed) for c in a] == [
        (c.name, c.joint, c.n_params, c.passed) for c in b
    ]
    for x, y in zip(a, b, strict=True):
        for field in ("gain_mm2", "cv_rms_mm", "geometry_correlation"):
            assert getattr(x, field) == pytest.approx(getattr(y, field), rel=1e-7, abs=1e-12, nan_ok=True)
        for field in ("p_cv", "p_chi2"):  # tiny p-values: compare their logarithms
            assert np.log(max(getattr(x, field), 1e-300)) == pytest.approx(
                np.log(max(getattr(y, field), 1e-300)), rel=1e-6, abs=1e-9
            )
    # the full refits start from linear solutions equal to rounding and stop at their tolerance
    assert [s["rms_mm"] for s in fast.stages] == pytest.approx([s["rms_mm"] for s in slow.stages], rel=1e-6)


def test_batched_screening_selects_what_the_refit_selects_on_the_gravity_cell(gravity_cell_diagnosis):
    _, train, val, fast = gravity_cell_diagnosis  # run_diagnosis's default: batched
    _same_screening(
        fast, run_diagnosis(train, "ur10", df_validate=val, options=DiagnosisOptions(screening="refit"))
    )


def test_batched_screening_selects_what_the_refit_selects_with_backlash_in_the_cell():
    _, train, _ = cell_datasets(seed=3, backlash=True, step_m=0.15)
    fast = run_diagnosis(train, "ur10", options=DiagnosisOptions(screening="batched"))
    _same_screening(fast, run_diagnosis(train, "ur10", options=DiagnosisOptions(screening="refit")))


def test_unknown_screening_is_refused():
    with pytest.raises(ValueError, match="screening"):
        run_diagnosis(
            make_dataset(np.zeros((3, 6)), np.ones((3, 3))),
            "ur10",
            options=DiagnosisOptions(screening="fast"),
        )
