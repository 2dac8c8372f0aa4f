"""Several SMRs per pose and a 6-DoF probe's orientation as extra equations (issue 11 section 3).

Model-only: campaigns of the simulated cell (fakes.campaign, batch physics, no sockets), a few seconds.
"""

import json
import warnings
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from sim_campaigns import grid_joints, held_out_joints

from fakes.campaign import Probe, simulate_campaign
from fakes.cell import SimCellConfig, SimulatedCell
from hil.analysis.calibration.folds import spatial_folds
from hil.analysis.calibration.noise_floor import estimate_noise_floor
from hil.analysis.calibration.solve import Problem, calibrate, confounded_pairs, parameter_correlations
from hil.data.dataset import (
    ORIENTATION_COLUMNS,
    DatasetError,
    convert_orientation_convention,
    orientations,
    pose_ids,
    validate_dataset,
)
from hil.geometry.kinematics import forward_kinematics, kinematic_rotation_jacobian
from hil.geometry.robots import get_robot
from hil.model.calibrated_model import CalibratedModel, initial_model
from hil.model.effects import EffectContext, make_effect

WRIST = ("theta5", "d5", "a5", "alpha5")  # joint 5: positions see it only through the short tool lever


def _cell(seed: int) -> SimulatedCell:
    return SimulatedCell(SimCellConfig(robot="ur10", seed=seed, compliance=False))


@pytest.fixture(scope="module")
def three_smr():
    cell = _cell(2)
    q = grid_joints(cell, step_m=0.2, seed=2)
    return cell, q, simulate_campaign(cell, q, nests=[1, 2, 3])


@pytest.fixture(scope="module")
def probe_campaign():
    cell = _cell(1)
    probe = Probe.drawn(1)
    df = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=1), probe=probe)
    return cell, probe, df


def _rotation_fd(rot, x_count: int, h: float = 1e-6) -> np.ndarray:
    """Finite-difference angular Jacobian (N, 3, P): log(R(x + h e_i) R(x)^T) / h."""
    R0 = rot(np.zeros(x_count))
    cols = []
    for i in range(x_count):
        dx = np.zeros(x_count)
        dx[i] = h
        cols.append(Rotation.from_matrix(rot(dx) @ np.swapaxes(R0, 1, 2)).as_rotvec() / h)
    return np.stack(cols, axis=2)


@pytest.mark.parametrize("use_beta", [True, False])
def test_rotation_jacobian_matches_finite_differences(use_beta):
    rng = np.random.default_rng(4)
    nominal = get_robot("ur10", use_beta=use_beta)
    errors = {n: rng.normal(0, 1e-3) for n in nominal.param_names}  # beta too: its axis moves with alpha
    kin = nominal.with_errors(errors)
    q = rng.uniform(-2.5, 2.5, (7, 6))
    R, J = kinematic_rotation_jacobian(kin, q)
    np.testing.assert_allclose(R, forward_kinematics(kin, q)[:, :3, :3], atol=1e-12)
    fd = _rotation_fd(
        lambda dx: forward_kinematics(kin.with_params(kin.params + dx), q)[:, :3, :3], len(kin.params)
    )
    np.testing.assert_allclose(J, fd, atol=2e-6)
    # The full model: base, tool points, a probe per nest and a joint effect, in the model's parameter order.
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.0, 2.0]).as_matrix()
    T[:3, 3] = [1.5, -0.4, 0.2]
    model = CalibratedModel(
        "ur10",
        nominal,
        kin,
        T,
        {1: np.array([0.03, -0.02, 0.11]), 2: np.array([-0.06, 0.04, 0.09])},
        probes={k: Rotation.from_rotvec(rng.normal(0, 0.5, 3)).as_matrix() for k in (1, 2)},
    )
    ctx = EffectContext(q)
    eff = make_effect("cyclic", 2)
    assert eff.prepare(ctx, nominal)
    model = model.with_effect(replace(eff, params=rng.normal(0, 1e-3, len(eff.params))))
    smr = np.array([1, 2, 1, 2, 2, 1, 1])
    ctx.p_flange_tool = model._row_tools(smr)
    R_pred, J_full = model.rotation_jacobian_ctx(ctx, smr)
    np.testing.assert_allclose(R_pred, model.predict_rotation_ctx(ctx, smr), atol=1e-12)
    fd = _rotation_fd(
        lambda dx: model.apply_increment(dx).predict_rotation_ctx(ctx, smr), len(model.param_names)
    )
    np.testing.assert_allclose(J_full, fd, atol=2e-6)
    assert (
        np.abs(J_full[:, :, model.param_names.index("probe2_rz")][smr == 1]).max() == 0
    )  # one probe per nest


