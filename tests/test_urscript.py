"""URScript programs read and compensated offline (hil.compensation.urscript, .program, `hil compensate PROGRAM`).

The programs are written here in the style PolyScope saves (`global Waypoint_1_p=p[...]`, its `_q`, `$` labels,
get_inverse_kin with qnear, pose_trans of a constant feature) and in an engineer's hand (pose literals, blends,
comments). The compensated joints are judged through `CalibratedModel.predict_poses`, not the loop's predictor.
"""

from __future__ import annotations

import gzip
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from hil.compensation.program import ProgramOptions, compensate_program
from hil.compensation.target_update import pose_errors
from hil.compensation.urscript import ProgramError, read_program
from hil.geometry.ik import ur_branch_index
from hil.geometry.kinematics import forward_kinematics
from hil.geometry.se3 import make_transform, pose_to_transform, transform_to_pose
from tests.cli_in_process import hil_in_process

sys.path.insert(0, str(Path(__file__).parent))
from calib_data import compliant_ur10, ur10_joints  # noqa: E402

TOOL = np.array([0.03, -0.02, 0.11])


@pytest.fixture(scope="module")
def model():
    return compliant_ur10(0, {1: TOOL}, TOOL, n_poses=200)


def literal(v: np.ndarray) -> str:
    return "p[" + ", ".join(f"{x:.12f}" for x in v) + "]"


def joints_text(q: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(v)) for v in q) + "]"


def tcp_poses(model, q: np.ndarray) -> np.ndarray:
    """UR pose vectors of the TCP (the SMR point, flange axes) at nominal joints q."""
    return transform_to_pose(forward_kinematics(model.nominal, q) @ make_transform(np.eye(3), TOOL))


def polyscope(model, q: np.ndarray, extra: str = "") -> str:
    poses = tcp_poses(model, q)
    lines = [
        "def Program():",
        "  set_standard_analog_input_domain(0, 1)",
        f"  set_tcp({literal([*TOOL, 0, 0, 0])})",
    ]
    for k in range(len(q)):
        lines += [
            f"  global Waypoint_{k + 1}_p={literal(poses[k])}",
            f"  global Waypoint_{k + 1}_q={joints_text(q[k])}",
        ]
    lines.append('  $ 1 "Robot Program"')
    for k in range(len(q)):
        lines.append(f'  $ {k + 2} "Waypoint_{k + 1}"')
        lines.append(
            f"  movej(get_inverse_kin(Waypoint_{k + 1}_p, qnear=Waypoint_{k + 1}_q), a=1.39, v=1.04)"
        )
    return "\n".join([*lines, extra, "end"]) + "\n"


def test_polyscope_program_targets_with_qnear_and_labels(model):
    q = ur10_joints(np.random.default_rng(1), 3)
    motions = read_program(polyscope(model, q))
    targets = motions.pose_targets
    assert [t.command for t in targets] == ["movej"] * 3
    assert [t.line for t in targets] == [12, 14, 16]
    for t, qk, pose in zip(targets, q, tcp_poses(model, q), strict=True):
        np.testing.assert_allclose(t.q_near, qk)
        np.testing.assert_allclose(t.T_base_tcp, pose_to_transform(pose), atol=1e-11)
        np.testing.assert_allclose(t.T_flange_tcp[:3, 3], TOOL)
    assert motions.runtime == []


