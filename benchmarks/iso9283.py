"""The ISO 9283 pose test on the simulated cell, through the drivers, before and after compensation, with
each pose's AP set against the cell's true error at the commanded joints.

Run:  PYTHONPATH=. python benchmarks/iso9283.py [--seed 3] [--cycles 10] [--side-mm 300]

The cell is `hil sim`'s default UR10 (hidden geometric errors, gravity compliance, tracker noise at its MPE).
The model used for compensation is calibrated from a simulated grid campaign of the same cell (200 mm step,
geometry and gravity compliance). "AP true" is the distance of the noise-free true SMR position at the
commanded joints from the commanded position (the figure AP estimates; their difference is noise over
sqrt(cycles) and the robot's repeatability).
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
    args = ap.parse_args()

    from calib_data import cell_datasets, true_effect_model
    from sim_session import running_cell, session_on

    from fakes.cell import SimCellConfig, SimulatedCell
    from procedures import iso9283, registration

    folder = Path(tempfile.mkdtemp(prefix="iso-bench-"))
    _, train, _ = cell_datasets(step_m=0.2, n_val=1, seed=args.seed)
    model = true_effect_model(train, "ur10", ("gravity_compliance",))
    model.save(folder / "model.json")
    t0 = time.time()
    with (
        running_cell(folder, seed=args.seed, time_scale=100.0) as (_, config),
        session_on(config, folder / "c.sqlite") as session,
    ):
        registration.PROCEDURE(session)
        result = iso9283.PROCEDURE(
            session, cycles=args.cycles, side_m=args.side_mm / 1e3, model=str(folder / "model.json")
        )
        T_reg = session.registration.T_tracker_base
    print(result.table())
    print(f"({time.time() - t0:.0f} s on the simulated cell)\n")
    sim = SimulatedCell(SimCellConfig(seed=args.seed))
    truth = sim.ground_truth()
    nest = np.asarray(truth["tool_nests_flange_m"][0])

    def true_points(q: np.ndarray) -> np.ndarray:
        _, frames = sim.true_joint_offsets(q, np.ones_like(q), 0.0)
        T = sim.T_tracker_base @ frames[:, -1] @ sim.nominal.T_last_flange
        return T[:, :3, :3] @ nest + T[:, :3, 3] + np.asarray(truth["smr_centering_m"][0])

    cube = result.cube
    q_after = iso9283.compensated_joints(config, model, cube)
    print(f"{'run':<8}{'pose':<6}{'AP mm':>9}{'AP true mm':>12}{'diff um':>9}{'RP mm':>9}")
    for step, T, q in (("before", T_reg, cube.q_rad), ("after", model.T_tracker_base, q_after)):
        cmd = cube.p_base_m @ T[:3, :3].T + T[:3, 3]
        ap_true = np.linalg.norm(true_points(q) - cmd, axis=1) * 1e3
        for k, p in enumerate(result.reports[step].poses):
            print(f"{step:<8}{p.pose:<6}{p.AP_m * 1e3:9.4f}{ap_true[k]:12.4f}{(p.AP_m * 1e3 - ap_true[k]) * 1e3:9.1f}"
                  f"{p.RP_m * 1e3:9.4f}")  # fmt: skip


if __name__ == "__main__":
    main()
