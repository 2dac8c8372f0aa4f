"""The PT paper's measured experiment (methods.md section 4) on `hil sim`, through ur-rtde, emScon and the procedures.

`hil run pseudo_target --pt-paper`: no calibration (the nominal model), three SMRs in the tool's nests for the
pose, the ZYZ triple-angle generator, two measured corrections per target; once on random targets, once on a
circle trajectory (`--targets circle:N`). The simulated UR10 carries more than the paper's error family
(geometric errors and gravity compliance): cyclic gear errors, backlash and thermal growth too. The campaign
first holds a registration and a tool fit (tool_fit, in the tool paper's order).

The paper's circle figure (14.21 -> 0.002 mm) comes from its model-based simulation without noise and with
errors ten times a real arm's; ours is the measured loop on the simulated cell, so it ends near the tracker's
noise floor, not at 0.002 mm. The cell's backlash makes the plain loop stall near 0.1 mm (each correction
reaches its pose from another side); the rows with `--approach-deg 0.5` reach every pose from one side.

Run: PYTHONPATH=. python benchmarks/paper_pt.py [--quick] [--targets N] [--circle-points N]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.paper_tool import EFFECTS  # noqa: E402

PAPER = "pt"


def run_experiment(
    quick: bool, seed: int = 0, targets: int | None = None, circle_points: int | None = None
) -> dict[str, dict]:
    """Registration and tool fit, then the --pt-paper loop on random targets and on a circle, each in its own
    copy of the registered campaign: {"targets": summary, "circle": summary}."""
    from procedures import pseudo_target, registration, tool_fit
    from tests.sim_session import running_cell, session_on

    fit = {"check_poses": 12, "validation_poses": 6, "shots": 3} if quick else {}
    shots = 3 if quick else 10
    where = str(targets or (5 if quick else 20))
    circle = f"circle:{circle_points or (6 if quick else 2000)}"
    one_sided = {"approach_rad": np.deg2rad(0.5)}  # every joint reaches its pose from below (backlash)
    loops = {
        "targets": (where, {}),
        "approach": (where, one_sided),
        "circle": (circle, one_sided),
    }
    out = {}
    with (
        tempfile.TemporaryDirectory() as folder,
        running_cell(Path(folder), time_scale=50.0, seed=seed, extra_args=EFFECTS) as (_, config),
    ):
        base = Path(folder) / "registered.sqlite"
        with session_on(config, base) as session:
            registration.PROCEDURE(session)
            tool_fit.PROCEDURE(session, **fit)
        for name, (goal, options) in loops.items():
            path = Path(folder) / f"{name}.sqlite"
            shutil.copy(base, path)
            with session_on(config, path) as session:
                result = pseudo_target.PROCEDURE(
                    session, pt_paper=True, targets=goal, seed=seed, shots=shots, **options
                )
            out[name] = {"summary": result.summary(), "errors_mm": [
                [e * 1e3 for e in t.errors_m] for t in result.visited]}  # fmt: skip
    return out


def rows(quick: bool, targets: int | None = None, circle_points: int | None = None) -> list[dict]:
    """The PT paper's figures beside ours (columns: paper, quantity, paper_value, ours, unit, note); quick: 5
    targets and a 6-point circle at 3 shots, else 20 targets and the paper's 2 000-point circle at 10 shots
    (the circle alone is about an hour on the simulated cell)."""
    runs = run_experiment(quick, targets=targets, circle_points=circle_points)

    def row(quantity: str, paper_value: float | None, ours: float, unit: str, note: str) -> dict:
        return {"paper": PAPER, "quantity": quantity, "paper_value": paper_value, "ours": float(ours),
                "unit": unit, "note": note}  # fmt: skip

    s = runs["targets"]["summary"]
    p, o, n = s["position_mm"], s["orientation_deg"], s["visited"]
    table = [
        row("mean position error, nominal start", 1.1257, p["start"]["mean"], "mm", f"{n} targets, 3 SMRs"),
        row("mean position error, 2 measured corrections", 0.0262, p["final"]["mean"], "mm", "generator zyz"),
        row("max position error, 2 measured corrections", 0.0577, p["final"]["max"], "mm", ""),
        row("mean orientation error, nominal start", 0.3155, o["start"]["mean"], "deg", ""),
        row("mean orientation error, 2 measured corrections", 0.012, o["final"]["mean"], "deg", ""),
        row("max orientation error, 2 measured corrections", 0.0247, o["final"]["max"], "deg", ""),
    ]
    means = [sum(e[i] for e in runs["targets"]["errors_mm"]) / n for i in range(3)]
    table.append(
        row(
            "mean position error after 1 correction",
            None,
            means[1],
            "mm",
            "the paper gives start and end only",
        )
    )
    a = runs["approach"]["summary"]["position_mm"]
    table += [
        row("mean position error, 2 corrections, one-sided approach", None, a["final"]["mean"], "mm",
            "--approach-deg 0.5: every joint reaches its pose from below (the cell has backlash)"),
        row("max position error, 2 corrections, one-sided approach", None, a["final"]["max"], "mm", ""),
    ]  # fmt: skip
    c = runs["circle"]["summary"]
    table += [
        row(f"circle ({c['visited']} points): mean error before", 14.21, c["position_mm"]["start"]["mean"], "mm",
            "paper: model-based simulation, errors ~10x a real arm's"),
        row(f"circle ({c['visited']} points): mean error after", 0.002, c["position_mm"]["final"]["mean"], "mm",
            "ours measured, one-sided approach: ends near the tracker's noise, not 0.002"),
    ]  # fmt: skip
    return table


if __name__ == "__main__":
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--quick", action="store_true", help="5 targets, a 6-point circle, 3 shots (a minute or two)"
    )
    parser.add_argument("--targets", type=int, help="random targets (default 5 quick, 20 full)")
    parser.add_argument("--circle-points", type=int, help="points of the circle (default 6 quick, 2000 full)")
    args = parser.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from paper_cell import print_rows

    print_rows(rows(args.quick, args.targets, args.circle_points))
