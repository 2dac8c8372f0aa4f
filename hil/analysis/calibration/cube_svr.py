"""The SVR paper's compensation model: the nominal robot plus one SVR per cube fitted to the raw error.

The paper (methods.md 3) registers the tracker to the robot, then learns the whole positioning error against
the nominal model (no kinematic calibration) with one SVR per 100 mm cube. Here: the nominal geometry with
only the base frame and the tool points fitted (what "uncompensated" means in both papers' tables), and a
per-cube SVRMap on that model's error as its residual map, so `predict` and the compensation use it as
they use any calibrated model. Ours (hil.analysis.diagnosis.pipeline) calibrates first and maps what is left.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from hil.analysis.calibration.solve import Problem, solve_ridge_igg3
from hil.geometry.kinematics import KinematicModel, tool_points
from hil.model.calibrated_model import CalibratedModel, initial_model
from hil.model.residual_maps import SVRMap


def registered_nominal(
    nominal: KinematicModel, df: pd.DataFrame, tool_guess_m: np.ndarray | None = None
) -> CalibratedModel:
    """The nominal geometry with only the base frame and the tool points fitted to the measurements."""
    model = initial_model(nominal, df, tool_guess_m=tool_guess_m)
    free = np.array([n.startswith(("base_", "tool")) for n in model.param_names])
    return solve_ridge_igg3(model, Problem.from_frame(model, df), free, robust=False).model


def raw_error(model: CalibratedModel, df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joints (N, 6), the model's tool positions in the base frame (N, 3) and measured - model (N, 3), m."""
    prob = Problem.from_frame(model, df)
    error = prob.residuals(model)[:, :3]
    p_base = tool_points(model.kinematic, prob.ctx.q, model._row_tools(prob.smr))
    return prob.ctx.q, p_base, error


def fit_cube_svr(
    nominal: KinematicModel, df: pd.DataFrame, cube_m: float = 0.1, tool_guess_m: np.ndarray | None = None
) -> CalibratedModel:
    """The registered nominal model carrying a per-cube SVR of its raw error as its residual map."""
    model = registered_nominal(nominal, df, tool_guess_m)
    q, p_base, error = raw_error(model, df)
    svr = SVRMap(mode="per_cube", cube_m=cube_m).fit(q, p_base, error, 0.0)
    model.residual_map = svr.to_dict()
    model.info["residual_map"] = svr.describe()  # what the report prints: the mode and what it learned
    return model
