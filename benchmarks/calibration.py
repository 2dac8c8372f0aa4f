"""Calibration benchmark: solver timing, and the grid paper's stages on a simulated IRB2600.

Run:  PYTHONPATH=. python benchmarks/calibration.py [--sizes 200,500,2000] [--seed 0]

1. Time to calibrate N points (UR10 with random geometric errors, 15 um tracker noise, 1% of the points
   blunders of 1-3 mm) with the robust solvers: ridge + IGG3 and least_squares with a soft-L1 loss. Each
   includes the initial registration and the identifiability analysis.
2. The grid paper's table (methods.md 2d): an IRB2600 carrying the paper's identified DH errors as its
   hidden truth, plus a gravity joint compliance that no geometric model holds (so that a residual is left
   for the grid to catch, as on the real robot), measured by an AT960-class tracker 3 m away. Training: the
   paper's 800 x 1600 x 1200 mm volume at 200 mm; test: 100 random points in the same volume. Stages:
   uncompensated (nominal model, base frame registered) -> kinematic calibration -> + IDW on the grid.
   Errors are prediction errors at the test points (measured - model), the quantity a compensation
   removes to first order.
3. Time of the whole diagnosis loop on the simulated UR10 cell at grid steps of 150, 100 and 70 mm.
4. Big campaigns (issue 11, section 4): `diagnose` on 12 000 poses (target <= 120 s, <= 1 GB) and both
   solvers of `calibrate` on 200 000 poses (target <= 60 s), random poses of the simulated UR10 cell with
   gravity compliance (and backlash for the diagnosis); peak memory is the process's maximum RSS.
   `--big 0` skips them (they take minutes on a busy 2-core machine).
5. A campaign shaped like the real ones (issue 19): `hil diagnose` run as a user runs it (a subprocess: robot
   read from a .toml file, joints in degrees, a 6-DoF probe's orientations, targets <= 120 s and <= 1 GB).
   With HIL_REAL_DATA set (the ipa-robot-accuracy repository, see benchmarks/real_campaigns.py) it is the
   public UR10 series A grid (11 911 poses); without, 12 000 random poses of the simulated UR10 cell with
   gravity compliance and backlash, read by a T-Mac-like probe. `--real 0` skips it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fakes.physics import chain_frames, gravity_torques
from hil.analysis.calibration.solve import Problem, calibrate, solve_ridge_igg3
from hil.analysis.diagnosis.baseline import error_stats
from hil.data.dataset import make_dataset
from hil.geometry.ik import IKOptions, solve_ik
from hil.geometry.kinematics import KinematicModel, measured_point, tool_points
from hil.geometry.robots import get_robot
from hil.geometry.se3 import make_transform
from hil.model.calibrated_model import initial_model
from hil.model.residual_maps import MAP_KINDS, IDWGridMap, kfold_map_errors, make_map

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from calib_data import ur10_joints  # noqa: E402 - the calibration tests' joint sampler (tests/calib_data.py)

# methods.md 2d: (d_alpha deg, d_a mm, d_d mm, d_theta deg) per joint.
PAPER_ERRORS = np.array(
    [
        [-0.0075, -0.2411, -0.3452, 0.0817],
        [-0.0035, 0.3212, -0.0181, -0.0350],
        [-0.0028, 0.4681, 0.0000, -0.0164],
        [0.3780, 0.1615, 0.1751, 0.0100],
        [-0.0113, 0.0524, 0.0081, 0.0980],
        [-0.0063, 0.0301, -0.0482, 0.0011],
    ]
)
PAPER_TABLE = {  # stage: (max, mean, RMS) mm
    "uncompensated": (1.883, 0.897, 0.812),
    "kinematic calibration": (0.441, 0.227, 0.144),
    "+ IDW grid": (0.237, 0.059, 0.049),
}
PAPER_TCP_M = np.array([0.3572, 0.2789, 39.4306]) / 1000.0


def _tracker_noise(rng: np.random.Generator, p: np.ndarray) -> np.ndarray:
    sigma = (15e-6 + 6e-6 * np.linalg.norm(p, axis=1)) / 2.0
    return p + sigma[:, None] * rng.standard_normal(p.shape)


def timing(sizes: list[int], seed: int) -> None:
    rng = np.random.default_rng(seed)
    nominal = get_robot("ur10")
    true = nominal.with_errors(
        {n: rng.normal(0, 3e-4 if n[0] in "ad" else 5e-4) for n in nominal.param_names}
    )
    T = make_transform(Rotation.from_rotvec([0.05, -0.1, 2.0]).as_matrix(), [2.0, 0.5, -0.3])
    tool = np.array([0.03, -0.02, 0.11])
    print("Calibration time (UR10, 33 parameters of which 27 identifiable, 1% blunders)")
    print(f"{'points':>7} {'solver':>12} {'time s':>8} {'RMS mm':>8} {'flagged':>8} {'blunders found':>15}")
    for n in sizes:
        q = ur10_joints(rng, n)
        p = _tracker_noise(rng, measured_point(true, q, T, tool))
        bad = rng.choice(n, max(n // 100, 1), replace=False)
        p[bad] += rng.choice([-1, 1], (len(bad), 3)) * rng.uniform(1e-3, 3e-3, (len(bad), 3))
        df = make_dataset(q, p)
        for solver in ("ridge", "lm"):
            t0 = time.perf_counter()
            res = calibrate(df, "ur10", solver=solver)
            dt = time.perf_counter() - t0
            found = int(np.sum(res.outliers[bad]))
            print(
                f"{n:7d} {res.solver:>12} {dt:8.2f} {res.rms_mm:8.4f} {int(res.outliers.sum()):8d} "
                f"{found:>9d} of {len(bad)}"
            )


class _Irb2600Truth:
    """The simulated IRB2600: paper DH errors + gravity compliance (fakes.physics), tracker 3 m away."""

    def __init__(self, seed: int) -> None:
        self.nominal = get_robot("irb2600", use_beta=False)
        errors = {}
        for j, (dal, da, dd, dth) in enumerate(PAPER_ERRORS, start=1):
            errors |= {
                f"alpha{j}": np.deg2rad(dal),
                f"a{j}": da / 1e3,
                f"d{j}": dd / 1e3,
                f"theta{j}": np.deg2rad(dth),
            }
        self.true: KinematicModel = self.nominal.with_errors(errors)
        self.masses = np.array([90.0, 45.0, 35.0, 15.0, 6.0, 1.0])
        self.stiffness = np.array([2.0e6, 1.2e6, 1.0e6, 2.0e5, 2.0e5, 2.0e5])  # N m/rad: ~0.1-0.2 mm sag
        self.T = make_transform(Rotation.from_rotvec([0.0, 0.0, np.pi]).as_matrix(), [3.0, 0.2, -0.5])
        self.rng = np.random.default_rng(seed)

    def measure(self, q: np.ndarray) -> np.ndarray:
        m = self.true
        frames = chain_frames(q, m.theta, m.d, m.a, m.alpha, m.beta)
        dq = gravity_torques(frames, self.masses) / self.stiffness
        frames = chain_frames(q + dq, m.theta, m.d, m.a, m.alpha, m.beta)
        T_flange = frames[:, -1]
        p_base = T_flange[:, :3, :3] @ PAPER_TCP_M + T_flange[:, :3, 3]
        return _tracker_noise(self.rng, p_base @ self.T[:3, :3].T + self.T[:3, 3])


def _joints_for(nominal: KinematicModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nominal IK for tool points with the tool pointing down; returns (joints, reached mask)."""
    R_down = Rotation.from_rotvec([np.pi, 0.0, 0.0]).as_matrix()
    targets = make_transform(np.broadcast_to(R_down, (len(points), 3, 3)), points)
    q_near = np.deg2rad([0.0, 10.0, 10.0, 0.0, 60.0, 0.0])
    res = solve_ik(
        nominal, targets, mode="pose", p_flange_tool=PAPER_TCP_M, q_near=q_near, options=IKOptions(rng=0)
    )
    return res.q[res.success], res.success


