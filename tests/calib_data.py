"""Datasets for the calibration tests: synthetic (from hil.geometry.kinematics only) and from the simulated cell."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from hil.data.dataset import make_dataset
from hil.geometry.kinematics import forward_kinematics, measured_point
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform
from hil.model.calibrated_model import CalibratedModel
from hil.model.effects import EffectContext, make_effect


def ur10_joints(rng: np.random.Generator, n: int) -> np.ndarray:
    """Joint sets spread over a UR10's working volume in front of it (elbow up)."""
    return np.column_stack(
        [
            rng.uniform(-1.2, 1.2, n),
            rng.uniform(-2.3, -0.7, n),
            rng.uniform(0.6, 2.3, n),
            rng.uniform(-2.5, -0.5, n),
            rng.uniform(-2.2, -0.9, n),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )


ANGLE_NOISE_RAD = np.deg2rad(0.01)  # a 6-DoF probe's stated noise (hil's default)
POSITION_NOISE_M = 15e-6  # the tracker's MPE model at ~2.5 m, 1 sigma


def wrist_cyclic_campaign(n: int = 250, seed: int = 4, angle_noise_rad: float = ANGLE_NOISE_RAD):
    """A UR10 whose joint 6 has a once-per-turn error (0.02 deg) while the SMR sits on the joint-6 axis: the
    error turns the probe but does not move the SMR."""
    return wrist_cyclic_campaigns((n,), seed, angle_noise_rad)[0]


def wrist_cyclic_campaigns(sizes: tuple[int, ...], seed: int = 4, angle_noise_rad: float = ANGLE_NOISE_RAD):
    """Campaigns of `sizes` random poses each of one `wrist_cyclic_campaign` cell (a 6-DoF probe's position
    and orientation per row), measured one after the other: the first is that campaign, the next ones
    validation poses of the same arm."""
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    errors = {nm: rng.normal(0, 3e-4 if nm[0] in "ad" else 5e-4) for nm in nominal.param_names}
    errors |= {"a6": 0.0, "alpha6": 0.0}  # keep the flange's z axis the joint-6 axis
    true = nominal.with_errors(errors)
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    tool = np.array([0.0, 0.0, 0.11])
    R_flange_probe = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    out = []
    for n in sizes:
        q = ur10_joints(rng, n)
        dq = np.zeros_like(q)
        dq[:, 5] = 0.3e-3 * np.sin(q[:, 5]) + 0.15e-3 * np.cos(q[:, 5])
        T_flange = forward_kinematics(true, q + dq)
        p = (T_flange[:, :3, :3] @ tool + T_flange[:, :3, 3]) @ T[:3, :3].T + T[:3, 3]
        p += rng.normal(0, POSITION_NOISE_M, p.shape)
        R = T[:3, :3] @ T_flange[:, :3, :3] @ R_flange_probe
        R = Rotation.from_rotvec(rng.normal(0, angle_noise_rad, (n, 3))).as_matrix() @ R
        df = make_dataset(q, p, smr=1, R_tracker_probe=R)
        df.attrs["position_noise_m"] = POSITION_NOISE_M
        out.append(df)
    return out


def synthetic(n: int = 200, seed: int = 0, noise_m: float = 15e-6):
    """A UR10 with random DH errors, a random tracker pose and tool point; returns (truth, frame, make)."""
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    errors = {nm: rng.normal(0, 3e-4 if nm[0] in "ad" else 5e-4) for nm in nominal.param_names}
    true = nominal.with_errors(errors)
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    tool = np.array([0.03, -0.02, 0.11])

    def make(k: int, noise: float = noise_m) -> tuple[np.ndarray, np.ndarray]:
        q = ur10_joints(rng, k)
        return q, measured_point(true, q, T, tool) + rng.normal(0, noise, (k, 3))

    q, p = make(n)
    truth = {"model": true, "T_tracker_base": T, "tool": tool}
    return truth, make_dataset(q, p, smr=1), make


def cell_datasets(step_m: float = 0.1, n_val: int = 100, seed: int = 0, **config):
    """A grid campaign (training) and random held-out poses (validation) on the simulated UR10 cell."""
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, **config))
    train = simulate_campaign(cell, grid_joints(cell, step_m=step_m, seed=seed))
    val = simulate_campaign(cell, held_out_joints(cell, n_val, seed=seed + 1))
    return cell, train, val