def test_feature_frames_fold_and_runtime_poses_are_listed():
    plane = np.array([0.4, -0.2, 0.1, 0.0, 0.0, 0.7])
    local = np.array([0.05, 0.02, 0.3, 3.1, 0.1, 0.0])
    text = "\n".join(
        [
            "def p1():",
            f"  global Plane_1={literal(plane)}",
            f"  movel(pose_trans(Plane_1, pose_trans(pose_inv({literal(local)}), {literal(local)})), a=1.2, v=0.25)",
            f"  movel(pose_trans(Plane_1, {literal(local)}), a=1.2, v=0.25, r=0.005)  # blend kept",
            "  pick = get_actual_tcp_pose()",
            "  movel(pick, a=1.2, v=0.1)",
            f"  moved = {literal(local)}",
            f"  moved = pose_trans(moved, {literal(local)})",
            "  movep(moved, a=1.2, v=0.1, r=0.01)",
            "  movej([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])",
            "end",
        ]
    )
    motions = read_program(text)
    T_plane, T_local = pose_to_transform(plane), pose_to_transform(local)
    targets = motions.pose_targets
    np.testing.assert_allclose(targets[0].T_base_tcp, T_plane, atol=1e-12)
    np.testing.assert_allclose(targets[1].T_base_tcp, T_plane @ T_local, atol=1e-12)
    assert [(r.line, r.command) for r in motions.runtime] == [(6, "movel"), (9, "movep")]
    assert "get_actual_tcp_pose" in motions.runtime[0].why
    assert "assigned 2 times" in motions.runtime[1].why
    assert [type(m).__name__ for m in motions.motions] == ["PoseTarget", "PoseTarget", "JointTarget"]


def test_rewrite_keeps_every_other_character(model):
    q = ur10_joints(np.random.default_rng(2), 4)
    poses = tcp_poses(model, q)
    text = "\n".join(
        [
            "def Work():",
            f"  set_tcp({literal([*TOOL, 0, 0, 0])})",
            '  textmsg("start")  # say so',
            "  set_standard_digital_out(2, True)",
            f"  movel({literal(poses[0])}, a=1.2, v=0.25, r=0.002)  # approach",
            f"  movec({literal(poses[1])}, {literal(poses[2])}, a=1.2, v=0.1, r=0.0, mode=0)",
            "  movej([0.1, -1.6, 1.5, -1.4, -1.57, 0.2], a=1.4, v=1.05)",
            f"  movej({literal(poses[3])}, a=1.4, v=1.05)",
            "  sleep(0.5)",
            "end",
        ]
    )
    motions = read_program(text)
    assert [(t.command, t.role) for t in motions.pose_targets] == [
        ("movel", "target"),
        ("movec", "via"),
        ("movec", "target"),
        ("movej", "target"),
    ]
    done = compensate_program(model, motions)
    assert np.all(done.result.ok)
    old, new = text.splitlines(), done.text.splitlines()
    assert len(new) == len(old)
    for number in (1, 2, 3, 4, 7, 9, 10):
        assert new[number - 1] == old[number - 1]
    assert new[4].endswith(", a=1.2, v=0.25, r=0.002)  # approach") and new[4].startswith("  movel([")
    assert new[5].startswith("  movec([") and new[5].endswith(", a=1.2, v=0.1, r=0.0, mode=0)")
    assert "p[" not in new[4] + new[5] + new[7]
    rewritten = read_program(done.text)
    q_written = np.array([m.q for m in rewritten.motions if m.line != 7])
    np.testing.assert_allclose(q_written, done.result.q, atol=1e-9)


def test_compensated_joints_reach_the_poses_on_the_programs_branches(model):
    """Each target on the branch of its qnear (two of them elbow-down after elbow-up neighbours), and the
    model puts the TCP on every pose: the predicted pose error is below the loop's threshold."""
    rng = np.random.default_rng(3)
    q = ur10_joints(rng, 6)
    flipped = q.copy()
    flipped[[1, 4], 2] *= -1  # the elbow on the other side for two waypoints
    T_target_flange = forward_kinematics(model.nominal, flipped)
    motions = read_program(polyscope(model, flipped))
    done = compensate_program(model, motions, ProgramOptions(threshold_m=1e-6))
    assert np.all(done.result.ok), done.result.summary()
    np.testing.assert_array_equal(
        ur_branch_index(model.kinematic, done.result.q), ur_branch_index(model.nominal, flipped)
    )
    reached = model.predict_poses(done.result.q)
    T_target = model.T_tracker_base @ T_target_flange
    T_target[:, :3, 3] = (
        T_target_flange[:, :3, :3] @ TOOL + T_target_flange[:, :3, 3]
    ) @ model.T_tracker_base[:3, :3].T + model.T_tracker_base[:3, 3]
    dp, dr = pose_errors(reached, T_target)
    assert dp.max() < 2e-6 and dr.max() < 1e-4
    dp0, _ = pose_errors(model.predict_poses(flipped), T_target)
    assert dp0.mean() > 2e-4  # the nominal joints miss: there was something to compensate


