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

from hil.geometry.se3 import fit_circle_3d, fit_rigid, make_transform, rotation_log

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


def seated_face_height_m(smr_radius_m: float, hole_diameter_m: float) -> float:
    """Expected height of a face-resting SMR's centre above the hole-ball plane: r - sqrt(r^2 - (d/2)^2)
    (0.288 mm for a 1.5" SMR in 6.6 mm holes, the tool paper's flange)."""
    if not 0.0 < hole_diameter_m < 2 * smr_radius_m:
        raise ValueError("the hole diameter must lie between 0 and the SMR's diameter")
    return float(smr_radius_m - np.sqrt(smr_radius_m**2 - (hole_diameter_m / 2) ** 2))


def hole_angles_rad(T_tracker_flange: np.ndarray, p_tracker_holes: dict[int, np.ndarray]) -> dict[int, float]:
    """Each hole ball's angle (rad) around the fitted flange axis, from the fitted +x, in (-pi, pi]."""
    T = np.asarray(T_tracker_flange, float)
    return {
        k: float(np.arctan2(*(T[:3, :3].T @ (np.asarray(p, float) - T[:3, 3]))[[1, 0]]))
        for k, p in p_tracker_holes.items()
    }


def hole_angle_errors_rad(angles_rad: dict[int, float]) -> dict[int, float]:
    """How far each of holes 1..6 sits from its nominal place (k - 3.5) * 60 deg, wrapped into (-pi, pi]."""
    return {
        k: float(np.angle(np.exp(1j * (a - np.deg2rad((k - 3.5) * 60.0)))))
        for k, a in angles_rad.items()
        if 1 <= k <= 6
    }


def bisector_error_rad(angles_rad: dict[int, float]) -> float:
    """Angle between hole 7's direction and the bisector of holes 3 and 4 (the paper's second way to +x)."""
    bisector = np.angle(np.exp(1j * angles_rad[3]) + np.exp(1j * angles_rad[4]))
    return float(np.angle(np.exp(1j * (angles_rad[7] - bisector))))


def distance_method_sigma_m(
    T_base_flange: np.ndarray, p_tracker: np.ndarray, p_flange: np.ndarray, misfit_rms_m: float
) -> float:
    """Standard error (m, 3-D) of the distance-constraint tool point: its misfit (mostly the robot's own error)
    through the equations' geometry; the N(N-1)/2 pair equations carry only N - 3 independent points' worth
    of information, so the formal covariance is inflated by sqrt(pairs / (N - 3))."""
    T = np.asarray(T_base_flange, float)
    P = np.asarray(p_tracker, float)
    n = len(P)
    if n < 4:
        raise ValueError("the distance method's standard error needs at least 4 poses")
    i, j = np.triu_indices(n, k=1)
    R, t = T[:, :3, :3], T[:, :3, 3]
    b = R @ np.asarray(p_flange, float) + t
    d = b[i] - b[j]
    u = d / np.linalg.norm(d, axis=1)[:, None]
    J = np.einsum("ka,kab->kb", u, R[i] - R[j])
    cov = misfit_rms_m**2 * np.linalg.inv(J.T @ J)
    return float(np.sqrt(np.trace(cov) * len(i) / (n - 3)))


@dataclass(frozen=True)
class ToolOrientation:
    """The tool as mounted against its drawing: the rotation taking the drawn nests onto the fitted ones."""

    T_flange_tool: np.ndarray  # (4, 4): drawing (tool) frame in the flange frame
    rotation_rad: float  # angle of that rotation: 0 for a tool on its dowel
    shape_error_m: float  # worst nest off the rigidly moved drawing: a swapped nest, a wrong drawing


def tool_orientation(p_flange_drawn: np.ndarray, p_flange_fitted: np.ndarray) -> ToolOrientation:
    """Tool orientation from three or more nests (K, 3): the best rigid map drawing -> fit (Kabsch)."""
    drawn = np.asarray(p_flange_drawn, float)
    fitted = np.asarray(p_flange_fitted, float)
    if drawn.shape != fitted.shape or drawn.ndim != 2 or len(drawn) < 3:
        raise ValueError("the tool's orientation needs three or more nests, drawn and fitted")
    T, _ = fit_rigid(drawn, fitted)
    moved = drawn @ T[:3, :3].T + T[:3, 3]
    angle = float(np.linalg.norm(rotation_log(T[:3, :3])))
    return ToolOrientation(T, angle, float(np.max(np.linalg.norm(moved - fitted, axis=1))))


def common_point_error_m(p_base_m: np.ndarray, p_tracker_m: np.ndarray) -> np.ndarray:
    """The tool paper's validation: predicted base points moved onto the tracker's by the best rigid
    transform (common-point transformation); each point's remaining distance (N,) m."""
    p_base = np.asarray(p_base_m, float)
    T, _ = fit_rigid(p_base, p_tracker_m)
    return np.linalg.norm(p_base @ T[:3, :3].T + T[:3, 3] - np.asarray(p_tracker_m, float), axis=1)
