"""The fake tracker inside `hil sim`, beside the fake controller on the same simulated cell: announced as
{"tracker": {"url": ...}} and reachable, with its control-channel faults."""

import numpy as np
import pytest

from drivers.emscon import EmsconConfig, EmsconTracker
from fakes import launch
from hil.instruments.tracker import NoTargetError

pytestmark = pytest.mark.sim  # starts a simulated cell or a fake server over sockets


@pytest.mark.timeout(90)
def test_tracker_served_by_hil_sim():
    with launch.sim_cell(time_scale=10) as cell:
        url = cell.info["tracker"]["url"]
        assert url.startswith(f"socket://{cell.host}:")
        p_smr = np.array([2.0, 0.5, -0.2])
        placed = cell.control.call("place_smr", smr_id=2, kind="fixed", point_m=p_smr.tolist())
        np.testing.assert_allclose(placed["center_tracker_m"], p_smr)
        with EmsconTracker(EmsconConfig(url=url, meas_time_s=0.5)) as tracker:
            tracker.point_at(p_smr + 0.01)
            m = tracker.measure(shots=3)
            assert np.linalg.norm(m.p_tracker_m - p_smr) < 1e-4
            cell.control.call("tracker.fault", kind="beam_break", count=1)
            with pytest.raises(NoTargetError):
                tracker.measure()
            tracker.measure()
            state = cell.control.call("tracker.state")
        assert state["locked_smr"] == 2 and state["exit_requests"] == 0
