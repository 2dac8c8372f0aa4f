"""Joint-axis identification by circle point analysis: each joint turned alone, its SMR arcs fitted, the
axis lines chained into a kinematic model.

A sweep turns one joint while the others stand still; every SMR on the moving part draws an arc about that
joint's axis. Per arc: plane by SVD, circle by an algebraic fit in that plane; then one geometric fit of
the axis line to all arcs of the joint (each arc keeps its own radius and height along the axis). The axis
points the way a positive joint turn moves the SMRs (right-hand rule). Refused: too short an arc, an SMR
(almost) on the axis, collinear points, a second joint moving inside a sweep, sweeps that do not share one
reference pose (only the joints before the swept one count: joint j's axis depends on them alone, so a sweep
may hold the later joints elsewhere, e.g. the arm stretched where gravity sag leaves the arc a circle). The
lines, all at the reference pose q_ref, give standard DH frames (common normals), with
Hayati's beta between (nearly) parallel axes (the normal taken in the plane through the previous origin,
d = 0). Lengths in metres, angles in radians inside.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from hil.data.dataset import SAME_POSE_RAD, joint_columns, points_m, smr_ids
from hil.geometry.coupling import JointCoupling
from hil.geometry.kinematics import KinematicModel

MIN_ARC_RAD = math.radians(30.0)  # a shorter arc leaves the circle's centre (the axis) poorly fixed
MIN_RADIUS_SIGMAS = 50.0  # an SMR closer to the axis than this many tracker sigmas: refused
COLLINEAR_SIGMAS = 5.0  # points within this many sigmas of a straight line draw no usable circle
MIN_POINTS = 4  # per arc: three fix a circle, a fourth gives a residual
PARALLEL_RAD = math.radians(1.0)  # consecutive axes within this are parallel: Hayati's beta, not a normal
HELD_RAD = 10 * SAME_POSE_RAD  # a joint that moves less than this inside a sweep stands still
DEFAULT_SIGMA_M = 10e-6  # per-axis 1-sigma of one tracker reading when none is given


class SweepError(ValueError):
    """A sweep (or a set of sweeps) circle point analysis cannot use; the message says why and what to do."""


@dataclass(frozen=True)
class Sweep:
    """One sweep: the joint it turns (0-based), its rows in the frame and its label."""

    joint: int
    rows: np.ndarray
    label: str


@dataclass
class AxisFit:
    """One joint's axis in the tracker frame and the quality of its arcs (SI)."""

    joint: int  # 0-based
    point_m: np.ndarray  # (3,) the point of the line nearest the arcs' centres' mean
    direction: np.ndarray  # (3,) unit, right-hand rule for a positive joint turn
    radii_m: dict[int, float]  # per SMR
    centres_m: dict[int, np.ndarray]  # per SMR, on the axis
    residual_rms_m: float  # geometric distance of the points from their circles
    swept_rad: float  # the joint's travel in the sweep (readings)
    arc_rad: float  # the largest angle the SMRs turned about the fitted axis
    points: int
    sweeps: list[str] = field(default_factory=list)
    direction_sigma_rad: float = 0.0  # 1-sigma angle of the direction (RMS over both tilts), from the fit
    point_sigma_m: float = 0.0  # 1-sigma distance of the point across the true line, from the fit

    def to_dict(self) -> dict:
        return {
            "joint": self.joint + 1,
            "point_mm": (self.point_m * 1e3).tolist(),
            "direction": self.direction.tolist(),
            "direction_sigma_deg": math.degrees(self.direction_sigma_rad),
            "point_sigma_mm": self.point_sigma_m * 1e3,
            "residual_rms_mm": self.residual_rms_m * 1e3,
            "swept_deg": math.degrees(self.swept_rad),
            "arc_deg": math.degrees(self.arc_rad),
            "radius_mm": {str(k): v * 1e3 for k, v in self.radii_m.items()},
            "points": self.points,
            "sweeps": self.sweeps,
        }