def test_several_smrs_per_pose_are_extra_equations(three_smr):
    cell, q, df = three_smr
    assert len(df) == 3 * len(q) and df["smr"].tolist()[:6] == [1, 2, 3, 1, 2, 3]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "duplicated rows": the three readings of a pose differ
        assert len(validate_dataset(df)) == len(df)
    poses = pose_ids(df)
    assert poses.max() + 1 == len(q) and np.all(np.bincount(poses) == 3)
    # Three nests read at one pose are no repeated poses: the noise floor stays the tracker's.
    assert "tracker noise model" in estimate_noise_floor(df).method
    both = calibrate(df, "ur10")
    one = calibrate(df[df["smr"] == 1].reset_index(drop=True), "ur10")
    assert sorted(both.model.tools) == [1, 2, 3]
    nests = np.asarray(cell.ground_truth()["tool_nests_flange_m"])
    for k in (2, 3):  # theta6.. merge into every tool point alike: compare the layout, not raw values
        got = np.linalg.norm(both.model.tools[k] - both.model.tools[1])
        assert got == pytest.approx(np.linalg.norm(nests[k - 1] - nests[0]), abs=1e-5)
    assert both.rms_mm < 0.03 and not both.outliers.any()
    # Three lever arms per pose see the wrist's orientation: joint 5's standard errors shrink far more than
    # the sqrt(3) that three times the rows alone would give, and the conditioning improves.
    for name in WRIST:
        assert one.std[name] / both.std[name] > 3.0, name
    assert both.identifiability.condition_after < one.identifiability.condition_after


def test_folds_keep_every_smr_of_a_pose_together(three_smr):
    _, q, df = three_smr
    prob = Problem.from_frame(initial_model("ur10", df), df)
    poses = pose_ids(df)
    for folds in (prob.spatial_folds(5, 0), prob.random_folds(5, 0)):
        label = np.full(len(df), -1)
        for i, f in enumerate(folds):
            label[f] = i
        assert (label >= 0).all()
        assert all(len(set(label[poses == p])) == 1 for p in range(len(q)))
    # k-means on the rows themselves would split poses (a held-out SMR predicted from its own pose).
    naive = np.full(len(df), -1)
    for i, f in enumerate(spatial_folds(prob.measured, 5, 0)):
        naive[f] = i
    assert sum(len(set(naive[poses == p])) > 1 for p in range(len(q))) > 0
    # Nest by nest in separate passes over the grid: the same joints are still one pose.
    passes = df.sort_values("smr", kind="stable").reset_index(drop=True)
    by_pass = pose_ids(passes)
    assert by_pass.max() + 1 == len(q) and np.all(np.bincount(by_pass) == 3)
    # A subset (as the diagnosis screens on inliers) keeps its poses together too.
    sub = prob.subset(np.flatnonzero(poses % 4 != 1))
    assert sum(len(f) for f in sub.spatial_folds(5, 0)) == len(sub.measured)


