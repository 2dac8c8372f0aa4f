"""A procedure shipped from outside this repository registers through the `hil.procedures` entry points,
shows up in `hil run --help`, is refused with its declared range, and runs on the simulated cell."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from hil.data.store import CampaignStore
from tests.sim_session import running_cell

pytestmark = pytest.mark.sim  # one test runs the plug-in on the simulated cell

# A shop floor's own procedure, in one short file: three poses near the middle of the working volume, the
# SMR in nest 1; judged by how far the measured distances between the points are from the nominal ones.
PLUGIN_MODULE = '''
"""Distance check: is the arm's scale right? Put SMR 1 in tool nest 1, guide the beam onto it; the robot
visits a few poses near the middle of its volume; the distances between the measured points must match
the nominal ones within the limit."""

import numpy as np

from hil.geometry.kinematics import tool_points
from hil.runner.operator import OperatorStep
from hil.runner.plan import Plan, PlannedPose
from hil.runner.clear_joints import clear_travel_order, plan_cell_joints
from hil.runner.planners import facing_poses, workspace_box
from hil.runner.procedure import Limit, Measurement, Parameter, Procedure

NAME = "distance_check"


def plan(config, options):
    poses, spacing_m = options.poses, options.spacing_m
    box = workspace_box(config.nominal, config.p_base_tracker_m)
    offsets = spacing_m * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T = facing_poses(box.centre_m + offsets, config.p_base_tracker_m, np.random.default_rng(0), tilt_deg=0.0)
    joints = plan_cell_joints(config, T, nest=1)  # clear of the arm, the tracker and the keep-out boxes
    place = (OperatorStep("Put SMR 1 in tool nest 1.", "place_smr", smr=1, location="nest1"),)
    lock = (OperatorStep("Guide the beam onto SMR 1.", "lock_beam", smr=1),)
    q = joints.q[joints.usable][:poses]
    q = q[clear_travel_order(config.nominal, config.envelope, q, config.q_home_rad)]
    return Plan(NAME, [PlannedPose(f"d{k + 1}", NAME, "poses", qk, "nest1", setup=place, at_pose=lock) for k, qk in enumerate(q)], config)


def check(session, options, the_plan):
    relock = the_plan.poses[0].at_pose[0]  # no registration needed: the operator guides a broken beam back
    session.engine.visit(the_plan, aim=False, reaim=lambda: session.ask(relock))
    points = session.recorded_points(NAME, "poses")
    nominal = tool_points(session.nominal, points.q_rad, session.config.nests_flange_m[0])
    i, j = np.triu_indices(len(nominal), 1)
    error = np.abs(np.linalg.norm(points.p_tracker_m[i] - points.p_tracker_m[j], axis=1)
                   - np.linalg.norm(nominal[i] - nominal[j], axis=1))
    judged = session.engine.measured("distance_error", float(error.max()))  # judged against its limit, recorded
    result = {"max_distance_error_mm": float(error.max() * 1e3), "passed": judged.verdict == "pass"}
    session.finish_step(NAME, "check", result)
    return result


PROCEDURE = Procedure(
    name=NAME,
    purpose="is the arm's scale right: distances between a few measured points against the nominal ones",
    instruction=__doc__,
    parameters=(
        Parameter("poses", "poses to measure", 3, int, minimum=3, maximum=6),
        Parameter("spacing", "distance between the poses", 100.0, float, unit="mm", minimum=20.0, maximum=300.0),
    ),
    plan=plan,
    body=check,
    limits=(Limit("max_distance_error", "distance error between two points", 3.0, "mm"),),
    measurements=(Measurement("distance_error", "worst distance error", "mm", "max_distance_error"),),
    steps=("poses", "check"),
    summary=lambda result: f"distance check: worst {result['max_distance_error_mm']:.3f} mm",
)
'''


# The same kind of plug-in written for the hil before options records: its plan and body take every
# parameter as a keyword. It is refused with what to change, and hides no other procedure.
OLD_FORM_MODULE = """
from hil.runner.plan import Plan
from hil.runner.procedure import Parameter, Procedure


def plan(config, *, poses):
    return Plan("old_check", [], config)


def check(session, *, poses):
    return {}