# ------------------------------------------------------------------------------------------ one circle
def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing `normal` to a right-handed basis (u, v, normal)."""
    seed = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, seed)
    u /= np.linalg.norm(u)
    return u, np.cross(normal, u)


def check_arc(points_m: np.ndarray, sigma_m: float, what: str) -> None:
    """Refuse an arc that cannot fix a circle: too few points, or points on a straight line within noise."""
    p = np.asarray(points_m, float)
    if len(p) < MIN_POINTS:
        raise SweepError(f"{what}: {len(p)} points; an arc needs at least {MIN_POINTS}: measure more points")
    centred = p - p.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    off_line = s[1] / math.sqrt(len(p))  # RMS distance from the best straight line
    if off_line < COLLINEAR_SIGMAS * sigma_m:
        raise SweepError(
            f"{what}: the points are collinear (within {off_line * 1e3:.4f} mm of a straight line): no circle; "
            "turn the joint further or put the SMR farther from its axis"
        )


def fit_circle(points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Circle through points (N, 3): centre, unit plane normal, radius (plane by SVD, algebraic fit in it)."""
    p = np.asarray(points_m, float)
    c0 = p.mean(axis=0)
    _, _, Vt = np.linalg.svd(p - c0)
    n = Vt[2]
    u, v = _plane_basis(n)
    x, y = (p - c0) @ u, (p - c0) @ v
    A = np.column_stack([x, y, np.ones_like(x)])
    (D, E, F), *_ = np.linalg.lstsq(A, -(x**2 + y**2), rcond=None)
    cx, cy = -D / 2.0, -E / 2.0
    r = math.sqrt(max(cx**2 + cy**2 - F, 0.0))
    return c0 + cx * u + cy * v, n, r


# ------------------------------------------------------------------------------------------ one axis
def _line_residuals(params: np.ndarray, arcs: list[np.ndarray], n0, u0, v0, a0) -> np.ndarray:
    """Per point: height above its arc's plane and radial distance minus its arc's radius."""
    n = n0 + params[0] * u0 + params[1] * v0
    n = n / np.linalg.norm(n)
    a = a0 + params[2] * u0 + params[3] * v0
    out = []
    for k, p in enumerate(arcs):
        h, r = params[4 + 2 * k], params[5 + 2 * k]
        d = p - a
        along = d @ n
        radial = np.linalg.norm(d - along[:, None] * n, axis=1)
        out += [along - h, radial - r]
    return np.concatenate(out)


@dataclass(frozen=True)
class LineFit:
    """One axis line fitted to its arcs (SI): the line, each arc's radius and height along it, the fit's
    residual and the largest arc, and the line's 1-sigma uncertainty from the fit's own scatter."""

    point_m: np.ndarray  # (3,) the foot on the line of the arcs' mean centre
    direction: np.ndarray  # (3,) unit, right-hand rule for a positive joint turn
    radii_m: list[float]
    heights_m: list[float]
    residual_rms_m: float
    arc_rad: float
    direction_sigma_rad: float  # RMS angle between the fitted and the true direction (both tilts)
    point_sigma_m: float  # RMS distance of `point_m` from the true line, across it


def fit_axis(
    arcs_m: list[np.ndarray],
    joints_rad: list[np.ndarray],
    sigma_m: float = DEFAULT_SIGMA_M,
    what: str = "sweep",
) -> LineFit:
    """One axis line fitted to several arcs about it (each (N_k, 3)) whose joint readings are `joints_rad`
    (each (N_k,)). The direction is the right-hand axis of a positive joint turn; the point is the foot of
    the arcs' mean centre. The uncertainties are the Gauss-Newton covariance at the solution scaled by the
    residuals' own variance (so an arc that is no circle widens them, as it should)."""
    for k, p in enumerate(arcs_m):
        check_arc(p, sigma_m, f"{what}, arc {k + 1}" if len(arcs_m) > 1 else what)
    sol, a, n = _solve_line(arcs_m)
    heights = [float(h) for h in sol.x[4::2]]
    radii = [float(r) for r in sol.x[5::2]]
    res = sol.fun.reshape(-1)
    # right-hand rule: a positive joint step must turn every arc's points positively about n
    turn, arc = 0.0, 0.0
    for p, q in zip(arcs_m, joints_rad, strict=True):
        d = p - a
        d -= (d @ n)[:, None] * n
        u, v = _plane_basis(n)
        phi = np.unwrap(np.arctan2(d @ v, d @ u))
        turn += float(np.sum(np.diff(phi) * np.diff(q)))
        arc = max(arc, float(np.ptp(phi)))
    if turn < 0:
        n = -n
    rms = float(np.sqrt(np.mean(res**2) * 2.0))  # two components per point: the distance's RMS
    along = _along(arcs_m, a, n)
    s2 = float(res @ res) / max(len(res) - len(sol.x), 1)  # the residuals' variance
    direction_sigma, point_sigma = _line_sigmas(sol.jac, s2, along)
    return LineFit(a + along * n, n, radii, heights, rms, arc, direction_sigma, point_sigma)