def test_probe_orientation_recovers_what_positions_see_poorly(probe_campaign):
    cell, probe, df = probe_campaign
    truth = cell.ground_truth()["parameter_errors"]
    with_rot = calibrate(df, "ur10")
    without = calibrate(df.drop(columns=list(ORIENTATION_COLUMNS)), "ur10")
    # 3-D RMS of the rotation residual at the probe's 0.01 deg per axis noise: sqrt(3) * 0.01 deg.
    assert with_rot.orientation_rms_deg == pytest.approx(np.sqrt(3) * 0.01, rel=0.25)
    assert without.orientation_rms_deg is None and with_rot.rms_mm < 0.03
    dropped = {d["name"]: d for d in with_rot.identifiability.dropped}
    assert set(dropped) == {"theta1", "d1", "theta6", "d6", "a6", "alpha6"}
    assert dropped["theta6"]["merged_into"][0][0] == "probe1_rz"  # as d6 merges into the tool point
    a = {r["name"]: r for r in with_rot.parameter_table()}
    b = {r["name"]: r for r in without.parameter_table()}
    common = [n for n in cell.nominal.param_names if n in a and n in b]
    # At least as good everywhere: every estimate within 4 standard errors of the injected error, and the
    # standard errors never larger; joint 5 much better (std errors / 3, errors / 2 in RMS).
    for n in common:
        assert abs(a[n]["delta"] - truth[n]) < 4 * a[n]["std_ls"], n
        assert a[n]["std_ls"] <= 1.02 * b[n]["std_ls"], n
    assert all(b[n]["std_ls"] / a[n]["std_ls"] > 3 for n in WRIST)
    err = {
        k: np.sqrt(np.mean([(t[n]["delta"] - truth[n]) ** 2 for n in WRIST])) for k, t in (("a", a), ("b", b))
    }
    assert err["a"] < 0.5 * err["b"]
    # The probe's orientation (with theta6/alpha6 merged into it) predicts held-out poses' orientation.
    q_val = held_out_joints(cell, 30, seed=7)
    val = simulate_campaign(cell, q_val, probe=Probe(probe.R_flange_probe, angle_sigma_rad=0.0))
    R_err = Rotation.from_matrix(with_rot.model.predict_rotation(val) @ np.swapaxes(orientations(val), 1, 2))
    assert np.rad2deg(np.max(R_err.magnitude())) < 0.01


def test_angle_noise_weighs_the_rotation_equations(probe_campaign):
    _, _, df = probe_campaign
    positions_only = calibrate(df.drop(columns=list(ORIENTATION_COLUMNS)), "ur10").model
    noisy_probe = calibrate(df, "ur10", probe_angle_noise_rad=np.deg2rad(20.0)).model
    sharp_probe = calibrate(df, "ur10").model
    kin = lambda m: m.kinematic.params  # noqa: E731
    # A probe said to be 2000x noisier barely moves the fit away from the position-only one.
    assert (
        np.abs(kin(noisy_probe) - kin(positions_only)).max()
        < 0.05 * np.abs(kin(sharp_probe) - kin(positions_only)).max()
    )
    with pytest.raises(ValueError, match="angle noise"):
        calibrate(df, "ur10", probe_angle_noise_rad=0.0)


