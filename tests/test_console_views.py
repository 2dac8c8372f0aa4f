"""What the console's plots show, from a campaign written here with known answers: each point's deviation
from where the nominal model and the campaign's registration put it, and the reference poses' drift since
their first round."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from cell_fixtures import sim_cell_toml

from hil.console.station import CONTROL_LAPSE_S, Station
from hil.console.views import history, point_deviations
from hil.data.store import CampaignStore, MeasurementRecord
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import make_transform, transform_points
from hil.runner.cell_config import parse_cell_config

T_TRACKER_BASE = make_transform(np.eye(3), np.array([2.0, -0.5, 0.3]))


def point(step: str, point_id: str, q: np.ndarray, p_tracker_m: np.ndarray, t_s: float) -> MeasurementRecord:
    return MeasurementRecord(
        procedure="grid_sampling", step=step, point_id=point_id, q_target_rad=q, q_rad=q,
        T_base_flange=np.eye(4), p_tracker_m=p_tracker_m, spread_m=[5e-6] * 3, std_m=[5e-6] * 3, shots=3,
        rejected_shots=(), smr=1, location="nest1", temperature_c=20.0 + t_s / 100, pressure_hpa=1013.0,
        humidity_pct=40.0, timestamp_s=1.7e9 + t_s,
    )  # fmt: skip


@pytest.fixture(scope="module")
def config():
    return parse_cell_config(tomllib.loads(sim_cell_toml()))


def nominal_point(config, q: np.ndarray) -> np.ndarray:
    """Where the nominal model and the registration put nest 1's SMR (tracker frame, m)."""
    T = forward_kinematics(config.nominal, q[None])[0]
    return transform_points(T_TRACKER_BASE, (T[:3, :3] @ config.nests_flange_m[0] + T[:3, 3])[None])[0]


def test_deviations_and_reference_drift(tmp_path, config):
    rng = np.random.default_rng(3)
    q = config.q_home_rad + rng.uniform(-0.3, 0.3, (4, 6))
    offsets_mm = [0.5, 1.0, 2.0, 0.25]
    campaign = tmp_path / "c.sqlite"
    with CampaignStore(campaign) as store:
        store.finish_step("registration", "fit", {"T_tracker_base": T_TRACKER_BASE.tolist(), "rms_mm": 0.5})
        store.record_measurement(point("reference", "r1-000", q[0], nominal_point(config, q[0]), 0.0))
        for k in (1, 2):
            p = nominal_point(config, q[k]) + [offsets_mm[k] / 1e3, 0.0, 0.0]
            store.record_measurement(point("grid", f"g{k}", q[k], p, 10.0 * k))
        moved = nominal_point(config, q[0]) + [0.0, 0.0, 0.03e-3]  # the same pose 0.03 mm higher
        store.record_measurement(point("reference", "r1-001", q[0], moved, 60.0))
    shown = point_deviations(campaign, config)
    assert shown.registered
    assert shown.point_id == ["r1-000", "g1", "g2", "r1-001"]
    assert shown.deviation_mm == pytest.approx([0.0, 1.0, 2.0, 0.03], abs=1e-6)
    assert shown.drift_mm[0] == pytest.approx(0.0) and shown.drift_mm[3] == pytest.approx(0.03, abs=1e-6)
    assert shown.drift_mm[1] is None and shown.drift_mm[2] is None  # grid points have no drift
    assert shown.reference_pose == ["r1", None, None, "r1"]  # the drift plot's trace of each reading
    assert shown.t_s == [0.0, 10.0, 20.0, 60.0]
    [entry] = history(tmp_path)
    assert entry.name == "c.sqlite" and [(p.procedure, p.points) for p in entry.procedures] == [
        ("grid_sampling", 4)
    ]
    assert entry.driven_by is None and entry.report is None


def test_no_deviation_before_a_registration(tmp_path, config):
    campaign = tmp_path / "c.sqlite"
    q = config.q_home_rad
    with CampaignStore(campaign) as store:
        store.record_measurement(point("grid", "g1", q, nominal_point(config, q), 0.0))
    shown = point_deviations(campaign, config)
    assert not shown.registered and shown.deviation_mm == [None]
    assert shown.reference_pose == [None]


def test_control_goes_to_one_browser_and_lapses_when_its_page_is_gone(tmp_path, config):
    now = [0.0]
    station = Station(config, tmp_path, clock=lambda: now[0])
    assert station.claim("a") and not station.claim("b")
    assert station.controlled_by_another("b") and not station.controlled_by_another("a")
    now[0] = CONTROL_LAPSE_S  # a's page kept its stream open until now
    station.seen("a")
    now[0] += CONTROL_LAPSE_S
    assert not station.claim("b")  # seen just the lapse ago: still a's
    now[0] += 0.5
    assert not station.controlled_by_another("b")
    assert station.claim("b") and station.controls("b") and not station.controls("a")
    station.release("a")  # not a's to release any more
    assert station.controls("b")
    station.release("b")
    assert station.claim("a")