def grid_paper(seed: int) -> None:
    cell = _Irb2600Truth(seed)
    nominal = cell.nominal
    lo = np.array([0.7, -0.8, 0.3])
    axes = [np.arange(0.0, 0.8001, 0.2), np.arange(0.0, 1.6001, 0.2), np.arange(0.0, 1.2001, 0.2)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) + lo
    q_grid, ok = _joints_for(nominal, grid)
    rng = np.random.default_rng(seed + 1)
    test_pts = lo + rng.uniform(0, 1, (400, 3)) * np.array([0.8, 1.6, 1.2])
    q_test, _ = _joints_for(nominal, test_pts)
    q_test = q_test[:100]
    train = make_dataset(q_grid, cell.measure(q_grid))
    test = make_dataset(q_test, cell.measure(q_test))
    print(
        f"\nGrid paper stages on a simulated IRB2600 ({len(train)} of {len(grid)} grid vertices reachable at "
        f"200 mm, {len(test)} random test points)"
    )

    # Uncompensated: nominal geometry, only base frame and tool registered.
    nom = initial_model(nominal, train, tool_guess_m=PAPER_TCP_M)
    prob = Problem.from_frame(nom, train)
    reg = np.array([n.startswith(("base_", "tool")) for n in nom.param_names])
    nom = solve_ridge_igg3(nom, prob, reg, robust=False).model
    kin = calibrate(train, nominal, "ridge", tool_guess_m=PAPER_TCP_M).model
    r_test_nom = Problem.from_frame(nom, test).residuals(nom)
    tprob = Problem.from_frame(kin, test)
    r_test_kin = tprob.residuals(kin)
    # + IDW on the grid: the residual at each grid vertex, interpolated in the cube around each target.
    gprob = Problem.from_frame(kin, train)
    r_grid = gprob.residuals(kin)
    p_grid = tool_points(kin.kinematic, gprob.ctx.q, kin._row_tools(gprob.smr))
    idw = IDWGridMap(step_m=0.2).fit(gprob.ctx.q, p_grid, r_grid, 10e-6)
    p_test = tool_points(kin.kinematic, tprob.ctx.q, kin._row_tools(tprob.smr))
    r_test_idw = r_test_kin - idw.predict_raw(tprob.ctx.q, p_test)
    ours = {
        "uncompensated": error_stats(r_test_nom),
        "kinematic calibration": error_stats(r_test_kin),
        "+ IDW grid": error_stats(r_test_idw),
    }
    print(f"{'stage':<24}{'max':>8}{'mean':>8}{'RMS':>8}   |  paper: {'max':>7}{'mean':>8}{'RMS':>8}   (mm)")
    for stage, (pmax, pmean, prms) in PAPER_TABLE.items():
        o = ours[stage]
        print(
            f"{stage:<24}{o['max_mm']:8.3f}{o['mean_mm']:8.3f}{o['rms_mm']:8.3f}   |  "
            f"{'':7}{pmax:7.3f}{pmean:8.3f}{prms:8.3f}"
        )
    print(
        "(the paper's 'RMS' column is below its mean, so it is likely a standard deviation; ours is the RMS)"
    )
    # The residual-map families side by side: 5-fold on the grid, and on the 100 test points.
    folds = [np.arange(k, len(train), 5) for k in range(5)]
    print(
        f"\n{'residual map':<14}{'5-fold RMS':>11}{'test RMS':>10}{'test max':>10}   (mm, after kinematic calibration)"
    )
    for kind in MAP_KINDS:
        cv = kfold_map_errors(kind, gprob.ctx.q, p_grid, r_grid, 10e-6, folds)
        m = IDWGridMap(step_m=0.2) if kind == "idw" else make_map(kind)
        m.fit(gprob.ctx.q, p_grid, r_grid, 10e-6)
        e = error_stats(r_test_kin - m.predict_raw(tprob.ctx.q, p_test))
        print(f"{kind:<14}{error_stats(cv)['rms_mm']:11.4f}{e['rms_mm']:10.4f}{e['max_mm']:10.4f}")


