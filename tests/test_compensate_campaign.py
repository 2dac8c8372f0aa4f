"""`hil compensate model.json CAMPAIGN -o JOINTS.csv`: the targets a campaign file holds, compensated.

The campaign is written through CampaignStore as a session writes it (snapshot, registration, tool fit, grid
and validation measurements, the pseudo-target loop's pinned targets), no simulator. The model is the truth
here: its public `predict` at the written joints must land on the targets the test computes on its own.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from calib_data import ur10_joints
from scipy.spatial.transform import Rotation

from hil.calibrated_model import CalibratedModel
from hil.dataset import make_dataset
from hil.effects import EffectContext, make_effect
from hil.kinematics import forward_kinematics
from hil.robots import get_robot
from hil.se3 import make_transform, transform_points
from hil.store import CampaignStore, MeasurementRecord
from tests.cli_in_process import hil_in_process

pytestmark = pytest.mark.timeout(120)
NESTS_MM = np.array([[30.0, -20.0, 110.0], [-40.0, 25.0, 95.0], [10.0, 45.0, 120.0]])  # the drawing
FIT_MM = NESTS_MM[:2] + [[0.05, -0.03, 0.02], [-0.04, 0.06, 0.01]]  # the tool fit (nests 1, 2)
Q_COLS = [f"q{i}_rad" for i in range(1, 7)]


def true_model(seed: int = 0) -> CalibratedModel:
    """A calibrated UR10 with geometric errors, gravity compliance on joints 2 and 3 and two nests' tool points."""
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    kin = nominal.with_errors({n: rng.normal(0, 3e-4 if n[0] in "ad" else 5e-4) for n in nominal.param_names})
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    q = ur10_joints(rng, 100)
    ctx = EffectContext(q, p_flange_tool=np.tile(FIT_MM[0] / 1e3, (len(q), 1)))
    effects = []
    for j in (2, 3):
        eff = make_effect("gravity_compliance", j)
        assert eff.prepare(ctx, nominal)
        eff.params = rng.normal(0.0, 1e-3, len(eff.params))
        effects.append(eff)
    tools = {1: FIT_MM[0] / 1e3 + 1e-4, 2: FIT_MM[1] / 1e3 - 1e-4}
    return CalibratedModel("ur10", nominal, kin, T, tools, effects)


def registration(model: CalibratedModel) -> np.ndarray:
    """The campaign's registration: the model's base, off by about a millimetre (as a Kabsch fit is)."""
    return make_transform(
        Rotation.from_rotvec([2e-4, -1e-4, 3e-4]).as_matrix() @ model.T_tracker_base[:3, :3],
        model.T_tracker_base[:3, 3] + [8e-4, -5e-4, 3e-4],
    )


def record(step: str, point_id: str, q: np.ndarray, smr: int, t_s: float, location: str | None = None):
    return MeasurementRecord(
        procedure="grid_sampling" if step in ("grid", "validation") else "registration",
        step=step,
        point_id=point_id,
        q_target_rad=q,
        q_rad=q + 1e-5,
        T_base_flange=np.eye(4),
        p_tracker_m=[2.0, 0.3, 0.1],
        spread_m=[5e-6] * 3,
        std_m=[5e-6] * 3,
        shots=3,
        rejected_shots=(),
        smr=smr,
        location=location or f"nest{smr}",
        temperature_c=20.0 + 0.01 * t_s,
        pressure_hpa=1013.0,
        humidity_pct=40.0,
        timestamp_s=1.7e9 + t_s,
    )


