"""Benchmark of the measurement runner.

Part one, the campaign store, on a file in /tmp (WAL, synchronous=FULL, one commit per point as a session does):
  1. record_measurement per call (durable on return);
  2. has_measurement per call (the resume check before every point), for recorded and unknown points;
  3. reading everything back: measurements() and campaign_dataset().
Part two, a grid campaign on `hil sim` through ur-rtde and emScon (registration first): points per minute,
and the runner's own time per point beyond the driver calls (store commit, envelope check of the whole
path, resume check, progress, planning), measured by timing every robot and tracker call.

Run: PYTHONPATH=. python benchmarks/runner.py [--points 2000] [--step-mm 150] [--time-scale 20] [--no-sim]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.data.store import CampaignStore, MeasurementRecord, campaign_dataset  # noqa: E402


def make_records(n: int, seed: int = 0) -> list[MeasurementRecord]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        T = np.eye(4)
        T[:3, 3] = rng.normal(size=3)
        q = rng.uniform(-3, 3, 6)
        out.append(
            MeasurementRecord(
                procedure="grid_sampling",
                step="grid",
                point_id=f"g{i:05d}",
                q_target_rad=q,
                q_rad=q + rng.normal(0, 1e-5, 6),
                T_base_flange=T,
                p_tracker_m=rng.normal(size=3),
                spread_m=rng.uniform(0, 1e-5, 3),
                std_m=rng.uniform(0, 1e-5, 3),
                shots=5,
                rejected_shots=(),
                smr=1,
                location="nest1",
                temperature_c=21.0,
                pressure_hpa=1012.0,
                humidity_pct=40.0,
                timestamp_s=1.7e9 + i,
                extra={"attempts": 1, "order": "travel"},
            )
        )
    return out


def timed(calls) -> np.ndarray:
    """Seconds of each call of the zero-argument callables."""
    out = np.empty(len(calls))
    for i, call in enumerate(calls):
        t = time.perf_counter()
        call()
        out[i] = time.perf_counter() - t
    return out


def timed_proxy(target, totals: dict, name: str):
    """The driver, with the time spent in its calls added up in totals[name]."""

    class Proxy:
        def __getattr__(self, attr):
            value = getattr(target, attr)
            if not callable(value):
                return value

            def call(*args, **kwargs):
                t0 = time.perf_counter()
                try:
                    return value(*args, **kwargs)
                finally:
                    totals[name] += time.perf_counter() - t0

            return call

    return Proxy()


class InstantRobot:
    """A Robot that is wherever it is told at once (no controller): leaves only the runner's own time."""

    def __init__(self, q: np.ndarray, nominal):
        self.q, self.nominal = np.asarray(q, float), nominal

    def move_joints(self, q, speed=None, accel=None):
        self.q = np.asarray(q, float)

    def joints(self):
        return self.q.copy()

    def flange_pose(self):
        from hil.geometry.kinematics import forward_kinematics

        return forward_kinematics(self.nominal, self.q[None])[0]

    def wait_settled(self, dwell_s=None, timeout_s=None):
        pass

    def stop(self):
        pass

    def recover(self):
        pass

    def close(self):
        pass


class InstantTracker:
    """A Tracker that answers at once with a fixed point."""

    def measure(self, shots: int = 1):
        from hil.instruments.tracker import TrackerMeasurement

        zero = np.zeros(3)
        return TrackerMeasurement(
            np.ones(3), zero, zero, 0.0, np.ones((shots, 3)), (), 20.0, 1013.0, 40.0, time.time(), 1
        )

    def point_at(self, p_tracker_m):
        pass

    def close(self):
        pass


def runner_alone(step_mm: float, validation: int) -> dict:
    """The grid procedure with instant instruments: all that is left is the runner (envelope check of every
    path, resume check, durable commit, aiming prediction, progress), per point, planning excluded."""
    import tomllib

    from hil.runner.cell_config import parse_cell_config
    from hil.runner.operator import ScriptedOperator
    from hil.runner.session import Session
    from procedures import grid_sampling
    from tests.cell_fixtures import sim_cell_toml

    config = parse_cell_config(tomllib.loads(sim_cell_toml()))
    with tempfile.TemporaryDirectory() as folder:
        store = CampaignStore(Path(folder) / "campaign.sqlite")
        robot = InstantRobot(config.q_home_rad, config.nominal)
        session = Session(
            config, robot, InstantTracker(), store, ScriptedOperator({"place_smr": lambda step: None})
        )
        with session:
            session.finish_step("registration", "fit", {"T_tracker_base": np.eye(4).tolist(), "rms_mm": 1.0})
            t0 = time.perf_counter()
            grid_sampling.PROCEDURE.make_plan(config, step_m=step_mm / 1e3, validation=validation)
            plan_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            result = grid_sampling.PROCEDURE(session, step_m=step_mm / 1e3, validation=validation)
            wall = time.perf_counter() - t0
    points = result.recorded + result.validation_recorded
    return {"points": points, "per_point_ms": 1e3 * (wall - plan_s) / points}


