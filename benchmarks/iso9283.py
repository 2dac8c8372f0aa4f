"""The ISO 9283 test on the simulated cell, through the drivers, before and after compensation: each pose's AP
set against the cell's true error at the commanded joints, and each path's AT against the true path's.

Run:  PYTHONPATH=. python benchmarks/iso9283.py [--seed 3] [--cycles 10] [--side-mm 300] [--path-runs 10]
      [--path-speed 0.25] [--smrs 3] [--time-scale 4]

The cell is `hil sim`'s default UR10 (hidden geometric errors, gravity compliance, tracker noise at its MPE).
The model used for compensation is calibrated from a simulated grid campaign of the same cell (200 mm step,
geometry and gravity compliance). "AP true" is the distance of the noise-free true SMR position at the
commanded joints from the commanded position (the figure AP estimates; their difference is noise over
sqrt(cycles) and the robot's repeatability). "AT true" is the largest distance, in the planes normal to the
commanded path at the measurement's commanded points, of the noise-free true path (the controller's joints
every 2 mm along the moveL, the cell's truth at them) from the commanded path. The path samples come every
controller tick of the cell (8 ms x the time scale), so a lower --time-scale samples the paths more densely.
With --smrs 3 the orientation figures too: "AP_abc true" is the tool's true orientation (the drawing's nests
fitted to their true centres at the commanded joints) less the commanded one, per angle.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--cycles", type=int, default=10)
    ap.add_argument("--side-mm", type=float, default=300.0)
    ap.add_argument("--path-runs", type=int, default=10)
    ap.add_argument("--path-speed", type=float, default=0.25, help="m/s")
    ap.add_argument("--smrs", type=int, default=3)
    ap.add_argument("--time-scale", type=float, default=4.0)
    args = ap.parse_args()

    import pandas as pd
    from calib_data import cell_datasets, true_effect_model
    from iso_truth import true_path as iso_truth_path
    from iso_truth import true_smr_points
    from sim_session import running_cell, session_on

    from fakes.cell import SimCellConfig, SimulatedCell
    from hil.analysis.standards.iso9283 import commanded_tangents, crossings
    from hil.data.dataset import orientation_columns
    from hil.geometry.se3 import fit_rigid
    from procedures import iso9283, registration

    folder = Path(tempfile.mkdtemp(prefix="iso-bench-"))
    _, train, _ = cell_datasets(step_m=0.2, n_val=1, seed=args.seed)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    model.save(folder / "model.json")
    t0 = time.time()
    with (
        running_cell(folder, seed=args.seed, time_scale=args.time_scale) as (_, config),
        session_on(config, folder / "c.sqlite") as session,
    ):
        registration.PROCEDURE(session)
        result = iso9283.PROCEDURE(
            session, cycles=args.cycles, side_m=args.side_mm / 1e3, model=str(folder / "model.json"),
            path_runs=args.path_runs, path_speed_m_s=args.path_speed, csv=str(folder / "iso.csv"), smrs=args.smrs,
        )  # fmt: skip
        T_reg = session.registration.T_tracker_base
    print(result.table())
    print(f"({time.time() - t0:.0f} s on the simulated cell)\n")
    sim = SimulatedCell(SimCellConfig(seed=args.seed))
    truth = sim.ground_truth()

    def true_points(q: np.ndarray) -> np.ndarray:
        return true_smr_points(sim, q)

    def true_path(run: iso9283.PathRun) -> np.ndarray:
        return iso_truth_path(sim, config, run)

    cube = result.cube
    q_after = iso9283.compensated_joints(config, model, cube)
    print(f"{'run':<8}{'pose':<6}{'AP mm':>9}{'AP true mm':>12}{'diff um':>9}{'RP mm':>9}")
    for step, T, q in (("before", T_reg, cube.q_rad), ("after", model.T_tracker_base, q_after)):
        cmd = cube.p_base_m @ T[:3, :3].T + T[:3, 3]
        ap_true = np.linalg.norm(true_points(q) - cmd, axis=1) * 1e3
        for k, p in enumerate(result.reports[step].poses):
            print(f"{step:<8}{p.pose:<6}{p.AP_m * 1e3:9.4f}{ap_true[k]:12.4f}{(p.AP_m * 1e3 - ap_true[k]) * 1e3:9.1f}"
                  f"{p.RP_m * 1e3:9.4f}")  # fmt: skip
    if args.smrs >= 3:
        nests_true = np.asarray(truth["tool_nests_flange_m"])
        print(
            f"\n{'run':<8}{'pose':<6}{'AP_a':>8}{'true':>8}{'AP_b':>8}{'true':>8}{'AP_c':>8}{'true':>8}  deg"
        )
        for step, T, q in (("before", T_reg, cube.q_rad), ("after", model.T_tracker_base, q_after)):
            _, frames = sim.true_joint_offsets(q, np.ones_like(q), 0.0)
            T_true = sim.T_tracker_base @ frames[:, -1] @ sim.nominal.T_last_flange
            p = np.einsum("nij,kj->nki", T_true[:, :3, :3], nests_true) + T_true[:, None, :3, 3]
            p = p + np.asarray(truth["smr_centering_m"])
            R = np.array([fit_rigid(config.nests_flange_m, pk)[0][:3, :3] for pk in p])
            R_cmd = T[:3, :3] @ cube.R_base_flange
            cmd = np.array([float(v[0]) for v in orientation_columns(R_cmd[None]).values()])
            true_abc = (np.column_stack(list(orientation_columns(R).values())) - cmd + 180.0) % 360.0 - 180.0
            for k, pf in enumerate(result.reports[step].poses):
                assert pf.AP_abc_rad is not None
                both = np.column_stack([np.rad2deg(pf.AP_abc_rad), true_abc[k]]).ravel()
                print(f"{step:<8}{pf.pose:<6}" + "".join(f"{v:8.4f}" for v in both))
    if not args.path_runs:
        return
    paths = iso9283.plan_paths(config, cube, 1, model, args.path_speed)
    print(
        f"\n{'run':<8}{'path':<8}{'AT mm':>9}{'AT true mm':>12}{'diff um':>9}{'RT mm':>9}{'samples/run':>13}"
    )
    for step, csv in (("before", "iso-paths.csv"), ("after", "iso-paths-after.csv")):
        samples = pd.read_csv(folder / csv)
        for run in paths[step]:
            rows = samples[samples["path"] == run.name]
            first = rows[rows["run"] == rows["run"].min()]
            c = first[["x_cmd_mm", "y_cmd_mm", "z_cmd_mm"]].to_numpy() / 1e3
            c = c[np.concatenate([[True], np.linalg.norm(np.diff(c, axis=0), axis=1) > 1e-9])]
            x = crossings(true_path(run), c, commanded_tangents(c))
            ok = np.isfinite(x[:, 0])
            at_true = float(np.linalg.norm(x[ok] - c[ok], axis=1).max() * 1e3)
            fig = result.paths[step][run.name] if result.paths else None
            assert fig is not None
            print(f"{step:<8}{run.name:<8}{fig.AT_m * 1e3:9.4f}{at_true:12.4f}{(fig.AT_m * 1e3 - at_true) * 1e3:9.1f}"
                  f"{fig.RT_m * 1e3:9.4f}{len(rows) / fig.runs:13.0f}")  # fmt: skip


if __name__ == "__main__":
    main()