def write_campaign(path, model: CalibratedModel, loop_targets: np.ndarray | None = None) -> dict:
    """A campaign as the runner leaves it; returns the commanded joints, nests and ids per step."""
    rng = np.random.default_rng(5)
    layout: dict = {}
    with CampaignStore(path) as store:
        store.add_snapshot({"cell": {"robot": {"model": "ur10"}, "tool": {"nests_flange_mm": NESTS_MM.tolist()}}})
        store.record_measurement(record("poses", "r01", ur10_joints(rng, 1)[0], 1, 0.0))
        store.finish_step("registration", "fit", {"T_tracker_base": registration(model).tolist(), "rms_mm": 0.9})
        store.finish_step("tool_fit", "fit", {"nests_flange_mm": {"1": FIT_MM[0].tolist(), "2": FIT_MM[1].tolist()}})
        t = 10.0
        for step, n, prefix in (("grid", 8, "g1-"), ("validation", 5, "v")):
            q = ur10_joints(rng, n)
            smr = np.where(np.arange(n) % 3 == 2, 2, 1) if step == "grid" else np.ones(n, int)
            ids = [f"{prefix}{k:04d}" for k in range(n)]
            for i in range(n):
                store.record_measurement(record(step, ids[i], q[i], int(smr[i]), t))
                t += 4.0
            if step == "grid":  # a face probe of the same step: not in a nest, no target
                store.record_measurement(record(step, "g1-face", q[0], 0, t, location="face"))
            layout[step] = {"q": q, "smr": smr, "ids": ids}
        if loop_targets is not None:
            store.finish_step("pseudo_target", "targets", {"targets_m": loop_targets.tolist(), "smrs": 3})
    return layout


def commanded_points(model: CalibratedModel, q: np.ndarray, smr: np.ndarray) -> np.ndarray:
    """Where the commanded joints aim the SMR: nominal UR10, the tool fit's nest, the campaign's registration."""
    T = forward_kinematics(get_robot("ur10"), q)
    p_flange = FIT_MM[smr - 1] / 1e3
    p_base = np.einsum("nij,nj->ni", T[:, :3, :3], p_flange) + T[:, :3, 3]
    return transform_points(registration(model), p_base)


def predicted(model: CalibratedModel, q: np.ndarray, smr: np.ndarray) -> np.ndarray:
    """The model's public prediction of the SMR centre, per row's nest."""
    return model.predict(make_dataset(q, np.zeros((len(q), 3)), smr=smr))





@pytest.fixture(scope="module")
def model():
    return true_model()