def _solve_line(arcs_m: list[np.ndarray]):
    """The least-squares line of `_line_residuals` from per-arc circle fits: (solution, point, direction)."""
    fits = [fit_circle(p) for p in arcs_m]
    # a common normal orientation before averaging (SVD normals have arbitrary signs)
    normals = np.array([f[1] for f in fits])
    normals *= np.sign(normals @ normals[0])[:, None]
    n0 = normals.mean(axis=0)
    n0 /= np.linalg.norm(n0)
    a0 = np.mean([f[0] for f in fits], axis=0)
    u0, v0 = _plane_basis(n0)
    x0 = [0.0, 0.0, 0.0, 0.0]
    for c, _, r in fits:
        x0 += [float((c - a0) @ n0), r]
    sol = least_squares(
        _line_residuals, np.array(x0), args=(arcs_m, n0, u0, v0, a0), method="lm", x_scale="jac"
    )
    n = n0 + sol.x[0] * u0 + sol.x[1] * v0
    return sol, a0 + sol.x[2] * u0 + sol.x[3] * v0, n / np.linalg.norm(n)


def _along(arcs_m: list[np.ndarray], a: np.ndarray, n: np.ndarray) -> float:
    """Where along the line (from `a`) the reported point lies: level with the arcs' mean centre."""
    return float((np.mean([p.mean(axis=0) for p in arcs_m], axis=0) - a) @ n)


def expected_line_sigmas(arcs_m: list[np.ndarray], sigma_m: float) -> tuple[float, float]:
    """The 1-sigma (direction angle rad, point m) a fit of arcs like these (noise-free, e.g. from a nominal
    model) would have with readings of per-axis noise `sigma_m`: for planning how many points an arc needs."""
    sol, a, n = _solve_line(arcs_m)
    return _line_sigmas(sol.jac, sigma_m**2, _along(arcs_m, a, n))


def _line_sigmas(jac: np.ndarray, s2: float, along_m: float) -> tuple[float, float]:
    """1-sigma of the line fitted by `_line_residuals`: the direction's angle (rad) and the distance across
    the line (m) of its point `along_m` from the fit's origin, both as RMS over the two directions across
    it. Covariance (J^T J)^-1 s2, s2 the variance of one residual."""
    cov = np.linalg.pinv(jac.T @ jac) * s2
    tilt, shift = cov[:2, :2], cov[2:4, 2:4]
    across = shift + along_m * (cov[2:4, :2] + cov[:2, 2:4]) + along_m**2 * tilt
    return math.sqrt(max(float(np.trace(tilt)), 0.0)), math.sqrt(max(float(np.trace(across)), 0.0))


# ------------------------------------------------------------------------------------------ sweeps
def coupling_hint(coupling: str | None) -> str:
    """What to say when two readings move together: the coupling the joints were converted by, or how to
    give one (a coupled controller, FANUC's J2/J3, reports readings that move together in a one-joint turn)."""
    if coupling:
        return (
            f"; the readings were converted to kinematic joints by the robot's coupling ({coupling}) and two "
            "still move: check the coupling and that the data holds the controller's joints"
        )
    return (
        "; if the controller couples these joints (FANUC's pendant J3 moves with J2), give --robot with the "
        "robot file whose [coupling] declares it, and --joint-convention controller"
    )


