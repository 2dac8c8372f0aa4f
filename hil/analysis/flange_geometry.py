"""Tool-frame calibration from tracker points (tool paper, methods.md section 1).

Two methods:
- `fit_flange_frame` + `tool_point_in_flange`: the geometric flange-hole method. SMR centres seated
  in three or more of the six circle holes give the hole-ball plane and its circle centre; one SMR on
  the flange face gives the face height; hole 7 gives +x. Beyond the paper, any number of circle
  holes (>= 3) is accepted and fitted by least squares, and the fit reports its own residuals.
- `tool_point_by_distances`: the distance-constraint baseline, which needs no flange holes but lets
  the robot's own positioning error into the result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from hil.geometry.se3 import fit_circle_3d, make_transform

SMR_RADIUS_M = 0.01905


@dataclass(frozen=True)
class FlangeFit:
    """The flange frame in the tracker frame, and how well the hole balls fitted their circle."""

    T_tracker_flange: np.ndarray  # (4, 4)
    circle_radius_m: float
    circle_residual_rms_m: float  # in-plane radial and out-of-plane scatter of the hole balls
    face_height_m: float  # height of the face-ball centre above the hole-ball plane


def fit_flange_frame(
    p_tracker_holes: dict[int, np.ndarray],
    p_tracker_face: np.ndarray,
    smr_radius_m: float = SMR_RADIUS_M,
    p_tracker_viewpoint: np.ndarray | None = None,
) -> FlangeFit:
    """Flange frame from SMR centres (tracker frame, metres).

    p_tracker_holes: hole number -> centre of the SMR seated there; needs >= 3 of holes 1..6 and hole 7.
    p_tracker_face: centre of the SMR resting on the flange face at any free spot.
    p_tracker_viewpoint: where the tracker stands (default its origin): the face looks towards it,
    which fixes the sign of the flange z axis.
    """
    circle_ids = sorted(k for k in p_tracker_holes if 1 <= k <= 6)
    if len(circle_ids) < 3:
        raise ValueError(f"need the SMR in at least 3 of holes 1..6 (got holes {circle_ids})")
    if 7 not in p_tracker_holes:
        raise ValueError("need the SMR seated in hole 7: it defines the flange +x direction")
    circle_points = np.array([p_tracker_holes[k] for k in circle_ids], dtype=float)
    centre, normal, radius = fit_circle_3d(circle_points)
    viewpoint = np.zeros(3) if p_tracker_viewpoint is None else np.asarray(p_tracker_viewpoint, float)
    if normal @ (viewpoint - centre) < 0:
        normal = -normal
    height = float(normal @ (np.asarray(p_tracker_face, float) - centre))
    if not 0.0 < height < 2 * smr_radius_m:
        raise ValueError(
            f"the face ball sits {height * 1e3:.2f} mm from the hole-ball plane; expected between 0 and "
            f"{2 * smr_radius_m * 1e3:.1f} mm: was the SMR really resting on the flange face?"
        )
    origin = centre + (height - smr_radius_m) * normal
    to_hole7 = np.asarray(p_tracker_holes[7], float) - centre
    x_axis = to_hole7 - (to_hole7 @ normal) * normal
    if np.linalg.norm(x_axis) < 1e-3:
        raise ValueError("hole 7 lies on the flange axis; it must be off-centre to define +x")
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(normal, x_axis)
    R = np.column_stack([x_axis, y_axis, normal])
    offsets = circle_points - centre
    out_of_plane = offsets @ normal
    in_plane = np.linalg.norm(offsets - np.outer(out_of_plane, normal), axis=1) - radius
    residual = float(np.sqrt(np.mean(out_of_plane**2 + in_plane**2)))
    return FlangeFit(make_transform(R, origin), float(radius), residual, height)


def tool_point_in_flange(T_tracker_flange: np.ndarray, p_tracker_tool: np.ndarray) -> np.ndarray:
    """Tool SMR centre in the flange frame from its tracker reading: R^T (p - O)."""
    R = T_tracker_flange[:3, :3]
    return R.T @ (np.asarray(p_tracker_tool, float) - T_tracker_flange[:3, 3])


def tool_point_by_distances(
    T_base_flange: np.ndarray, p_tracker: np.ndarray, p_flange_guess: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """Distance-constraint tool point (tool paper 1b): |B_P_i - B_P_j| = |L_P_i - L_P_j| for all pairs.

    T_base_flange (N, 4, 4) as the robot reports it, p_tracker (N, 3) the tool SMR readings.
    Returns the tool point in the flange (3,) and the RMS distance misfit (m).
    """
    T = np.asarray(T_base_flange, float)
    P = np.asarray(p_tracker, float)
    if T.shape[0] != P.shape[0] or T.shape[0] < 3:
        raise ValueError("need at least 3 poses, each with a flange pose and a tracker point")
    i, j = np.triu_indices(len(P), k=1)
    d_tracker = np.linalg.norm(P[i] - P[j], axis=1)
    R, t = T[:, :3, :3], T[:, :3, 3]

    def misfit(p: np.ndarray) -> np.ndarray:
        b = R @ p + t
        return np.linalg.norm(b[i] - b[j], axis=1) - d_tracker

    guess = np.zeros(3) if p_flange_guess is None else np.asarray(p_flange_guess, float)
    sol = least_squares(misfit, guess, method="lm", xtol=1e-14, ftol=1e-14)
    return sol.x, float(np.sqrt(np.mean(sol.fun**2)))