def test_orientation_columns_conventions_and_refusals(probe_campaign):
    _, _, df = probe_campaign
    R = orientations(df)
    intrinsic = df.copy()
    angles = np.rad2deg(Rotation.from_matrix(R).as_euler("XYZ"))
    intrinsic[list(ORIENTATION_COLUMNS)] = angles
    assert not np.allclose(orientations(intrinsic), R, atol=1e-6)  # read in the default: wrong
    np.testing.assert_allclose(
        orientations(convert_orientation_convention(intrinsic, "xyz-intrinsic")), R, atol=1e-9
    )
    with pytest.raises(ValueError, match="xyz-extrinsic or xyz-intrinsic"):
        convert_orientation_convention(df, "zyz")
    with pytest.raises(DatasetError, match="rx_deg, ry_deg, rz_deg"):
        validate_dataset(df.drop(columns=["rz_deg"]))
    bad = df.copy()
    bad.loc[4, "ry_deg"] = np.nan
    with pytest.raises(DatasetError, match="ry_deg.*row.*5"):
        validate_dataset(bad)
    # A `pose` column says which rows share a pose, whatever their joints.
    posed = df.assign(pose=np.arange(len(df)) // 2)
    assert pose_ids(validate_dataset(posed)).max() + 1 == (len(df) + 1) // 2


def test_model_file_keeps_the_probe(probe_campaign, tmp_path):
    _, _, df = probe_campaign
    model = calibrate(df, "ur10").model
    model.save(tmp_path / "m.json")
    back = CalibratedModel.load(tmp_path / "m.json")
    np.testing.assert_allclose(back.predict_rotation(df), model.predict_rotation(df), atol=1e-12)
    assert back.param_names == model.param_names and back.info["orientation"]["angle_noise_deg"] == 0.01
    positions_only = calibrate(df.drop(columns=list(ORIENTATION_COLUMNS)), "ur10").model
    with pytest.raises(ValueError, match="calibrate with orientation data"):
        positions_only.predict_rotation(df)


def test_cli_reads_the_convention_and_reports_orientation(probe_campaign, tmp_path, capsys):
    from hil.cli import main

    _, _, df = probe_campaign
    data = df.copy()
    data[list(ORIENTATION_COLUMNS)] = np.rad2deg(Rotation.from_matrix(orientations(df)).as_euler("XYZ"))
    data.to_csv(tmp_path / "probe.csv", index=False)
    args = ["calibrate", str(tmp_path / "probe.csv"), "-o", str(tmp_path / "m.json")]
    assert (
        main([*args, "--orientation-convention", "xyz-intrinsic", "--residuals", str(tmp_path / "r.csv")])
        == 0
    )
    assert pd.read_csv(tmp_path / "r.csv")["rot_deg"].median() < 0.03
    out = capsys.readouterr().out
    rms = [
        float(line.split("orientation RMS ")[1].split()[0])
        for line in out.splitlines()
        if "ridge-igg3:" in line
    ]
    assert rms and rms[0] < 0.03  # read in its own convention, the probe agrees with the arm
    assert "probe orientation SMR 1 in the flange" in out
    for bad in (["--orientation-convention", "zyz"], ["--probe-angle-noise-deg", "0"]):
        with pytest.raises(SystemExit) as exit_:  # refused by the option parser, before any work
            main([*args, *bad])
        assert exit_.value.code == 2 and bad[0] in capsys.readouterr().err
    # Read in the wrong (default) convention, the probe disagrees with the arm by tens of degrees: refused
    # before any fit (it would drag the positions off by millimetres), naming the columns and the option.
    wrong = ["calibrate", str(tmp_path / "probe.csv"), "-o", str(tmp_path / "wrong.json")]
    assert main(wrong) == 2
    err = capsys.readouterr().err
    assert "rx_deg, ry_deg, rz_deg" in err and "--orientation-convention" in err and "radians" in err
    assert not (tmp_path / "wrong.json").exists()


def test_diagnose_with_a_probe_finds_compliance_and_reports_orientation(tmp_path, capsys):
    from hil.cli import main

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=2))  # gravity compliance on
    df = simulate_campaign(cell, grid_joints(cell, step_m=0.15, seed=2), probe=Probe.drawn(2))
    df.to_csv(tmp_path / "probe.csv", index=False)
    argv = [
        "diagnose",
        str(tmp_path / "probe.csv"),
        "--json",
        str(tmp_path / "r.json"),
        "--html",
        str(tmp_path / "r.html"),
    ]
    assert main([*argv, "--families", "gravity_compliance", "--probe-angle-noise-deg", "0.01"]) == 0
    out = capsys.readouterr().out
    assert "6-DoF probe, geometric ridge_igg3 fit" in out and "6-DoF probe, final model" in out
    page = (tmp_path / "r.html").read_text()
    assert "deg (6-DoF probe)" in page and "6-DoF probe, final model (effects included)" in page
    report = json.loads((tmp_path / "r.json").read_text())
    assert {(e["name"], e["joint"]) for e in report["effects_added"]} == {
        ("gravity_compliance", 2),
        ("gravity_compliance", 3),
    }
    assert report["verdict"]["residual"] == "floor"
    assert report["calibration"]["ridge_igg3"]["orientation_rms_deg"] < 0.03
    # Joint 5's pairs that positions alone confound (theta5/a5, d5/alpha5) are separated by the probe: the
    # calibration's "confounded" notes, which the verdict carries as calibration_note cautions, are gone.
    cautions = report["verdict"]["cautions"]
    notes = [c["text"] for c in cautions if c["kind"] == "calibration_note"]
    assert all(
        isinstance(c, dict) and "kind" in c for c in cautions
    )  # records, as hil.report.html reads them
    assert not [t for t in notes if t.startswith("confounded")]
    positions_only = calibrate(df.drop(columns=list(ORIENTATION_COLUMNS)), "ur10")
    assert [n for n in positions_only.notes if n.startswith("confounded: theta5 and a5")]