def planned_joints(cell, points_in_box, seed: int) -> np.ndarray:
    """Usable joints on the simulated cell for the points `points_in_box(box, rng)` of the default sampling
    box, planned from the tracker's position, the tool drawing and the nominal model (near-singular poses kept,
    as in the tests' campaigns)."""
    from hil.runner.planners import facing_poses, plan_joints, workspace_box

    rng = np.random.default_rng(seed)
    p_base_tracker = np.linalg.inv(cell.T_tracker_base)[:3, 3]
    points = points_in_box(workspace_box(cell.nominal, p_base_tracker), rng)
    poses = facing_poses(points, p_base_tracker, rng)
    p_nest = np.asarray(cell.config.tool_nests_flange_m[0])
    plan = plan_joints(cell.nominal, poses, p_nest, cell.config.q_home_rad, singular_sigma_m=0.0)
    return plan.q[plan.usable]


def diagnosis_timing(seed: int) -> None:
    """The whole diagnosis loop on the simulated UR10 cell (compliance + backlash) at three grid steps."""
    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell
    from hil.analysis.diagnosis.pipeline import run_diagnosis
    from hil.runner.planners import grid_points

    print("\nDiagnosis loop on the simulated UR10 (gravity compliance + backlash), grid campaigns")
    print(f"{'grid mm':>8} {'points':>7} {'time s':>7}  effects found")
    for step in (0.15, 0.10, 0.07):
        cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, backlash=True))
        df = simulate_campaign(
            cell, planned_joints(cell, lambda box, rng, step=step: grid_points(box, step), seed)
        )
        t0 = time.perf_counter()
        report = run_diagnosis(df, "ur10")
        dt = time.perf_counter() - t0
        found = ", ".join(f"{e['name']} j{e['joint']}" for e in report.effects_added)
        print(f"{step * 1000:8.0f} {len(df):7d} {dt:7.1f}  {found}")


