"""The purely kinematic chain nearest a full calibrated model, and what leaving its other terms out costs.

A URDF, the UR kinematics file and a DH table hold geometry only: a joint's yield under gravity, a gear's
cyclic error, a link's growth with temperature or a residual map cannot live in them. The export fits the
best kinematic chain to what the full model predicts over the joints it was trained on (the training
data's joints when given, else uniform in the model's training range: a box that holds the measured poses
and poses beyond them, so the figure is then a wider one), by least squares on the tool points in the tracker frame: the kinematic parameters and the
base frame move, the tool points stay the model's (they are the tool, not the chain). The base must move:
what gravity bends at the shoulder tilts the whole arm much as a tilted base would, and on the demo's UR10
a fixed base left 0.24 mm RMS where a free one leaves 0.09. The chain's base in the model's base frame
(`T_base_chain`) goes into the first joint's origin when written, so the written file keeps the model's
base frame. Three points 100 mm off the first nest along the flange's axes
are fitted with the nests, so the flange's orientation is held as well as its position. Thermal terms are
taken at their training reference (the mean temperature or time the model was fitted at): a chain cannot
follow the temperature, and the reference is where the model's geometry holds. The cost is the distance
between the full model's points and the chain's, RMS and max, on those poses.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from hil.analysis.calibration.solve import Problem, identify, solve_ridge_igg3
from hil.data.dataset import joints_rad, make_dataset
from hil.geometry.kinematics import BASE_PARAM_NAMES
from hil.geometry.se3 import invert
from hil.model.calibrated_model import CalibratedModel

EXPORT_POSES = 400  # poses the chain is fitted on: some thousand equations for ~30 parameters
ORIENTATION_ARM_M = 0.1  # the virtual points' distance from the first nest along the flange's axes
_VIRTUAL_NEST = 900  # ids of the virtual nests (900, 901, 902): above any real nest number


@dataclass(frozen=True)
class KinematicEquivalent:
    """The chain (`model`: the full model without its other terms, its geometry and base refitted; its
    base frame is `T_base_chain` in the full model's), the cost of leaving them out on `poses` poses (m),
    what was left out and the drivers held at their reference."""

    model: CalibratedModel
    T_base_chain: np.ndarray
    poses: int
    rms_m: float
    max_m: float
    left_out: tuple[str, ...]
    references: dict[str, float]

    @property
    def exact(self) -> bool:
        """Nothing was left out: the chain is the model's own geometry."""
        return not self.left_out


def left_out_terms(model: CalibratedModel) -> tuple[str, ...]:
    """The model's terms a kinematic chain cannot hold, named as the reports name them."""
    terms = [eff.family + (f" (joint {eff.joint})" if eff.joint else "") for eff in model.effects]
    if model.residual_map is not None:
        terms.append("residual map")
    return tuple(terms)


def kinematic_equivalent(
    model: CalibratedModel, joints: np.ndarray | None = None, poses: int = EXPORT_POSES, seed: int = 0
) -> KinematicEquivalent:
    """The best purely kinematic chain for a calibrated model (module docstring) over `joints` (N, n) rad,
    or `poses` joint sets uniform in its training range; the model's own geometry, at no cost, when it has
    no other terms."""
    chain = replace(model, effects=[], residual_map=None, spread=None)
    left_out = left_out_terms(model)
    if not left_out:
        return KinematicEquivalent(chain, np.eye(4), 0, 0.0, 0.0, (), {})
    q = _training_joints(model, poses, seed) if joints is None else np.atleast_2d(np.asarray(joints, float))
    full, references = _with_virtual_nests(model), _references(model)
    df = _rows(full, q, references)
    target = full.predict(df)
    fitted_start = replace(full, effects=[], residual_map=None, spread=None)
    fit_rows = make_dataset(q_rows(df, model), target, smr=df["smr"].to_numpy())
    for column, value in references.items():
        fit_rows[column] = value
    problem = Problem.from_frame(fitted_start, fit_rows)
    names = fitted_start.param_names
    n = fitted_start.kinematic.n_joints  # the last joint's parameters place the flange: they stay the model's
    moving = [p for p in fitted_start.kinematic.param_names if not p.endswith(str(n))]
    chain_params = np.isin(names, moving) | np.isin(names, BASE_PARAM_NAMES)
    free = identify(fitted_start, problem).keep_mask & chain_params
    fitted = solve_ridge_igg3(fitted_start, problem, free, robust=False).model
    off = np.linalg.norm(fitted.predict(df) - target, axis=1)
    kept = replace(chain, kinematic=fitted.kinematic, T_tracker_base=fitted.T_tracker_base)
    T_base_chain = invert(model.T_tracker_base) @ fitted.T_tracker_base
    return KinematicEquivalent(
        kept, T_base_chain, len(q), float(np.sqrt(np.mean(off**2))), float(np.max(off)), left_out, references
    )


def _training_joints(model: CalibratedModel, poses: int, seed: int) -> np.ndarray:
    """Joints uniform in the model's training range (its joint limits, within a turn, when it has none)."""
    span = model.info.get("training_joint_range_rad")
    if span:
        lo, hi = np.asarray(span[0], float), np.asarray(span[1], float)
    else:
        limits = model.nominal.joint_limits
        lo, hi = np.maximum(limits[:, 0], -np.pi), np.minimum(limits[:, 1], np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, (poses, len(lo)))


def _with_virtual_nests(model: CalibratedModel) -> CalibratedModel:
    """The model with three more tool points, ORIENTATION_ARM_M off its first nest along the flange's
    axes (the chain must turn the flange as the model does, not only place the nests)."""
    first = model.tools[min(model.tools)]
    tools = dict(model.tools)
    for k in range(3):
        tools[_VIRTUAL_NEST + k] = first + ORIENTATION_ARM_M * np.eye(3)[k]
    return replace(model, tools=tools)


def _references(model: CalibratedModel) -> dict[str, float]:
    """The thermal terms' driver columns at their training reference."""
    out: dict[str, float] = {}
    for eff in model.effects:
        driver = eff.state.get("driver")
        if driver in ("temperature_c", "t_s") and "reference" in eff.state:
            out.setdefault(str(driver), float(eff.state["reference"]))
    return out


def _rows(model: CalibratedModel, q: np.ndarray, references: dict[str, float]) -> pd.DataFrame:
    """One row per pose and nest (the joints repeated per nest), the drivers at their reference."""
    nests = sorted(model.tools)
    q_rows = np.repeat(q, len(nests), axis=0)
    df = make_dataset(q_rows, np.zeros((len(q_rows), 3)), smr=np.tile(nests, len(q)))
    for column, value in references.items():
        df[column] = value
    return df


def q_rows(df: pd.DataFrame, model: CalibratedModel) -> np.ndarray:
    return joints_rad(df, model.nominal.n_joints)