def true_effect_model(train, robot: str, families: tuple[str, ...]):
    """The model a user who knew the cell's effects would fit: geometry plus every candidate of those
    families the data can show (the yardstick of the diagnosis goals)."""
    return true_effect_fit(train, robot, families).model


def true_effect_fit(train, robot: str, families: tuple[str, ...], true_values: dict | None = None):
    """`true_effect_model`'s fit (its CalibrationResult: the coefficients' standard errors too). With
    `true_values` ({family: coefficient}, for effects of one coefficient) those families are held at the values
    the simulated cell applies, and only the rest is fitted: the model of a user who knew those effects exactly,
    not merely their families."""
    from hil.analysis.calibration.solve import calibrate
    from hil.data.dataset import joints_rad
    from hil.model.calibrated_model import initial_model
    from hil.model.effects import EffectContext, candidate_effects

    model = initial_model(robot, train)
    ctx = EffectContext.from_frame(train, joints_rad(train))
    for eff in candidate_effects(ctx, model.nominal, [], families):
        if true_values and eff.family in true_values:
            eff.params = np.array([true_values[eff.family]], dtype=float)
            eff.state["held"] = True
        model = model.with_effect(eff)
    return calibrate(train, model, "ridge")


def compliant_ur10(
    seed: int, tools_m: dict[int, np.ndarray], context_tool_m: np.ndarray, n_poses: int
) -> CalibratedModel:
    """A calibrated UR10 for compensation tests: geometric errors, a tracker 2 m away, gravity compliance on
    joints 2 and 3 (prepared on `n_poses` random poses carrying `context_tool_m`) and the given tool points."""
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    kin = nominal.with_errors({n: rng.normal(0, 3e-4 if n[0] in "ad" else 5e-4) for n in nominal.param_names})
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    q = ur10_joints(rng, n_poses)
    ctx = EffectContext(q, p_flange_tool=np.tile(context_tool_m, (len(q), 1)))
    effects = []
    for j in (2, 3):
        eff = make_effect("gravity_compliance", j)
        assert eff.prepare(ctx, nominal)  # the torque from the UR10's link masses: one compliance
        eff.params = np.array([rng.uniform(0.5e-5, 1.5e-5)])  # rad/(N m): 67-200 kN m/rad
        effects.append(eff)
    return CalibratedModel("ur10", nominal, kin, T, tools_m, effects)


def record_validated_campaign(store, model: CalibratedModel, validation) -> None:
    """Write into `store` (a campaign file or the shared store) what a finished campaign holds for compensating
    its validation targets: the robot in a station snapshot, `model`'s registration and nest 1, and the rows of
    `validation` as grid_sampling's validation points v0, v1, ..."""
    from hil.data.dataset import joints_rad, points_m
    from hil.data.store import MeasurementRecord

    store.add_snapshot({"cell": {"robot": {"model": model.robot}}})
    store.finish_step("registration", "fit", {"T_tracker_base": model.T_tracker_base.tolist()})
    store.finish_step(
        "tool_fit", "fit", {"nests_flange_mm": {"1": (np.asarray(model.tools[1]) * 1e3).tolist()}}
    )
    for i, (q, p) in enumerate(zip(joints_rad(validation), points_m(validation), strict=True)):
        store.record_measurement(
            MeasurementRecord(
                procedure="grid_sampling", step="validation", point_id=f"v{i}", q_target_rad=q, q_rad=q,
                T_base_flange=np.eye(4), p_tracker_m=p, spread_m=np.zeros(3), std_m=np.zeros(3), shots=10,
                rejected_shots=(), smr=1, location="nest1", temperature_c=20.0, pressure_hpa=1013.0,
                humidity_pct=40.0, timestamp_s=1.7e9 + i,
            )
        )  # fmt: skip