def sweeps_of(
    df: pd.DataFrame, n_joints: int = 6, source: str = "campaign", coupling: str | None = None
) -> list[Sweep]:
    """The sweeps of a campaign. With a `sweep` column its labels group the rows, and a sweep in which a
    second joint moves is refused; without one, runs of consecutive poses between which only one joint
    changes (and rows of one pose, e.g. several SMRs) form the sweeps. `coupling` describes the coupling
    the joints were converted by (None: the readings as given), for the refusals."""
    q = df[joint_columns(n_joints)].to_numpy(float)
    if "sweep" in df.columns:
        out = []
        labels = df["sweep"].astype(str).to_numpy()
        for label in dict.fromkeys(labels):
            rows = np.flatnonzero(labels == label)
            travel = np.ptp(q[rows], axis=0)
            moving = np.flatnonzero(travel > HELD_RAD)
            if len(moving) == 0:
                raise SweepError(
                    f"{source}: sweep {label}: no joint turns; turn one joint by at least 30 deg"
                )
            if len(moving) > 1:
                by = moving[np.argsort(travel[moving])[::-1]]
                raise SweepError(
                    f"{source}: sweep {label}: joint {by[1] + 1} moves too ({math.degrees(travel[by[1]]):.3f} deg) "
                    f"while joint {by[0] + 1} sweeps; hold every other joint still during a sweep"
                    + coupling_hint(coupling)
                )
            out.append(Sweep(int(moving[0]), rows, label))
        return out
    # pose blocks: consecutive rows at one pose (several SMRs, repeats); steps between blocks
    new_pose = np.concatenate([[True], np.any(np.abs(np.diff(q, axis=0)) > HELD_RAD, axis=1)])
    starts = np.flatnonzero(new_pose)
    ends = np.append(starts[1:], len(q))
    moved = np.abs(np.diff(q[starts], axis=0)) > HELD_RAD  # (blocks - 1, n)
    step_joint = np.where(moved.sum(axis=1) == 1, np.argmax(moved, axis=1), -1)
    out = []
    k = 0
    while k < len(step_joint):
        j = int(step_joint[k])
        if j < 0:
            k += 1
            continue
        last = k
        while last + 1 < len(step_joint) and step_joint[last + 1] == j:
            last += 1
        rows = np.arange(starts[k], ends[last + 1])
        out.append(Sweep(j, rows, f"rows {rows[0] + 1}-{rows[-1] + 1}"))
        k = last + 1
    if not out:
        raise SweepError(
            f"{source}: no sweep found (no run of rows in which one joint alone turns); record each joint "
            "turned alone, or label the rows with a `sweep` column"
        )
    return out


@dataclass
class AxesResult:
    """Every joint's axis, the reference pose they share and the model built from them."""

    axes: list[AxisFit]
    q_ref_rad: np.ndarray
    model: KinematicModel
    T_tracker_base: np.ndarray
    tool_points_m: dict[int, np.ndarray]  # SMRs in the flange frame of `model` at the last sweep
    parallel: list[bool]  # joint i's axis parallel to the next one's (Hayati's beta)

    def to_dict(self) -> dict:
        m = self.model
        return {
            "joints": [a.to_dict() for a in self.axes],
            "q_ref_deg": np.rad2deg(self.q_ref_rad).tolist(),
            "T_tracker_base_mm": _transform_mm(self.T_tracker_base),
            "dh": [
                {
                    "joint": i + 1,
                    "theta_offset_deg": math.degrees(m.theta[i]),
                    "d_mm": m.d[i] * 1e3,
                    "a_mm": m.a[i] * 1e3,
                    "alpha_deg": math.degrees(m.alpha[i]),
                    "beta_deg": math.degrees(m.beta[i]),
                    "hayati_beta": bool(m.uses_beta[i]),
                }
                for i in range(m.n_joints)
            ],  # fmt: skip
            "tool_points_mm": {str(k): (v * 1e3).tolist() for k, v in self.tool_points_m.items()},
        }