def grid_on_sim(step_mm: float, validation: int, time_scale: float) -> dict:
    """Registration, then a grid campaign on hil sim: points per minute and per-point times."""
    from contextlib import ExitStack

    from hil.station.instruments import open_session, simulated_operator
    from procedures import grid_sampling, registration
    from tests.sim_session import running_cell

    with (
        tempfile.TemporaryDirectory() as folder,
        running_cell(Path(folder), time_scale=time_scale, seed=0) as (_, config),
        ExitStack() as stack,
    ):
        operator = simulated_operator(config.simulator_control)
        session = open_session(config, Path(folder) / "campaign.sqlite", operator, stack, progress=False)
        with session:
            registration.PROCEDURE(session)
            totals = {"robot": 0.0, "tracker": 0.0, "store": 0.0}
            session.robot = timed_proxy(session.robot, totals, "robot")
            session.tracker = timed_proxy(session.tracker, totals, "tracker")
            session.store = timed_proxy(session.store, totals, "store")
            t0 = time.perf_counter()
            grid_sampling.PROCEDURE.make_plan(
                config, step_m=step_mm / 1e3, validation=validation
            )  # what run() plans first
            plan_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            result = grid_sampling.PROCEDURE(session, step_m=step_mm / 1e3, validation=validation)
            wall = time.perf_counter() - t0
            totals = dict(totals)  # closing the session below calls the drivers again
    points = result.recorded + result.validation_recorded
    return {
        "points": points,
        "wall_s": wall,
        "points_per_min": 60 * points / wall,
        "runner_ms": 1e3 * (wall - totals["robot"] - totals["tracker"]) / points,
        "per_point_ms": 1e3 * (wall - plan_s - totals["robot"] - totals["tracker"]) / points,
        "store_ms": 1e3 * totals["store"] / points,
        "robot_ms": 1e3 * totals["robot"] / points,
        "tracker_ms": 1e3 * totals["tracker"] / points,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=2000)
    parser.add_argument("--step-mm", type=float, default=150.0)
    parser.add_argument("--validation", type=int, default=20)
    parser.add_argument("--time-scale", type=float, default=20.0)
    parser.add_argument("--no-sim", action="store_true", help="skip part two (the campaign on hil sim)")
    args = parser.parse_args()
    records = make_records(args.points)
    folder = Path(tempfile.mkdtemp(prefix="hil-bench-store-", dir="/tmp"))
    try:
        with CampaignStore(folder / "bench.hilc") as store:
            rows = {
                "record_measurement (commit)": timed(
                    [lambda r=r: store.record_measurement(r) for r in records]
                ),
                "has_measurement (recorded)": timed(
                    [lambda r=r: store.has_measurement(r.procedure, r.step, r.point_id) for r in records]
                ),
                "has_measurement (unknown)": timed(
                    [
                        lambda i=i: store.has_measurement("grid_sampling", "grid", f"x{i}")
                        for i in range(args.points)
                    ]
                ),
            }
            reads = {
                f"measurements() of {args.points}": timed([store.measurements] * 5),
                f"campaign_dataset() of {args.points}": timed(
                    [lambda: campaign_dataset(store, "grid_sampling")] * 5
                ),
            }
        size_kb = (folder / "bench.hilc").stat().st_size / 1024
    finally:
        shutil.rmtree(folder)
    print(f"campaign store, {args.points} points, file in /tmp ({size_kb:.0f} KiB after close)")
    print(f"{'operation':<34}{'calls':>7}{'median ms':>11}{'p99 ms':>9}{'max ms':>9}")
    for name, t in {**rows, **reads}.items():
        ms = t * 1000
        print(f"{name:<34}{len(ms):>7}{np.median(ms):>11.3f}{np.percentile(ms, 99):>9.3f}{ms.max():>9.3f}")
    alone = runner_alone(100.0, 50)
    print(
        f"\nrunner alone (instant robot and tracker, 100 mm grid + 50 validation): {alone['points']} points, "
        f"{alone['per_point_ms']:.2f} ms per point beyond the instruments (planning excluded)"
    )
    if args.no_sim:
        return
    r = grid_on_sim(args.step_mm, args.validation, args.time_scale)
    print(
        f"\ngrid campaign on hil sim ({args.step_mm:g} mm, {args.validation} validation, --time-scale {args.time_scale:g})"
    )
    print(
        f"{'points':>7}{'wall s':>9}{'points/min':>12}{'runner ms/pt':>14}{'w/o planning':>14}{'of it store':>13}"
        f"{'robot ms/pt':>13}{'tracker ms/pt':>15}"
    )
    print(
        f"{r['points']:>7}{r['wall_s']:>9.1f}{r['points_per_min']:>12.1f}{r['runner_ms']:>14.2f}{r['per_point_ms']:>14.2f}"
        f"{r['store_ms']:>13.2f}{r['robot_ms']:>13.1f}{r['tracker_ms']:>15.1f}"
    )
    print(
        "runner ms/pt: time per point outside the robot and tracker drivers (w/o planning: less the one-off"
    )
    print(
        "plan of the whole grid); 'of it store': the campaign store's calls (the resume check and the durable"
    )
    print("commit, fsync included)")


if __name__ == "__main__":
    main()
