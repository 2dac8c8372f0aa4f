"""The fleet view on a simulated plant history: 200 robots x 10 campaigns in the shared store, built in seconds.

Each robot has its own geometry errors (24 kinematic parameters); every campaign, some 90 days apart, calibrates
it again: each parameter read with its standard error (0.02 mm, 0.003 deg) around the robot's truth, the base
frame anywhere (it moves with the cell). A few robots are moved between their last two campaigns (joint 2 hit:
a2 by 0.25 mm and theta2 by 0.03 deg) and a few have an error after calibration over the limit. The benchmark
times the build (COPY into the database), the read (one query), the flags and the HTML page, and counts how
many moved robots were flagged and how many unmoved ones were (the false alarms, against the stated rate).

Run:  PYTHONPATH=. python benchmarks/fleet.py [--robots 200] [--campaigns 10] [--url postgresql://...]
Without --url it starts a throw-away server from the distribution's binaries (tests/pg_server.py).
"""

from __future__ import annotations

import argparse
import json
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psycopg

from hil.data.store import MEASUREMENT_COLUMNS, CampaignStore, MeasurementRecord, ResultRecord

KINEMATIC = [f"{kind}{j}" for j in range(1, 7) for kind in ("theta", "d", "a", "alpha")]
BASE = ["base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz"]
STD_M, STD_RAD = 20e-6, np.deg2rad(0.003)
DAY_S = 86400.0
MOVED = {"a2": 0.25e-3, "theta2": np.deg2rad(0.03)}  # a crash into joint 2


def _unit(name: str) -> str:
    return "rad" if name.startswith(("theta", "alpha", "base_r")) else "m"


@dataclass(frozen=True)
class Campaign:
    """One simulated campaign: its robot, cell, time, temperature and what calibrating it gave."""

    uuid: uuid.UUID
    label: str
    robot_serial: str
    cell_name: str
    time_s: float
    temperature_c: float
    summary: dict


@dataclass(frozen=True)
class SimulatedFleet:
    campaigns: list[Campaign]
    moved: set[str]  # serials of the robots moved before their last campaign
    worn: set[str]  # serials whose last error after calibration is over 0.5 mm


def simulated_fleet(
    robots: int = 200, campaigns: int = 10, moved: int = 8, worn: int = 4, seed: int = 0
) -> SimulatedFleet:
    rng = np.random.default_rng(seed)
    serials = [f"2023{5500000 + i:07d}" for i in range(robots)]
    moved_set, worn_set = set(serials[:moved]), set(serials[moved : moved + worn])
    std = np.array([STD_RAD if _unit(n) == "rad" else STD_M for n in KINEMATIC])
    start = 1.70e9
    out: list[Campaign] = []
    for r, serial in enumerate(serials):
        truth = rng.normal(0.0, 5 * std)  # this robot's own geometry errors
        for k in range(campaigns):
            true_k = truth.copy()
            if serial in moved_set and k == campaigns - 1:
                for name, shift in MOVED.items():
                    true_k[KINEMATIC.index(name)] += shift
            read = true_k + rng.normal(0.0, std)
            after = (
                0.12e-3
                + rng.normal(0, 0.01e-3)
                + (0.5e-3 if serial in worn_set and k == campaigns - 1 else 0)
            )
            parameters = [
                {"name": n, "delta": float(v), "std": float(s), "unit": _unit(n)}
                for n, v, s in zip(KINEMATIC, read, std, strict=True)
            ] + [{"name": n, "delta": float(rng.normal(0, 0.5)), "std": 1e-5, "unit": _unit(n)} for n in BASE]
            temperature = float(22 + rng.normal(0, 2))
            summary = {
                "robot": "ur10", "solver": "ridge_igg3", "rows": 400, "errors_on": "training rows (in-sample)",
                "rms_before_m": float(1.8e-3 + rng.normal(0, 0.1e-3)), "rms_after_m": float(after),
                "parameters": parameters, "effects_found": [], "effects_assumed": [],
                "temperature_mean_c": temperature,
            }  # fmt: skip
            t = start + k * 90 * DAY_S + r * 3600.0
            out.append(
                Campaign(
                    uuid.uuid4(), f"{serial}-{k:02d}", serial, f"cell-{r % 40:02d}", t, temperature, summary
                )
            )
    return SimulatedFleet(out, moved_set, worn_set)


def _station(c: Campaign) -> dict:
    return {
        "robot_definition": {"model": "ur10"},
        "station": {
            "robot_serial_number": c.robot_serial, "robot_model_reported": "UR10", "cell_name": c.cell_name,
            "robot_controller_version": "5.11.1.0", "tracker": {"name": "AT960", "serial_number": 750123},
        },
    }  # fmt: skip