def big_campaigns(seed: int, diagnose_poses: int = 12000, calibrate_poses: int = 200000) -> None:
    """Section 4 of issue 11: diagnose on 12 000 poses, calibrate (both solvers) on 200 000."""
    import resource
    import warnings

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell
    from hil.analysis.diagnosis.pipeline import run_diagnosis
    from hil.runner.planners import random_points

    def peak_mb() -> float:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    print("\nBig campaigns (random poses of the simulated UR10)")
    print(f"{'task':<34} {'poses':>7} {'time s':>8} {'target s':>9} {'peak RSS MB':>12}  result")
    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, backlash=True))
    df = simulate_campaign(
        cell,
        planned_joints(cell, lambda box, rng: random_points(box, 2 * diagnose_poses, rng), seed + 1)[
            :diagnose_poses
        ],
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = run_diagnosis(df, "ur10")
    dt = time.perf_counter() - t0
    found = ", ".join(f"{e['name']} j{e['joint']}" for e in report.effects_added)
    print(f"{'diagnose':<34} {len(df):7d} {dt:8.1f} {120:9d} {peak_mb():12.0f}  {found}")
    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed))
    q = planned_joints(cell, lambda box, rng: random_points(box, 8000, rng), seed + 2)[:4000]
    rng = np.random.default_rng(seed)
    q = q[rng.integers(0, len(q), calibrate_poses)] + rng.normal(0, 0.01, (calibrate_poses, 6))
    df = simulate_campaign(cell, q)
    total = 0.0
    for solver in ("ridge", "lm"):
        t0 = time.perf_counter()
        res = calibrate(df, "ur10", solver=solver)
        dt = time.perf_counter() - t0
        total += dt
        print(
            f"{'calibrate, ' + res.solver:<34} {len(df):7d} {dt:8.1f} {'':>9} {peak_mb():12.0f}  RMS {res.rms_mm:.4f} mm"
        )
    print(f"{'calibrate, both solvers (the CLI)':<34} {len(df):7d} {total:8.1f} {60:9d}")