def test_wrong_orientation_readings_are_refused_before_any_fit(probe_campaign):
    _, _, df = probe_campaign
    wrong_convention = convert_orientation_convention(df, "xyz-intrinsic")
    radians = df.assign(**{c: np.deg2rad(df[c]) for c in ORIENTATION_COLUMNS})
    for bad in (wrong_convention, radians):
        for solver in ("ridge", "lm"):
            with pytest.raises(
                ValueError, match=r"rx_deg, ry_deg, rz_deg.*--orientation-convention.*radians"
            ):
                calibrate(bad, "ur10", solver)
    # Right readings pass; a probe far noisier than its stated noise gets a note after the fit.
    assert not [n for n in calibrate(df, "ur10").notes if n.startswith("orientation")]
    stated_too_sharp = calibrate(df, "ur10", probe_angle_noise_rad=np.deg2rad(0.001))
    assert [
        n for n in stated_too_sharp.notes if n.startswith("orientation") and "--probe-angle-noise-deg" in n
    ]


def test_lm_judges_rotations_by_their_own_scale(probe_campaign):
    """With the angle noise set 10x too small the scaled rotation residuals are 10x the positions': IGG3
    keeps them (their own robust scale), and so must LM's robust loss, or the two solvers disagree."""
    _, _, df = probe_campaign
    angle = np.deg2rad(0.001)
    ridge = calibrate(df, "ur10", "ridge", probe_angle_noise_rad=angle)
    lm = calibrate(df, "ur10", "lm", probe_angle_noise_rad=angle)
    a = {r["name"]: r for r in ridge.parameter_table()}
    b = {r["name"]: r for r in lm.parameter_table()}
    # The solvers differ by ~0.5 standard errors at the right noise setting (prior, IGG3 vs soft L1) and
    # stay so; a loss with the positions' scale would push every rotation into its linear part (1.6 on theta5).
    for n in WRIST:
        assert abs(a[n]["value"] - b[n]["value"]) < 1.0 * a[n]["std_ls"], n
    assert not lm.outliers.any()


def test_ridge_prior_leaves_the_probe_orientation_free(probe_campaign):
    """The ridge prior holds the robot's geometry; the set-up (base, tools, probe) is fitted freely."""
    from hil.analysis.calibration.solve import full_values, solve_ridge_igg3

    _, _, df = probe_campaign
    model = initial_model("ur10", df)
    prob = Problem.from_frame(model, df, orientation=True)
    setup = np.array([n.startswith(("base_", "tool", "probe")) for n in model.param_names])
    plain = solve_ridge_igg3(model, prob, setup, ridge=0.0, robust=False, max_iter=20).model
    held = solve_ridge_igg3(model, prob, setup, ridge=1e3, robust=False, max_iter=20).model
    probe = np.array([n.startswith("probe") for n in model.param_names])
    start = full_values(model)[probe]
    assert np.abs(full_values(plain)[probe] - start).max() > 1e-4  # the initial probe estimate is refined
    # A prior that (wrongly) held the probe would keep it near the start however strong the data.
    np.testing.assert_allclose(full_values(held)[probe], full_values(plain)[probe], atol=1e-9)


def test_few_distinct_poses_give_no_fold_figures_instead_of_a_crash():
    """4 poses x 3 nests x 6 revisits: 72 rows but only 4 poses for the 5 spatial folds."""
    from hil.analysis.diagnosis.pipeline import DiagnosisOptions, run_diagnosis

    cell = _cell(1)
    q = np.tile(grid_joints(cell, step_m=0.3, seed=1)[:4], (6, 1))
    df = simulate_campaign(cell, q, nests=[1, 2, 3])
    assert len(df) == 72 and len(set(pose_ids(df))) == 4
    res = calibrate(df, "ur10")
    assert res.std_folds == {}  # too few poses for a spread over 5 folds of poses
    folds = Problem.from_frame(res.model, df).spatial_folds(5, 0)
    assert len(folds) == 4 and sorted(np.concatenate(folds).tolist()) == list(range(72))
    with pytest.raises(ValueError, match="4 distinct robot poses .* too few for 5-fold"):
        run_diagnosis(df, "ur10", options=DiagnosisOptions(families=("cyclic",)))


