"""The other configurations of a six-joint arm with parallel joints 2 and 3 and a spherical wrist, as IK seeds.

Such an arm (most industrial arms: FANUC, ABB, KUKA, Yaskawa; not UR's offset wrist, which has its closed
form in hil.geometry.ik) puts its wrist centre where the tool pose asks in up to four ways: the base turned
towards it or half a turn away (the shoulder), and, in the plane joints 2 and 3 turn in, the elbow on either
side of the line from joint 2's axis to the wrist centre (the two triangles of upper arm and forearm). The
wrist then orients the tool in two ways (joint 5 one way or the other). `arm_configuration_seeds` turns one
joint set into the eight joint sets whose arm stands in each of those ways, the wrist as it was or flipped:
exact for the elbow about the same base angle, approximate for the shoulder turned when the arm has a sideways
offset; seeds, which the IK makes exact. Nothing here knows about bodies or limits.
"""

from __future__ import annotations

import numpy as np

from hil.geometry.kinematics import KinematicModel, link_frames

WRIST_CENTRE_FRAME = 4  # frame 4's origin: where the axes of joints 4, 5 and 6 meet on a spherical wrist


def has_parallel_shoulder_and_elbow(model: KinematicModel, tol_rad: float = 1e-3) -> bool:
    """True for a six-joint model whose joints 2 and 3 turn about parallel axes (to `tol_rad`: a calibrated
    model's Hayati beta tilts them a little), the arms whose elbow has two sides in one plane."""
    if model.n_joints != 6:
        return False
    frames = link_frames(model, np.zeros((1, 6)))[0]
    return bool(abs(float(frames[1, :3, 2] @ frames[2, :3, 2])) > np.cos(tol_rad))


def arm_configuration_seeds(model: KinematicModel, q: np.ndarray) -> np.ndarray:
    """(8, N, 6) joint sets for the tool poses of q (N, 6): the shoulder as in q or turned half a turn,
    the elbow on either side, the wrist as in q or flipped (q4 + pi, -q5, q6 + pi). Not wrapped into
    any limits; one of the eight is q itself."""
    q = np.atleast_2d(np.asarray(q, float))
    wrist_centre = link_frames(model, q)[:, WRIST_CENTRE_FRAME, :3, 3]
    arms = []
    for turn in (0.0, np.pi):
        turned = q.copy()
        turned[:, 0] += turn
        arms += _both_elbows(model, turned, wrist_centre)
    flip = np.array([0.0, 0.0, 0.0, np.pi, 0.0, np.pi])
    flipped = [arm * np.array([1, 1, 1, 1, -1, 1]) + flip for arm in arms]
    return np.stack(arms + flipped)


def _both_elbows(model: KinematicModel, q: np.ndarray, wrist_centre_m: np.ndarray) -> list[np.ndarray]:
    """q (N, 6) with joints 2 and 3 set so that the wrist centre lies (as near as the plane allows) on
    `wrist_centre_m` (N, 3), the elbow on one side and on the other of the line from joint 2's axis."""
    frames = link_frames(model, q)
    o1, axis = frames[:, 1, :3, 3], frames[:, 1, :3, 2]  # joint 2's axis
    o2, axis3 = frames[:, 2, :3, 3], frames[:, 2, :3, 2]  # joint 3's axis, parallel
    same_way = np.sign(np.sum(axis * axis3, axis=1))  # joint 3 turns about +axis or -axis
    upper = _in_plane(o2 - o1, axis)
    forearm = _in_plane(frames[:, WRIST_CENTRE_FRAME, :3, 3] - o2, axis)
    to_wrist = _in_plane(wrist_centre_m - o1, axis)
    L2, L3, d = (np.linalg.norm(v, axis=1) for v in (upper, forearm, to_wrist))
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_a = np.clip((L2**2 + d**2 - L3**2) / (2.0 * L2 * d), -1.0, 1.0)  # angle at joint 2's axis
    a = np.arccos(np.nan_to_num(cos_a, nan=1.0))
    out = []
    for side in (1.0, -1.0):
        elbow = _turned(to_wrist, axis, side * a) * (L2 / np.maximum(d, 1e-12))[:, None]
        turn2 = _angle_about(axis, upper, elbow)
        # joint 2 turns upper arm and forearm together: the forearm's angle from the upper arm is joint 3's
        turn3 = same_way * (_angle_about(axis, elbow, to_wrist - elbow) - _angle_about(axis, upper, forearm))
        seed = q.copy()
        seed[:, 1] += turn2
        seed[:, 2] += turn3
        out.append(seed)
    return out


def _in_plane(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """v (N, 3) less its component along the unit axis (N, 3)."""
    return v - np.sum(v * axis, axis=1, keepdims=True) * axis


def _angle_about(axis: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) the signed angle about the unit axis (N, 3) that turns a onto b (both in its plane)."""
    return np.arctan2(np.sum(axis * np.cross(a, b), axis=1), np.sum(a * b, axis=1))


def _turned(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """v (N, 3), perpendicular to the unit axis, turned about it by angle (N,) (Rodrigues)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(axis, v) * s