def real_shaped_campaign(seed: int, poses: int = 12000) -> None:
    """Section 5: `hil diagnose` (a subprocess, as a user runs it) on a campaign shaped like a real one."""
    import os
    import resource
    import subprocess
    import tempfile

    from hil.data.dataset import joint_columns

    with tempfile.TemporaryDirectory() as tmp:
        robot = Path(tmp) / "my_ur10.toml"  # the robot read from a file, as a user's own robot would be
        robot.write_text(
            (Path(__file__).resolve().parents[1] / "hil/geometry/robot_models/ur10.toml").read_text()
        )
        real = os.environ.get("HIL_REAL_DATA")
        if real and Path(real).exists():
            from real_campaigns import read_raw, to_contract

            df, what = to_contract(read_raw(Path(real), "A")), "public UR10 series A grid"
        else:
            df, what = _simulated_real_shape(seed, poses), "simulated UR10, 6-DoF probe"
        for c in joint_columns(6):  # joints in degrees, as controllers export them
            df[c.replace("_rad", "_deg")] = np.rad2deg(df.pop(c))
        data = Path(tmp) / "campaign.csv"
        df.to_csv(data, index=False)
        root = Path(__file__).resolve().parents[1]
        cmd = [sys.executable, "-m", "hil.cli", "diagnose", "--robot", str(robot), str(data)]
        t0 = time.perf_counter()
        out = subprocess.run(
            cmd, capture_output=True, text=True, cwd=root, env={**os.environ, "PYTHONPATH": str(root)}
        )
        dt = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    if out.returncode != 0:
        result = "failed: " + out.stderr.strip()[-300:]
    else:
        result = next((ln for ln in out.stdout.splitlines() if ln.startswith("Added:")), "no effect added")
    print(f"\nA campaign shaped like a real one ({what}): hil diagnose as a subprocess")
    print(f"{'poses':>7} {'time s':>8} {'target s':>9} {'peak RSS MB':>12} {'target MB':>10}  result")
    print(f"{len(df):7d} {dt:8.1f} {120:9d} {peak:12.0f} {1024:10d}  {result[:100]}")


def _simulated_real_shape(seed: int, poses: int):
    """Random poses of the simulated UR10 (compliance, backlash) read by a 6-DoF probe with a hidden mounting."""
    from fakes.campaign import Probe, simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell
    from hil.runner.planners import random_points

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=seed, backlash=True))
    q = planned_joints(cell, lambda box, rng: random_points(box, 2 * poses, rng), seed + 3)[:poses]
    return simulate_campaign(cell, q, probe=Probe.drawn(seed))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="200,500,2000")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--big", type=int, default=1, help="1: also the big-campaign figures (minutes)")
    parser.add_argument("--only-big", action="store_true", help="only the big-campaign figures")
    parser.add_argument("--only-real", action="store_true", help="only the real-shaped campaign (section 5)")
    parser.add_argument("--real", type=int, default=1, help="1: also the real-shaped campaign (section 5)")
    args = parser.parse_args()
    if not (args.only_big or args.only_real):
        timing([int(s) for s in args.sizes.split(",")], args.seed)
        grid_paper(args.seed)
        diagnosis_timing(args.seed)
    if (args.big and not args.only_real) or args.only_big:
        big_campaigns(args.seed)
    if (args.real and not args.only_big) or args.only_real:
        real_shaped_campaign(args.seed)


if __name__ == "__main__":
    main()