def _transform_mm(T: np.ndarray) -> list[list[float]]:
    out = np.array(T, float)
    out[:3, 3] *= 1e3
    return out.tolist()


def identify_axes(
    df: pd.DataFrame,
    n_joints: int = 6,
    sigma_m: float = DEFAULT_SIGMA_M,
    source: str = "campaign",
    name: str = "measured",
    coupling: str | None = None,
) -> AxesResult:
    """Every joint's axis from a campaign's sweeps (see `sweeps_of`), and the DH model they make. The joints
    are the kinematic ones; `coupling` describes the coupling they were converted by, for the refusals."""
    q = df[joint_columns(n_joints)].to_numpy(float)
    p = points_m(df)
    smr = smr_ids(df)
    sweeps = sweeps_of(df, n_joints, source, coupling)
    by_joint: dict[int, list[Sweep]] = {}
    for s in sweeps:
        travel = float(np.ptp(q[s.rows, s.joint]))
        if travel < MIN_ARC_RAD:
            raise SweepError(
                f"{source}: sweep {s.label} turns joint {s.joint + 1} by {math.degrees(travel):.1f} deg, too short "
                f"an arc to fix its axis; turn it by at least {math.degrees(MIN_ARC_RAD):.0f} deg"
            )
        by_joint.setdefault(s.joint, []).append(s)
    missing = [j + 1 for j in range(n_joints) if j not in by_joint]
    if missing:
        raise SweepError(
            f"{source}: no sweep of joint(s) {', '.join(map(str, missing))}; a model needs every joint turned alone"
            + coupling_hint(coupling)
        )
    q_ref = _reference_pose(q, by_joint, n_joints, source)
    axes = []
    for j in range(n_joints):
        rows = np.concatenate([s.rows for s in by_joint[j]])
        arcs, readings, ids = [], [], []
        for k in np.unique(smr[rows]):
            r = rows[smr[rows] == k]
            arcs.append(p[r])
            readings.append(q[r, j])
            ids.append(int(k))
        what = f"{source}: joint {j + 1}"
        line = fit_axis(arcs, readings, sigma_m, what)
        radii = line.radii_m
        small = [k for k, r in zip(ids, radii, strict=True) if r < MIN_RADIUS_SIGMAS * sigma_m]
        if small:
            raise SweepError(
                f"{what}: SMR {small[0]} lies {min(radii) * 1e3:.3f} mm from the axis, too close to fix it; "
                "put the SMR farther from the joint's axis"
            )
        a, n = line.point_m, line.direction
        centres = {k: a + ((arc_p.mean(axis=0) - a) @ n) * n for k, arc_p in zip(ids, arcs, strict=True)}
        axes.append(
            AxisFit(j, line.point_m, n, dict(zip(ids, radii, strict=True)), centres, line.residual_rms_m,
                    float(np.ptp(q[rows, j])), line.arc_rad, len(rows), [s.label for s in by_joint[j]],
                    line.direction_sigma_rad, line.point_sigma_m)
        )  # fmt: skip
    model, T_tb, parallel = model_from_axes(
        np.array([a.point_m for a in axes]), np.array([a.direction for a in axes]), q_ref,
        axes[-1].centres_m[min(axes[-1].centres_m)], name,
    )  # fmt: skip
    tools = _tool_points(model, T_tb, q, p, smr, by_joint[n_joints - 1])
    return AxesResult(axes, q_ref, model, T_tb, tools, parallel)


def _reference_pose(q: np.ndarray, by_joint: dict[int, list[Sweep]], n: int, source: str) -> np.ndarray:
    """The pose every axis is measured at: joint k's value while every later joint swept (the axis of joint
    j depends on joints 1..j-1 only); sweeps that disagree on it are refused."""
    q_ref = np.full(n, np.nan)
    seen: dict[int, str] = {}
    for j in range(n):
        for s in by_joint[j]:
            held = q[s.rows, :j].mean(axis=0) if j else np.zeros(0)
            for k in range(j):
                if np.isnan(q_ref[k]):
                    q_ref[k], seen[k] = held[k], s.label
                elif abs(held[k] - q_ref[k]) > HELD_RAD:
                    raise SweepError(
                        f"{source}: joint {k + 1} stood at {math.degrees(held[k]):.3f} deg during sweep {s.label} "
                        f"and at {math.degrees(q_ref[k]):.3f} deg during sweep {seen[k]}; sweep every joint from "
                        "one reference pose (return the others to it)"
                    )
    last = by_joint[n - 1][0]
    q_ref[n - 1] = float(np.median(q[last.rows, n - 1]))
    return q_ref