def _measurement(c: Campaign, i: int) -> MeasurementRecord:
    return MeasurementRecord(
        procedure="grid_sampling", step="grid", point_id=f"p{i}", q_target_rad=np.zeros(6), q_rad=np.zeros(6),
        T_base_flange=np.eye(4), p_tracker_m=np.zeros(3), spread_m=np.zeros(3), std_m=np.zeros(3), shots=10,
        rejected_shots=(), smr=1, location="nest1", temperature_c=c.temperature_c, pressure_hpa=1013.0,
        humidity_pct=40.0, timestamp_s=c.time_s + i,
    )  # fmt: skip


def write_to_database(conn: psycopg.Connection, fleet: SimulatedFleet) -> None:
    """The fleet's campaigns, station snapshots, two measurements each (dates, temperatures) and results, by
    COPY in one transaction (the schema must exist: open any campaign first)."""
    columns = ", ".join(f'"{c}"' for c in ("campaign", *MEASUREMENT_COLUMNS))
    with conn.transaction(), conn.cursor() as cur:
        with cur.copy("COPY campaigns (uuid, label, created_s) FROM STDIN") as sink:
            for c in fleet.campaigns:
                sink.write_row((c.uuid, c.label, c.time_s))
        with cur.copy("COPY snapshots (campaign, recorded_s, data) FROM STDIN") as sink:
            for c in fleet.campaigns:
                sink.write_row((c.uuid, c.time_s, json.dumps(_station(c))))
        with cur.copy(f"COPY measurements ({columns}) FROM STDIN") as sink:
            zeros = [0.0] * (6 + 6 + 16 + 9)
            for c in fleet.campaigns:
                for i in range(2):
                    sink.write_row(
                        (c.uuid, "grid_sampling", "grid", f"p{i}", *zeros, 10, "[]", 1, "nest1", c.temperature_c,
                         1013.0, 40.0, c.time_s + i, "{}", c.time_s + i)
                    )  # fmt: skip
        with cur.copy("COPY results (campaign, recorded_s, kind, summary, model) FROM STDIN") as sink:
            for c in fleet.campaigns:
                sink.write_row((c.uuid, c.time_s + 60, "calibration", json.dumps(c.summary), None))


def write_to_folder(folder: Path, fleet: SimulatedFleet) -> None:
    """The same history as campaign files (one per campaign), through the file store."""
    for c in fleet.campaigns:
        with CampaignStore(folder / f"{c.label}.sqlite") as store:
            store.add_snapshot(_station(c))
            for i in range(2):
                store.record_measurement(_measurement(c, i))
            store.record_result(ResultRecord("calibration", c.summary, None))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--robots", type=int, default=200)
    parser.add_argument("--campaigns", type=int, default=10)
    parser.add_argument("--url", default=None, help="an empty database of a running server (PGPASSWORD set)")
    parser.add_argument("--html", default="fleet.html")
    args = parser.parse_args()
    from hil.analysis.fleet.status import fleet_status
    from hil.data.fleet_source import read_fleet
    from hil.data.pg_store import PgCampaignStore
    from hil.report.fleet_html import write_fleet_html

    server = None
    url = args.url
    if url is None:
        import os
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from pg_server import PASSWORD, PgServer

        server = PgServer()
        server.start()
        os.environ["PGPASSWORD"] = PASSWORD
        url = server.create_database("fleet")
    try:
        started = time.perf_counter()
        fleet = simulated_fleet(args.robots, args.campaigns)
        simulated = time.perf_counter()
        with PgCampaignStore(url + "?campaign=schema"):  # migrates the empty database
            pass
        with psycopg.connect(url) as conn:
            write_to_database(conn, fleet)
        built = time.perf_counter()
        history = read_fleet(url)
        read = time.perf_counter()
        status = fleet_status(history)
        flagged = time.perf_counter()
        write_fleet_html(args.html, history, status)
        page = time.perf_counter()
    finally:
        if server is not None:
            server.remove()
    robots = status.robots.set_index("robot")
    moved = robots["moved"]
    print(f"{args.robots} robots x {args.campaigns} campaigns = {len(history.results)} results, "
          f"{len(history.parameters)} parameter rows")  # fmt: skip
    print(f"simulate {simulated - started:.2f} s, COPY into the store {built - simulated:.2f} s, "
          f"read (one query) {read - built:.2f} s, flags {flagged - read:.2f} s, HTML {page - flagged:.2f} s "
          f"({Path(args.html).stat().st_size / 1e6:.1f} MB); the view from the store: {page - built:.2f} s")  # fmt: skip
    caught = int(moved[list(fleet.moved)].sum())
    false = int(moved.drop(list(fleet.moved)).sum())
    worn = int(robots.loc[list(fleet.worn), "error_flag"].sum())
    print(f"moved robots flagged: {caught} of {len(fleet.moved)}; unmoved robots flagged (false alarms): {false} "
          f"of {args.robots - len(fleet.moved)} (stated fleet-wide rate 0.05); error over the limit flagged: "
          f"{worn} of {len(fleet.worn)}; first in the table: {', '.join(status.robots['robot'][:3])}")  # fmt: skip


if __name__ == "__main__":
    main()
