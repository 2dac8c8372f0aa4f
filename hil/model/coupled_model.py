"""A calibrated model of a robot whose controller couples its joints keeps the coupling (hil.geometry.coupling)
in its info, so every command and procedure that uses the model later converts the joints as the robot file did."""

from __future__ import annotations

from hil.geometry.coupling import JointCoupling, coupling_from_table, coupling_table
from hil.model.calibrated_model import CalibratedModel


def keep_coupling(model: CalibratedModel, coupling: JointCoupling | None) -> None:
    """Keep a coupled robot's coupling in the model's info, so predict and compensate convert as it did."""
    if coupling is not None and coupling.coupled_rows():
        model.info["coupling"] = coupling_table(coupling)


def model_coupling(model: CalibratedModel) -> JointCoupling | None:
    """The joint coupling a model was calibrated with (its robot file's), None for an uncoupled robot."""
    table = model.info.get("coupling")
    return (
        None
        if table is None
        else coupling_from_table(table, model.kinematic.n_joints, "the model's coupling")
    )