def _common_normal(p1, z1, p2, z2) -> tuple[float, float]:
    """Parameters (t, s) of the closest points p1 + t z1 and p2 + s z2 of two non-parallel lines."""
    w = p1 - p2
    b = z1 @ z2
    d, e = z1 @ w, z2 @ w
    den = 1.0 - b * b
    return (b * e - d) / den, (e - b * d) / den


def _angle_about(v_from: np.ndarray, v_to: np.ndarray, axis: np.ndarray) -> float:
    """Signed angle from one vector to another about a unit axis (both perpendicular to it)."""
    return math.atan2(float(np.cross(v_from, v_to) @ axis), float(v_from @ v_to))


def model_from_axes(
    points_m: np.ndarray, directions: np.ndarray, q_ref: np.ndarray, flange_point_m: np.ndarray, name: str
) -> tuple[KinematicModel, np.ndarray, list[bool]]:
    """Standard DH (Hayati's beta between parallel axes) from the axis lines at the pose q_ref (tracker frame):
    the model, the base frame T_tracker_base (on axis 1, zero of joint 1 at q_ref's reading) and which joints
    are parallel to the next. The flange frame lies on the last axis, level with `flange_point_m`."""
    n = len(q_ref)
    z = [d / np.linalg.norm(d) for d in np.asarray(directions, float)]
    pts = np.asarray(points_m, float)
    theta, d, a, alpha, beta = (np.zeros(n) for _ in range(5))
    parallel = [False] * n
    # base origin: axis 1's foot of the common normal with axis 2 (or nearest axis 2's point if parallel)
    if abs(z[0] @ z[1]) > math.cos(PARALLEL_RAD):
        O = pts[0] + ((pts[1] - pts[0]) @ z[0]) * z[0]
    else:
        t, _ = _common_normal(pts[0], z[0], pts[1], z[1])
        O = pts[0] + t * z[0]
    zp = z[0]
    xs: list[np.ndarray] = []
    Os = [O]
    for i in range(n - 1):
        zi, pi = z[i + 1], pts[i + 1]
        if abs(zp @ zi) > math.cos(PARALLEL_RAD):  # Hayati: the normal in the plane through O, d = 0
            s = ((O - pi) @ zp) / (zi @ zp)
            Oi = pi + s * zi
            ai = float(np.linalg.norm(Oi - O))
            if ai < 1e-6:
                raise SweepError(f"joints {i + 1} and {i + 2} turn about one line; their axes must differ")
            x = (Oi - O) / ai
            y = np.cross(zp, x)
            b = math.asin(float(np.clip(zi @ x, -1, 1)))
            al = math.atan2(-float(zi @ y), float(zi @ zp))
            parallel[i], beta[i], d[i] = True, b, 0.0
        else:
            t, s = _common_normal(O, zp, pi, zi)
            foot, Oi = O + t * zp, pi + s * zi
            x = np.cross(zp, zi)
            x /= np.linalg.norm(x)
            ai = float((Oi - foot) @ x)
            Oi = foot + ai * x
            al = _angle_about(zp, zi, x)
            d[i] = t
        a[i], alpha[i] = ai, al
        xs.append(x)
        O, zp = Oi, zi
        Os.append(O)
    # x of the base frame: joint 1 reads its zero where the model's theta_1 is 0
    x0 = _rotate(xs[0], z[0], -q_ref[0])
    x_frame = x0
    for i in range(n - 1):
        theta[i] = _angle_about(x_frame, xs[i], z[i]) - q_ref[i]
        x_frame = _frame_x(xs[i], z[i], alpha[i], beta[i])
    # last joint: frame n on axis n, level with the flange point, no twist, theta offset 0
    d[n - 1] = float((np.asarray(flange_point_m, float) - O) @ zp)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x0, np.cross(z[0], x0), z[0], Os[0]
    theta = np.angle(np.exp(1j * theta))
    model = KinematicModel(
        name=name, theta=theta, d=d, a=a, alpha=alpha, beta=beta, uses_beta=np.array(parallel, bool),
        joint_limits=np.tile(np.deg2rad([-360.0, 360.0]), (n, 1)),
    )  # fmt: skip
    return model, T, parallel


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """v turned by `angle` about a unit axis (Rodrigues)."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * (axis @ v) * (1 - c)


def _frame_x(x_after_rz: np.ndarray, z_prev: np.ndarray, alpha: float, beta: float) -> np.ndarray:
    """The x axis of frame i given the x after joint i's Rz (x_i of the normal) and its Rx(alpha) Ry(beta):
    Rx leaves x alone, Ry(beta) tilts it towards -z of the rotated frame."""
    if beta == 0.0:
        return x_after_rz
    y = np.cross(z_prev, x_after_rz)
    z_rot = y * -math.sin(alpha) + z_prev * math.cos(alpha)  # Rx(alpha) applied to z
    return x_after_rz * math.cos(beta) - z_rot * math.sin(beta)


def _tool_points(
    model: KinematicModel, T_tb: np.ndarray, q: np.ndarray, p: np.ndarray, smr: np.ndarray, last: list[Sweep]
) -> dict[int, np.ndarray]:
    """Each SMR of the last joint's sweeps in the model's flange frame (mean over its rows)."""
    from hil.geometry.kinematics import forward_kinematics

    rows = np.concatenate([s.rows for s in last])
    T = T_tb @ forward_kinematics(model, q[rows])
    local = np.einsum("nji,nj->ni", T[:, :3, :3], p[rows] - T[:, :3, 3])
    return {int(k): local[smr[rows] == k].mean(axis=0) for k in np.unique(smr[rows])}


def robot_file_text(model: KinematicModel, comment: str = "", coupling: JointCoupling | None = None) -> str:
    """The model as a robot definition file (convention = "dh", hayati_beta where axes are parallel; the
    measured beta itself is left to calibration, the file format holds none), with the controller's
    `coupling` and its interaction limits when the arm has one."""
    lines = [f"# {line}" for line in comment.splitlines()] if comment else []
    lines += [f"name = {json.dumps(model.name)}", 'convention = "dh"', ""]
    for i in range(model.n_joints):
        lo, hi = np.rad2deg(model.joint_limits[i])
        lines += [
            "[[joint]]",
            f"d_mm = {model.d[i] * 1e3:.6f}",
            f"a_mm = {model.a[i] * 1e3:.6f}",
            f"alpha_deg = {math.degrees(model.alpha[i]):.8f}",
            f"theta_offset_deg = {math.degrees(model.theta[i]):.8f}",
            f"hayati_beta = {'true' if model.uses_beta[i] else 'false'}",
            f"limits_deg = [{lo:g}, {hi:g}]",
            "",
        ]
    if coupling is not None:
        lines += coupling_lines(coupling)
    return "\n".join(lines)


def coupling_lines(coupling: JointCoupling) -> list[str]:
    """A coupling as the `[coupling]` table of a robot file (hil.geometry.coupling)."""
    rows = ",\n".join(
        f"    [{', '.join(f'{v:g}' for v in row)}]" for row in coupling.kinematic_from_controller
    )
    lines = [f"# {coupling.describe()}", "[coupling]", f"kinematic_from_controller = [\n{rows},\n]", ""]
    for limit in coupling.limits:
        lines += [
            f"# {limit.describe()}",
            "[[coupling.limit]]",
            f"controller = [{', '.join(f'{v:g}' for v in limit.coefficients)}]",
            f"range_deg = [{math.degrees(limit.lower_rad):.10g}, {math.degrees(limit.upper_rad):.10g}]",
            "",
        ]
    return lines
