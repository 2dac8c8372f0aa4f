"""The cautions of a diagnosis' verdict, as typed records: one record class per kind of caution, each with the
figures its words need (hil.report.text words them, switching on the record).

A caution is serialised (report.json) as `{"kind": ..., **its fields}`, in the order the fields are declared;
a field that only the program reads (a calibration note's confounded pair) is left out.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, fields
from typing import Any, ClassVar


class CautionKind(enum.StrEnum):
    """What a caution is about (its `kind` in report.json)."""

    CALIBRATION_NOTE = "calibration_note"
    FIRST_CHOICE_SET_ASIDE = "first_choice_set_aside"
    PREVIOUS_EFFECTS_KEPT = "previous_effects_kept"
    STAGE_WORSE_THAN_PREVIOUS = "stage_worse_than_previous"
    AMBIGUOUS_EFFECTS = "ambiguous_effects"
    VALIDATION_UNREPRESENTED = "validation_unrepresented"
    VALIDATION_WORSE_THAN_GEOMETRIC = "validation_worse_than_geometric"
    VALIDATION_TEMPERATURES_OUTSIDE = "validation_temperatures_outside"
    THERMAL_PRIOR_CONTRADICTED = "thermal_prior_contradicted"
    VALIDATION_JOINTS_OUTSIDE = "validation_joints_outside"
    TRACKER_AIR_STUCK = "tracker_air_stuck"


@dataclass(frozen=True, kw_only=True)
class Caution:
    """One caution of the verdict; its class says which (`kind`)."""

    kind: ClassVar[CautionKind]
    unsaid: ClassVar[tuple[str, ...]] = ()  # fields the program reads and report.json does not hold

    def to_dict(self) -> dict[str, Any]:
        """The caution as report.json holds it: its kind, then its fields in declared order."""
        said = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in self.unsaid}
        return {"kind": self.kind.value, **said}


@dataclass(frozen=True, kw_only=True)
class CalibrationNote(Caution):
    """A geometric calibration's note (or the diagnosis' own), in its words; `pair`: the two parameters a
    note on a confounded pair is about (hil.analysis.calibration.solve.CalibrationResult.confounded), None
    for any other note."""

    kind = CautionKind.CALIBRATION_NOTE
    unsaid = ("pair",)
    text: str
    pair: tuple[str, str] | None = None


@dataclass(frozen=True, kw_only=True)
class FirstChoiceSetAside(Caution):
    """The selection's first choice led to a worse final model than a selection without it."""

    kind = CautionKind.FIRST_CHOICE_SET_ASIDE
    effect: dict
    heldout_rms_mm: float
    heldout_rms_without_mm: float


@dataclass(frozen=True, kw_only=True)
class PreviousEffectsKept(Caution):
    """A selection from the earlier diagnosis' effects predicted held-out points better than one that
    dropped some of them, and was kept."""

    kind = CautionKind.PREVIOUS_EFFECTS_KEPT
    effects: list[dict]
    dropped: list[dict]
    heldout_rms_mm: float
    heldout_rms_kept_mm: float
    p_value: float


@dataclass(frozen=True, kw_only=True)
class StageWorseThanPrevious(Caution):
    """A stage predicts held-out points worse than the stage before it."""

    kind = CautionKind.STAGE_WORSE_THAN_PREVIOUS
    stage: str
    rms_mm: float


@dataclass(frozen=True, kw_only=True)
class AmbiguousEffects(Caution):
    """Two effects explain the same residual on this data ({name, joint} each)."""

    kind = CautionKind.AMBIGUOUS_EFFECTS
    chosen: dict
    confounded_with: dict


@dataclass(frozen=True, kw_only=True)
class ValidationUnrepresented(Caution):
    """The validation campaign's error is far above the held-out one: training does not represent it."""

    kind = CautionKind.VALIDATION_UNREPRESENTED
    validate_rms_mm: float
    heldout_rms_mm: float
    reregistered: bool


@dataclass(frozen=True, kw_only=True)
class ValidationWorseThanGeometric(Caution):
    """On the validation campaign the final model predicts worse than the geometric one."""

    kind = CautionKind.VALIDATION_WORSE_THAN_GEOMETRIC
    final_rms_mm: float
    geometric_rms_mm: float


@dataclass(frozen=True, kw_only=True)
class ValidationTemperaturesOutside(Caution):
    """The validation temperatures (C, low and high) lie outside the training's."""

    kind = CautionKind.VALIDATION_TEMPERATURES_OUTSIDE
    validate_c: list[float]
    training_c: list[float]


@dataclass(frozen=True, kw_only=True)
class ThermalPriorContradicted(Caution):
    """The data contradict the material's thermal growth (per K); `standing` the term's (found, rejected)."""

    kind = CautionKind.THERMAL_PRIOR_CONTRADICTED
    data_per_k: float
    material_per_k: float
    standing: str


@dataclass(frozen=True, kw_only=True)
class TrackerAirStuck(Caution):
    """The tracker's air temperature read `air_c` at every point while the recorded temperature rose from
    `start_c` to `end_c` (`span_k` between its extremes): the tracker's scale per K of the recorded temperature
    (hil.analysis.diagnosis.physics_terms.tracker_air_summary) as the model holds it (`fitted_per_k` +-
    `std_per_k`), its prior, what the data alone make of it (None: they carry nothing of it) and its
    `standing` (found, assumed, rejected)."""

    kind = CautionKind.TRACKER_AIR_STUCK
    air_c: float
    start_c: float
    end_c: float
    span_k: float
    prior_per_k: float
    prior_std_per_k: float
    fitted_per_k: float
    std_per_k: float
    standing: str
    data_per_k: float | None = None
    data_std_per_k: float | None = None


@dataclass(frozen=True, kw_only=True)
class ValidationJointsOutside(Caution):
    """Validation joints (1-based) leave the training's range by more than `margin_deg`."""

    kind = CautionKind.VALIDATION_JOINTS_OUTSIDE
    joints: list[int]
    margin_deg: float


CAUTIONS: dict[CautionKind, type[Caution]] = {
    cls.kind: cls
    for cls in (
        CalibrationNote,
        FirstChoiceSetAside,
        PreviousEffectsKept,
        StageWorseThanPrevious,
        AmbiguousEffects,
        ValidationUnrepresented,
        ValidationWorseThanGeometric,
        ValidationTemperaturesOutside,
        ThermalPriorContradicted,
        ValidationJointsOutside,
        TrackerAirStuck,
    )
}