def test_payload_moves_the_joints_through_the_gravity_yield(model):
    q = ur10_joints(np.random.default_rng(4), 3)
    light = compensate_program(model, read_program(polyscope(model, q, "")))
    text = polyscope(model, q).replace(
        "  set_standard_analog_input_domain(0, 1)", "  set_payload(8.0, [0, 0, 0.05])"
    )
    heavy = compensate_program(model, read_program(text))
    assert [t.payload_kg for t in heavy.targets] == [8.0] * 3
    shift = np.abs(heavy.result.q - light.result.q).max(axis=1)
    assert np.all(shift > 1e-5)  # an 8 kg payload bends joints 2 and 3 by tens of microradians


def test_tcp_off_the_smr_needs_the_flanges_orientation(model):
    q = ur10_joints(np.random.default_rng(5), 2)
    text = polyscope(model, q).replace(
        f"set_tcp({literal([*TOOL, 0, 0, 0])})", "set_tcp(p[0, 0, 0.2, 0, 0, 0])"
    )
    with pytest.raises(ProgramError, match="flange's orientation"):
        compensate_program(model, read_program(text))
    three = replace(model, tools={1: TOOL, 2: TOOL + [0.05, 0, 0], 3: TOOL + [0, 0.05, 0]})
    done = compensate_program(three, read_program(text))
    assert np.all(done.result.ok)