PROCEDURE = Procedure(
    name="old_check", purpose="written for an older hil", instruction="",
    parameters=(Parameter("poses", "poses to measure", 3, int),), plan=plan, body=check,
)
"""


@pytest.fixture
def plugin_env(tmp_path):
    """A folder holding the plug-in module and its installed metadata, on PYTHONPATH for a `hil` process."""
    folder = tmp_path / "site"
    folder.mkdir()
    (folder / "shop_checks.py").write_text(textwrap.dedent(PLUGIN_MODULE))
    (folder / "old_checks.py").write_text(OLD_FORM_MODULE)
    info = folder / "shop_checks-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: shop-checks\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[hil.procedures]\ndistance_check = shop_checks:PROCEDURE\nold_check = old_checks:PROCEDURE\n"
    )
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(folder), os.environ.get("PYTHONPATH", "")])}


def _hil(env, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "hil", *args], capture_output=True, text=True, timeout=timeout, env=env
    )


def test_an_installed_procedure_is_listed_with_its_purpose_and_parameters(plugin_env):
    listing = _hil(plugin_env, "run", "--help")
    assert listing.returncode == 0, listing.stderr
    assert "distance_check" in listing.stdout and "is the arm's scale right" in listing.stdout
    assert "registration" in listing.stdout  # the repository's own are still there
    own = _hil(plugin_env, "run", "distance_check", "--help")
    assert own.returncode == 0, own.stderr
    assert "--spacing-mm" in own.stdout and "20..300 mm" in own.stdout and "default 100" in own.stdout
    assert "distance error between two points: 3 mm" in own.stdout


def test_a_procedure_written_to_the_old_form_is_refused_with_what_to_change(plugin_env, tmp_path):
    listing = _hil(plugin_env, "run", "--help")
    assert listing.returncode == 0 and "distance_check" in listing.stdout  # the others still load
    assert "old_check" in listing.stdout and "cannot load" in listing.stdout
    done = _hil(plugin_env, "run", "old_check", "--cell", "x.toml", "--campaign", str(tmp_path / "c.sqlite"))
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "its plan plan(config, *, poses)" in done.stderr and "takes poses by keyword" in done.stderr
    assert "Write it as `def plan(config, options)`" in done.stderr and "options.poses" in done.stderr


def test_an_installed_procedure_refuses_bad_parameters_before_connecting(plugin_env, tmp_path):
    from tests.cell_fixtures import sim_cell_toml

    cell = tmp_path / "cell.toml"
    cell.write_text(sim_cell_toml().replace("127.0.0.9", "127.254.254.254"))
    base = ["run", "distance_check", "--cell", str(cell), "--campaign", str(tmp_path / "c.sqlite")]
    done = _hil(plugin_env, *base, "--spacing-mm", "500")
    assert done.returncode == 2 and "--spacing-mm 500" in done.stderr and "20..300 mm" in done.stderr
    done = _hil(plugin_env, *base, "--spacing-m", "0.1")
    assert done.returncode == 2 and "use --spacing-mm" in done.stderr
    assert not (tmp_path / "c.sqlite").exists()


@pytest.mark.sim
@pytest.mark.timeout(300)
def test_an_installed_procedure_runs_on_the_simulated_cell(plugin_env, tmp_path):
    campaign = tmp_path / "campaign.sqlite"
    with running_cell(tmp_path, seed=2, time_scale=200.0) as (_, config):
        args = [
            "run",
            "distance_check",
            "--cell",
            str(tmp_path / "cell.toml"),
            "--campaign",
            str(campaign),
            "--poses",
            "4",
        ]
        done = _hil(plugin_env, *args, timeout=240)
        assert done.returncode == 0, done.stderr
        assert "distance check: worst" in done.stdout
        again = _hil(plugin_env, *args, timeout=240)  # a resume with nothing left to measure
        assert again.returncode == 0, again.stderr
    with CampaignStore(campaign) as store:
        rows = store.measurements("distance_check", "poses")
        result = store.step_result("distance_check", "check")
    assert sorted(rows["point_id"]) == ["d1", "d2", "d3", "d4"]  # four points, each measured once
    assert result is not None and result["passed"]
    with CampaignStore(campaign) as store:
        (judged,) = [o for o in store.outcomes() if o.procedure == "distance_check"][-1:]
    assert judged.verdict == "pass" and judged.limit_value == pytest.approx(3e-3)
    assert 0.0 < result["max_distance_error_mm"] < 3.0  # a real measurement: the arm's error, not zero


def test_finding_who_publishes_a_step_imports_no_diagnosis():
    """`hil run` reads every registered declaration to find the step a procedure needs (the registration):
    the declarations are light, the diagnosis and the reports are imported when a procedure runs them."""
    found = subprocess.run(
        [
            sys.executable, "-c",
            "import sys\n"
            "from hil.runner.procedure import Role\n"
            "from hil.runner.registry import publisher\n"
            "print(publisher(Role.REGISTRATION))\n"
            "print(sorted(m for m in sys.modules if m.startswith(('hil.analysis.diagnosis', 'hil.report.html'))))",
        ],
        capture_output=True, text=True, check=True, timeout=60,
    )  # fmt: skip
    assert found.stdout.splitlines() == ["('registration', 'fit')", "[]"], found.stdout