def test_grid_and_validation_targets_are_the_commanded_points_compensated_per_nest(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    layout = write_campaign(tmp_path / "job.sqlite", model)
    code, out, err = hil_in_process("compensate", "model.json", "job.sqlite", "-o", "val.csv", cwd=tmp_path, capsys=capsys)
    assert code == 0, err
    assert "5 validation targets" in err  # no loop in the campaign: the validation step is the default
    df = pd.read_csv(tmp_path / "val.csv")
    assert list(df["point_id"]) == layout["validation"]["ids"] and set(df["step_id"]) == {"validation"}

    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "grid.csv", "--step", "grid", "--threshold-mm", "0.001",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    df = pd.read_csv(tmp_path / "grid.csv")
    grid = layout["grid"]
    assert list(df["point_id"]) == grid["ids"]  # the face probe has no nest: no target
    np.testing.assert_array_equal(df["smr"], grid["smr"])
    target = commanded_points(model, grid["q"], grid["smr"])
    np.testing.assert_allclose(df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1e3, target, atol=1e-9)
    assert (df["status"] == "ok").all() and (df["error_mm"] < 0.001).all()
    assert (df["initial_error_mm"] > 0.05).all()  # there was something to compensate
    reached = predicted(model, df[Q_COLS].to_numpy(), grid["smr"])
    assert np.linalg.norm(reached - target, axis=1).max() < 1e-6  # each nest on its own target
    wrong_nest = predicted(model, df[Q_COLS].to_numpy(), np.ones(len(df), int))
    assert np.linalg.norm(wrong_nest - target, axis=1)[grid["smr"] == 2].min() > 0.05
    assert np.abs(df[Q_COLS].to_numpy() - grid["q"]).max() < 0.01  # the commanded posture, corrected
    np.testing.assert_allclose(df["t_s"], 10.0 + 4.0 * np.arange(len(df)))  # time of each point, for thermal models


def test_loop_targets_are_poses_by_default_and_unreachable_ones_stay_marked(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    q = ur10_joints(np.random.default_rng(7), 4)
    T = forward_kinematics(model.kinematic, q)
    T[:, :3, 3] = predicted(model, q, np.ones(4, int))
    T[:, :3, :3] = model.T_tracker_base[:3, :3] @ T[:, :3, :3]  # near the model's reach, orientation kept
    T[3, :3, 3] = transform_points(model.T_tracker_base, np.array([[4.0, 0.0, 0.5]]))[0]
    write_campaign(tmp_path / "job.sqlite", model, loop_targets=T)
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.sqlite", "-o", "loop.csv", "--threshold-mm", "0.002",
        cwd=tmp_path, capsys=capsys,
    )  # fmt: skip
    assert code == 0, err
    assert "4 loop targets" in err
    df = pd.read_csv(tmp_path / "loop.csv")
    assert list(df["point_id"]) == ["t001", "t002", "t003", "t004"] and set(df["step_id"]) == {"loop"}
    assert list(df["status"]) == ["ok"] * 3 + ["unreachable"]
    assert df.loc[3, Q_COLS].isna().all()
    rv = np.deg2rad(df[["rx_deg", "ry_deg", "rz_deg"]].to_numpy())
    np.testing.assert_allclose(Rotation.from_rotvec(rv).as_matrix(), T[:, :3, :3], atol=1e-9)
    assert (df["rotation_error_deg"][:3] < 1e-3).all() and (df["error_mm"][:3] < 0.002).all()
    reached = predicted(model, df[Q_COLS].to_numpy()[:3], np.ones(3, int))
    assert np.linalg.norm(reached - T[:3, :3, 3], axis=1).max() < 2e-6


def test_bad_campaign_input_exits_2_with_what_to_do(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    CampaignStore(tmp_path / "empty.sqlite").close()
    with CampaignStore(tmp_path / "reg.sqlite") as store:
        store.record_measurement(record("poses", "r01", ur10_joints(np.random.default_rng(1), 1)[0], 1, 0.0))
    write_campaign(tmp_path / "job.sqlite", model)
    with CampaignStore(tmp_path / "nest3.sqlite") as store:
        store.add_snapshot({"cell": {"robot": {"model": "ur10"}, "tool": {"nests_flange_mm": NESTS_MM.tolist()}}})
        store.finish_step("registration", "fit", {"T_tracker_base": registration(model).tolist()})
        store.record_measurement(record("grid", "g1-0000", ur10_joints(np.random.default_rng(2), 1)[0], 3, 1.0))
    pd.DataFrame({"x_mm": [2000.0], "y_mm": [0.0], "z_mm": [0.0]}).to_csv(tmp_path / "t.csv", index=False)
    cases = [
        (["empty.sqlite"], "holds no targets (it holds: no measurements)"),
        (["reg.sqlite"], "holds no targets (it holds: registration/poses (1))"),
        (["job.sqlite", "--step", "hole3"], "--step 'hole3' is not a target source"),
        (["job.sqlite", "--step", "loop"], "has no loop targets; it has: validation (5), grid (8)"),
        (["nest3.sqlite"], "targets of SMR nest(s) [3], but the model has tool points for nests [1, 2]"),
        (["t.csv", "--step", "grid"], "--step picks the targets of a campaign file"),
    ]
    for args, message in cases:
        code, out, err = hil_in_process("compensate", "model.json", *args, "-o", "j.csv", cwd=tmp_path, capsys=capsys)
        assert code == 2, (args, err)
        assert message in err and "what to do: " in err, err
    assert not (tmp_path / "j.csv").exists()
    code, out, err = hil_in_process("compensate", "model.json", "job.sqlite", "-o", "job.sqlite", cwd=tmp_path, capsys=capsys)
    assert code == 2 and "would be overwritten" in err