def test_cli_rewrites_a_program_and_refuses_a_urp(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    q = ur10_joints(np.random.default_rng(6), 3)
    extra = "  movel(pose_trans(get_actual_tcp_pose(), p[0, 0, 0.01, 0, 0, 0]))"
    (tmp_path / "job.script").write_text(polyscope(model, q, extra))
    code, out, err = hil_in_process(
        "compensate", "model.json", "job.script", "-o", "out.script", cwd=tmp_path, capsys=capsys
    )
    assert code == 0, err
    assert out.startswith("3 pose targets compensated (ok 3)")
    assert "line 17: movel(pose_trans(get_actual_tcp_pose()" in err
    assert (tmp_path / "out.script").read_text().count("movej([") == 3
    (tmp_path / "job.urp").write_bytes(gzip.compress(b"<URProgram name='job'/>"))
    code, _, err = hil_in_process(
        "compensate", "model.json", "job.urp", "-o", "out2.script", cwd=tmp_path, capsys=capsys
    )
    assert code == 2
    assert ".urp" in err and "save the program" in err


def test_cli_frame_base_equals_the_tracker_frame_targets(model, tmp_path, capsys):
    model.save(tmp_path / "model.json")
    q = ur10_joints(np.random.default_rng(7), 5)
    T = forward_kinematics(model.nominal, q)
    p_base = T[:, :3, :3] @ TOOL + T[:, :3, 3]
    p_tracker = p_base @ model.T_tracker_base[:3, :3].T + model.T_tracker_base[:3, 3]
    cols = ["x_mm", "y_mm", "z_mm"]
    pd.DataFrame(p_base * 1e3, columns=cols).to_csv(tmp_path / "base.csv", index=False)
    pd.DataFrame(p_tracker * 1e3, columns=cols).to_csv(tmp_path / "tracker.csv", index=False)
    for name, frame in (("base", "base"), ("tracker", "tracker")):
        code, _, err = hil_in_process(
            "compensate",
            "model.json",
            f"{name}.csv",
            "-o",
            f"{name}_q.csv",
            "--frame",
            frame,
            cwd=tmp_path,
            capsys=capsys,
        )
        assert code == 0, err
    a, b = (pd.read_csv(tmp_path / f"{n}_q.csv") for n in ("base", "tracker"))
    joint_cols = [f"q{j}_rad" for j in range(1, 7)]
    np.testing.assert_allclose(a[joint_cols].to_numpy(), b[joint_cols].to_numpy(), atol=1e-9)
    assert a["initial_error_mm"].mean() > 0.2


def test_the_motion_order_decides_the_approach_on_a_model_with_backlash(model):
    """The same pose after a taught position below it and after one above it on joint 2: the compensated
    joints differ by the gap, and each, reached from its own side, puts the TCP on the pose."""
    from hil.model.effects import make_effect

    backlash = make_effect("backlash", 2)
    backlash.params = np.array([2e-4])  # rad: half the gap
    with_gap = model.with_effect(backlash)
    q = ur10_joints(np.random.default_rng(8), 1)[0]
    pose = tcp_poses(model, q[None])[0]
    results = []
    for dq in (-0.2, 0.2):
        q_taught = q + np.array([0.0, dq, 0.0, 0.0, 0.0, 0.0])
        text = "\n".join(
            [
                "def p():",
                f"  set_tcp({literal([*TOOL, 0, 0, 0])})",
                f"  movej({joints_text(q_taught)})",
                f"  movej({literal(pose)})",
                "end",
            ]
        )
        done = compensate_program(with_gap, read_program(text), ProgramOptions(threshold_m=1e-6))
        assert np.all(done.result.ok)
        reached = with_gap.predict_poses(np.array([q_taught, done.result.q[0]]))[1]  # in this order
        T_flange = forward_kinematics(model.nominal, q[None])[0]
        meant = (
            model.T_tracker_base[:3, :3] @ (T_flange[:3, :3] @ TOOL + T_flange[:3, 3])
            + model.T_tracker_base[:3, 3]
        )
        assert np.linalg.norm(reached[:3, 3] - meant) < 2e-6
        results.append(done.result.q[0])
    gap = results[0] - results[1]
    assert abs(abs(gap[1]) - 4e-4) < 5e-5  # joint 2 takes the other side of the gap


def test_a_payload_the_model_cannot_weigh_is_said(model, tmp_path, capsys):
    q = ur10_joints(np.random.default_rng(9), 2)
    text = polyscope(model, q).replace("  set_standard_analog_input_domain(0, 1)", "  set_payload(3.0)")
    (tmp_path / "job.script").write_text(text)
    for name, m in (("weighed", model), ("rigid", replace(model, effects=[]))):
        m.save(tmp_path / f"{name}.json")
        code, _, err = hil_in_process(
            "compensate", f"{name}.json", "job.script", "-o", f"{name}.script", cwd=tmp_path, capsys=capsys
        )
        assert code == 0, err
        assert ("payload's sag is not compensated" in err) == (name == "rigid")


def test_literals_read_without_an_expression_tree_equal_the_trees_reading():
    """PolyScope's literals and get_inverse_kin(name, qnear=name) take a fast path: it must read what the
    expression tree reads (pose_trans with the identity forces the tree on the same values)."""
    pose = "p[0.4, -0.2, 0.3, 0.1, -3.0, 0.05]"
    joints = "[0.1, -1.2, 1.3, -1.6, -1.5, 0.2]"
    identity = "p[0, 0, 0, 0, 0, 0]"
    text = "\n".join(
        [
            f"  global A_p={pose}",
            f"  global A_q={joints}",
            f"  global B_p=pose_trans({identity}, {pose})",
            f"  global B_q=[{joints[1:-1]}, 0.0][0:6]",  # not a literal: the tree refuses it, qnear unread
            "  movej(get_inverse_kin(A_p, qnear=A_q))",
            "  movej(get_inverse_kin( A_p ))",
            "  movej(get_inverse_kin(pose_trans(p[0,0,0,0,0,0], A_p), qnear=A_q))",
            f"  movel({pose}, a=1.2)",
            f"  movel(pose_trans({identity}, {pose}))",
            f"  movej({joints})",
            "  movej(get_inverse_kin(B_p, qnear=B_q))",
        ]
    )
    motions = read_program(text)
    poses = motions.pose_targets
    assert [t.line for t in poses] == [5, 6, 7, 8, 9]
    for t in poses[1:]:
        np.testing.assert_allclose(t.T_base_tcp, poses[0].T_base_tcp, atol=1e-15)
    np.testing.assert_array_equal(poses[0].q_near, poses[2].q_near)
    assert poses[1].q_near is None and poses[3].q_near is None
    np.testing.assert_array_equal(motions.motions[5].q, [0.1, -1.2, 1.3, -1.6, -1.5, 0.2])
    assert [r.line for r in motions.runtime] == [11]
