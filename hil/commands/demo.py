"""`hil demo`: the main job on a simulated cell, end to end.

1. Sample a Cartesian grid (default 100 mm) and random held-out poses on the simulated cell, as a
   tracker would measure them, and write both campaigns in the dataset contract.
2. Calibrate and diagnose: find what the geometric model misses, add it, and print the error
   before and after on held-out and validation data.
3. Write the JSON report, the HTML report and the final model.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fakes.campaign import grid_joints, random_joints, simulate_campaign
from fakes.cell import CellConfig, SimulatedCell
from hil.dataset import write_dataset
from hil.diagnosis import run_diagnosis
from hil.report import write_html, write_json

CELL_EFFECTS: tuple[str, ...] = ("compliance", "cyclic", "backlash", "thermal")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the main job on a simulated cell: grid campaign, calibration, diagnosis, report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--robot", default="ur10", help="robot model (default ur10)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated cell (default 0)")
    parser.add_argument("--step-mm", type=float, default=100.0, help="grid step in mm (default 100)")
    parser.add_argument("--validate", type=int, default=100, help="random validation poses (default 100)")
    parser.add_argument(
        "--effects",
        default="compliance",
        help=f"physical effects switched on in the cell, comma-separated from {', '.join(CELL_EFFECTS)}, "
        "or 'none' (default: compliance, the PT paper's undeclared effect)",
    )
    parser.add_argument("--out", default="demo-out", help="output folder (default ./demo-out)")
    parser.set_defaults(func=run)


def parse_effects(text: str) -> dict[str, bool]:
    """'compliance,thermal' -> CellConfig flags; refuses unknown names with the list of known ones."""
    chosen = set() if text.strip().lower() == "none" else {e.strip() for e in text.split(",") if e.strip()}
    unknown = chosen - set(CELL_EFFECTS)
    if unknown:
        raise SystemExit(
            f"unknown effect(s) {sorted(unknown)}: choose from {', '.join(CELL_EFFECTS)} or none"
        )
    return {name: name in chosen for name in CELL_EFFECTS}


def run(args: argparse.Namespace) -> int:
    flags = parse_effects(args.effects)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cell = SimulatedCell(CellConfig(robot=args.robot, seed=args.seed, **flags))
    on = [k for k, v in flags.items() if v] or ["none"]
    print(f"simulated cell: {cell.robot_name}, seed {args.seed}, hidden geometric errors + {', '.join(on)}")

    q_grid = grid_joints(cell, step_m=args.step_mm / 1000.0, seed=args.seed)
    train = simulate_campaign(cell, q_grid)
    validate = simulate_campaign(cell, random_joints(cell, args.validate, seed=args.seed + 1))
    write_dataset(train, out / "grid.csv")
    write_dataset(validate, out / "validate.csv")
    print(f"measured {len(train)} grid poses at {args.step_mm:g} mm and {len(validate)} validation poses")

    report = run_diagnosis(train, cell.nominal, df_validate=validate, seed=args.seed)
    print()
    print(report.table())
    added = ", ".join(
        f"{e['name']}" + (f" (joint {e['joint']})" if e["joint"] else "") for e in report.effects_added
    )
    print(f"effects added: {added or 'none'}")
    print(report.conclusion)

    write_json(report, out / "report.json")
    write_html(report, out / "report.html")
    report.model.save(out / "model.json")
    print(f"\nwrote {out}/grid.csv, validate.csv, report.json, report.html, model.json")
    return 0