def test_spatial_folds_of_fewer_distinct_points_than_folds():
    pts = np.repeat(np.random.default_rng(0).normal(size=(3, 3)), 10, axis=0)
    assert sorted(len(f) for f in spatial_folds(pts, 5, 0)) == [10, 10, 10]
    assert [len(f) for f in spatial_folds(pts[:1], 5, 0)] == [1]


def _kmeans_folds_one_cluster_at_a_time(points: np.ndarray, k: int, seed: int, iters: int = 25) -> list:
    """spatial_folds as it was written first: every distance through an (N, K, 3) array, every cluster's mean
    on its own rows. The reference the vectorised one must equal, fold for fold."""
    rng = np.random.default_rng(seed)
    x = (points - points.mean(axis=0)) / (points.std(axis=0) + 1e-12)
    k = max(1, min(k, len(np.unique(x, axis=0))))
    centres = x[[rng.integers(len(x))]]
    for _ in range(1, k):
        d2 = np.min(((x[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        if d2.sum() <= 0:
            break
        centres = np.vstack([centres, x[rng.choice(len(x), p=d2 / d2.sum())]])
    for _ in range(iters):
        label = np.argmin(((x[:, None, :] - centres[None]) ** 2).sum(axis=2), axis=1)
        new = np.array(
            [x[label == c].mean(axis=0) if np.any(label == c) else centres[c] for c in range(len(centres))]
        )
        if np.allclose(new, centres):
            break
        centres = new
    return [f for f in (np.flatnonzero(label == c) for c in range(len(centres))) if len(f)]


def test_spatial_folds_are_the_per_cluster_k_means_folds_exactly():
    """The folds decide every held-out figure: the vectorised k-means gives the same folds as the per-cluster
    one on spread, flat and duplicated points (same sums in the same order, so the same labels)."""
    rng = np.random.default_rng(12)
    for trial in range(300):
        n = int(rng.integers(5, 500))
        pts = rng.normal(size=(n, 3)) * rng.uniform(0.05, 2.0, 3)
        if trial % 3 == 0:
            pts = np.round(pts, 1)  # repeated points and ties
        k, seed = int(rng.integers(1, 8)), int(rng.integers(0, 50))
        got, want = spatial_folds(pts, k, seed), _kmeans_folds_one_cluster_at_a_time(pts, k, seed)
        assert len(got) == len(want), trial
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)


def test_one_orientation_copied_onto_every_smr_row_of_a_pose_counts_once():
    cell = _cell(2)
    q = grid_joints(cell, step_m=0.2, seed=2)
    df = simulate_campaign(cell, q, nests=[1, 2, 3], probe=Probe.drawn(2))
    pose = pose_ids(df)
    copied = df.copy()  # a single-probe export: the pose's one reading on each of its SMR rows
    copied[list(ORIENTATION_COLUMNS)] = df.groupby(pose)[list(ORIENTATION_COLUMNS)].transform("first")
    first = copied[copied["smr"] == 1].reset_index(drop=True)  # each reading once
    model = initial_model("ur10", copied)
    kin = np.arange(len(model.nominal.param_names))

    def rotation_information(frame: pd.DataFrame) -> tuple[np.ndarray, float]:
        prob = Problem.from_frame(model, frame, orientation=True, position_noise=1e-5)
        J_rot = prob.evaluate(model)[1][:, 3:, kin].reshape(-1, len(kin))
        return J_rot.T @ J_rot, prob.n_rotation_readings

    info_copied, n_copied = rotation_information(copied)
    info_first, n_first = rotation_information(first)
    np.testing.assert_allclose(info_copied, info_first, rtol=1e-9, atol=1e-9 * np.abs(info_first).max())
    assert n_copied == pytest.approx(len(q)) and n_first == pytest.approx(len(q))
    # Independent readings of each row (as simulated) each count.
    assert rotation_information(df)[1] == pytest.approx(len(df))
    # The residual angles reported are the readings', not the weighted ones.
    res = calibrate(copied, "ur10")
    assert not res.outliers.any()  # copies judged on the scale of one reading
    R_err = orientations(copied) @ np.swapaxes(res.model.predict_rotation(copied), 1, 2)
    np.testing.assert_allclose(res.residual_rot_rad, Rotation.from_matrix(R_err).as_rotvec(), atol=1e-12)


def test_equation_count_message_counts_rotations_once_and_poses():
    cell = _cell(2)
    q = grid_joints(cell, step_m=0.3, seed=2)[:5]
    df = simulate_campaign(cell, q, nests=[1, 2, 3], probe=Probe.drawn(2))
    df[list(ORIENTATION_COLUMNS)] = df.groupby(pose_ids(df))[list(ORIENTATION_COLUMNS)].transform("first")
    with pytest.raises(ValueError, match=r"15 rows at 5 distinct poses give 60 equations"):
        calibrate(df, "ur10")


def test_confounded_pairs_leave_out_parameters_no_equation_moves(probe_campaign):
    # The diagnosis sets a noisy probe's rotations aside and asks for the confounded pairs on positions
    # alone: the probe's orientation in the flange then moves no equation and has no estimate. Its column is
    # zero and its variance zero up to rounding, which once divided into correlations like +5.7e141
    # ("a5 and probe1_rx correlate ..." on series A).
    _, _, df = probe_campaign
    result = calibrate(df, "ur10")
    names = result.model.param_names
    probe = [i for i, n in enumerate(names) if n.startswith("probe")]
    assert probe and all(names[i] in result.free for i in probe)
    positions = Problem.from_frame(result.model, df.drop(columns=list(ORIENTATION_COLUMNS)))
    r, J = positions.evaluate(result.model)
    assert np.all(J[..., probe] == 0.0)
    pairs = confounded_pairs(result, positions, evaluated=(r, J))
    assert {frozenset(p[:2]) for p in pairs} >= {frozenset(("theta5", "a5"))}  # positions confound these
    # Whether rounding leaves the zero column's variance exactly zero depends on the rest of the Jacobian
    # (a tiny variance of either sign otherwise): random columns, one zero, a5 made nearly theta5's; three of
    # these ten draws gave "a1 and probe1_rx correlate +3e132" here.
    for seed in range(10):
        rng = np.random.default_rng(seed)
        J = rng.normal(size=J.shape)
        J[..., probe[0]] = 0.0
        J[..., names.index("a5")] = J[..., names.index("theta5")] + 0.1 * rng.normal(size=J.shape[:-1])
        pairs = confounded_pairs(result, positions, evaluated=(r, J))
        assert [p[:2] for p in pairs] == [("theta5", "a5")]
        assert all(abs(c) <= 1.0 for *_, c in pairs)
        kept, corr = parameter_correlations(result, J)  # what each added effect's step reports too
        assert names[probe[0]] not in kept and np.all(np.abs(corr) <= 1.0 + 1e-9)


def test_right_readings_of_a_probe_far_off_the_flange_are_taken_and_radians_in_them_refused():
    """The orientation check compares the readings with the nominal arm registered on the positions, its tool
    points fitted too: a probe 110 mm off the flange (seed 6: refused at 5.2 deg when the check assumed the tool
    at the flange) is taken, and the same readings written in radians are still refused."""
    from calib_data import wrist_cyclic_campaign

    df = wrist_cyclic_campaign(250, seed=6)
    df = df[0] if isinstance(df, tuple) else df
    calibrate(df, "ur10", "ridge")  # no refusal
    in_radians = df.copy()
    in_radians[list(ORIENTATION_COLUMNS)] = np.deg2rad(df[list(ORIENTATION_COLUMNS)].to_numpy(float))
    with pytest.raises(ValueError, match="not radians"):
        calibrate(in_radians, "ur10", "ridge")
