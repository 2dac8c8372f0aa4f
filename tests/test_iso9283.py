"""ISO 9283 figures against answers worked out by hand on small campaigns, each refusal, and the command."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from hil.analysis.standards.iso9283 import (
    Iso9283Error,
    commanded_along,
    cube_poses,
    path_performance,
    pose_performance,
)
from tests.cli_in_process import run_hil

UM = 1e-3  # 1 um in mm: the tolerance of every figure


def campaign() -> pd.DataFrame:
    """P1: 3 cycles, commanded (100, 200, 300) mm, attained (101, 200, 300), (103, 200, 300), (102, 203, 300);
    angles commanded (10, 0, 179) deg, attained rx 10.1 / 10.3 / 10.2, rz -179.9 / 179.9 / -179.8 (across
    +-180). P2: commanded (0, 0, 0), attained (0, 0, 0), (1, 0, 0). P4: commanded (300, 0, 0), attained
    (301, 0, 0), (303, 0, 0)."""
    rows = [
        ("P1", 1, (101, 200, 300), (100, 200, 300), (10.1, 0, -179.9)),
        ("P1", 2, (103, 200, 300), (100, 200, 300), (10.3, 0, 179.9)),
        ("P1", 3, (102, 203, 300), (100, 200, 300), (10.2, 0, -179.8)),
        ("P2", 1, (0, 0, 0), (0, 0, 0), (10, 0, 179)),
        ("P2", 2, (1, 0, 0), (0, 0, 0), (10, 0, 179)),
        ("P4", 1, (301, 0, 0), (300, 0, 0), (10, 0, 179)),
        ("P4", 2, (303, 0, 0), (300, 0, 0), (10, 0, 179)),
    ]
    data = {f"q{i}_rad": [0.1 * k for k in range(len(rows))] for i in range(1, 7)}
    df = pd.DataFrame(data)
    df["pose"] = [r[0] for r in rows]
    df["cycle"] = [r[1] for r in rows]
    for k, ax in enumerate("xyz"):
        df[f"{ax}_mm"] = [float(r[2][k]) for r in rows]
        df[f"{ax}_cmd_mm"] = [float(r[3][k]) for r in rows]
        df[f"r{ax}_deg"] = [float(r[4][k]) for r in rows]
        df[f"r{ax}_cmd_deg"] = [(10.0, 0.0, 179.0)[k]] * len(rows)
    return df


@pytest.fixture(scope="module")
def report() -> dict:
    return pose_performance(campaign()).to_dict()


def test_pose_accuracy_is_the_barycentre_minus_the_command(report):
    """Barycentre (102, 201, 300): AP_x 2, AP_y 1, AP_z 0, AP sqrt(5)."""
    p1 = report["poses"]["P1"]
    assert p1["AP_x_mm"] == pytest.approx(2.0, abs=UM)
    assert p1["AP_y_mm"] == pytest.approx(1.0, abs=UM)
    assert p1["AP_z_mm"] == pytest.approx(0.0, abs=UM)
    assert p1["AP_mm"] == pytest.approx(2.236068, abs=UM)


def test_pose_repeatability_is_the_mean_distance_plus_three_sigmas(report):
    """l = sqrt2, sqrt2, 2: mean 1.609476, S_l 0.338204 (n - 1), RP 2.624087; P2: l = 0.5, 0.5, RP 0.5."""
    p1 = report["poses"]["P1"]
    assert p1["l_mean_mm"] == pytest.approx(1.609476, abs=UM)
    assert p1["S_l_mm"] == pytest.approx(0.338204, abs=UM)
    assert p1["RP_mm"] == pytest.approx(2.624087, abs=UM)
    assert report["poses"]["P2"]["RP_mm"] == pytest.approx(0.5, abs=UM)
    assert report["poses"]["P2"]["AP_mm"] == pytest.approx(0.5, abs=UM)


def test_orientation_accuracy_wraps_across_180_degrees(report):
    """rx errors 0.1, 0.3, 0.2: AP_a 0.2, RP_a 3 x 0.1; rz errors 1.1, 0.9, 1.2 (wrapped): AP_c 1.066667,
    RP_c 3 x 0.152753."""
    p1 = report["poses"]["P1"]
    assert p1["AP_a_deg"] == pytest.approx(0.2, abs=1e-6)
    assert p1["RP_a_deg"] == pytest.approx(0.3, abs=1e-6)
    assert p1["AP_c_deg"] == pytest.approx(1.066667, abs=1e-6)
    assert p1["RP_c_deg"] == pytest.approx(0.458258, abs=1e-6)
    assert p1["AP_b_deg"] == pytest.approx(0.0, abs=1e-9)


def test_distance_accuracy_between_p2_and_p4(report):
    """D = 301, 302 against 300: AD 1.5, RD 3 x 0.707107."""
    d = report["distance"]
    assert d["D_cmd_mm"] == pytest.approx(300.0, abs=UM)
    assert d["AD_mm"] == pytest.approx(1.5, abs=UM)
    assert d["RD_mm"] == pytest.approx(2.121320, abs=UM)


def test_the_five_poses_lie_on_the_cubes_diagonal_plane_a_tenth_in_from_the_corners():
    p = cube_poses(np.array([1.0, 2.0, 3.0]), 0.4)
    assert np.allclose(p[0], [1.0, 2.0, 3.0])
    half_diagonal = 0.5 * math.sqrt(0.4**2 * 2 + 0.4**2)
    assert np.allclose(np.linalg.norm(p[1:] - p[0], axis=1), 0.8 * half_diagonal)
    normal = np.cross(p[2] - p[1], p[4] - p[1])
    assert np.allclose((p - p[0]) @ normal, 0.0, atol=1e-12)
    assert np.linalg.norm(p[1] - p[3]) == pytest.approx(0.8 * 2 * half_diagonal)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda df: df.drop(columns=["cycle"]), "missing column(s) cycle"),
        (lambda df: df.drop(columns=["z_cmd_mm"]), "missing column(s) z_cmd_mm"),
        (lambda df: df[df["pose"] != "P1"].iloc[1:], "pose P2 has 1 cycle"),
        (lambda df: df.assign(cycle=[1, 1, 3, 1, 2, 1, 2]), "pose P1 cycle 1 appears twice"),
        (lambda df: df.assign(x_cmd_mm=[100, 100.5, 100, 0, 0, 300, 300]), "commanded at positions"),
    ],
)
def test_campaigns_the_formulas_cannot_take_are_refused_with_the_reason(change, words):
    with pytest.raises(Iso9283Error, match=None) as info:
        pose_performance(change(campaign()))
    assert words in str(info.value)


def test_path_accuracy_on_a_line_and_a_circle():
    """Two runs offset by 0.1 and 0.3 mm from the commanded path (other sampling than the command): the
    barycentre path lies 0.2 mm off (AT), each run 0.1 mm from it (RT = 0.1 + 3 x 0)."""
    x = np.linspace(0.0, 0.1, 11)
    line = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    xs = np.linspace(-0.01, 0.11, 97)
    runs = [np.column_stack([xs, np.full_like(xs, dy), np.zeros_like(xs)]) for dy in (0.1e-3, 0.3e-3)]
    fig = path_performance(line, runs)
    assert fig.AT_m * 1e3 == pytest.approx(0.2, abs=UM) and fig.RT_m * 1e3 == pytest.approx(0.1, abs=UM)
    phi = np.deg2rad(np.linspace(0.0, 180.0, 19))
    circle = 0.05 * np.column_stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)])
    phs = np.deg2rad(np.arange(-5.0, 185.0, 0.25))
    runs = [r * np.column_stack([np.cos(phs), np.sin(phs), np.zeros_like(phs)]) for r in (0.0501, 0.0503)]
    fig = path_performance(circle, runs)
    assert fig.AT_m * 1e3 == pytest.approx(0.2, abs=UM) and fig.RT_m * 1e3 == pytest.approx(0.1, abs=UM)
    with pytest.raises(Iso9283Error, match="at least 2 runs"):
        path_performance(circle, runs[:1])


def test_the_command_writes_the_figures_as_json(tmp_path, capsys):
    campaign().to_csv(tmp_path / "iso.csv", index=False)
    phi = np.deg2rad(np.arange(0.0, 180.0, 0.5))
    samples = []
    for run, r in ((1, 50.1), (2, 50.3), (3, 50.2)):
        samples.append(pd.DataFrame({
            "path": "circle", "run": run, "x_mm": r * np.cos(phi), "y_mm": r * np.sin(phi), "z_mm": 0.0,
            "x_cmd_mm": 50 * np.cos(phi), "y_cmd_mm": 50 * np.sin(phi), "z_cmd_mm": 0.0,
        }))  # fmt: skip
    pd.concat(samples).to_csv(tmp_path / "paths.csv", index=False)
    r = run_hil("iso9283", "iso.csv", "--paths", "paths.csv", "--json", "r.json", cwd=tmp_path, capsys=capsys)
    assert r.returncode == 0, r.stderr
    out = json.loads((tmp_path / "r.json").read_text())
    assert out["poses"]["P1"]["AP_mm"] == pytest.approx(2.236068, abs=UM)
    assert out["poses"]["P1"]["RP_mm"] == pytest.approx(2.624087, abs=UM)
    assert out["paths"]["circle"]["AT_mm"] == pytest.approx(0.2, abs=UM)
    assert "P1" in r.stdout and "AD +1.5000 mm" in r.stdout


def test_the_command_names_a_missing_column(tmp_path, capsys):
    campaign().drop(columns=["pose"]).to_csv(tmp_path / "iso.csv", index=False)
    r = run_hil("iso9283", "iso.csv", cwd=tmp_path, capsys=capsys)
    assert r.returncode == 2 and "missing column(s) pose" in r.stderr


def test_with_several_smrs_per_pose_one_is_assessed():
    """A second SMR read at every pose, 1 mm further along x: the default (lowest id) gives the first's
    figures, `smr=2` the second's (AP_x 1 mm larger, RP the same)."""
    one = campaign().assign(smr=1)
    two = one.assign(smr=2, x_mm=one["x_mm"] + 1.0)
    both = pd.concat([one, two], ignore_index=True)
    first, second = pose_performance(both).to_dict(), pose_performance(both, smr=2).to_dict()
    assert first["smr"] == 1 and first["poses"]["P1"]["AP_x_mm"] == pytest.approx(2.0, abs=UM)
    assert second["poses"]["P1"]["AP_x_mm"] == pytest.approx(3.0, abs=UM)
    assert second["poses"]["P1"]["RP_mm"] == pytest.approx(2.624087, abs=UM)
    with pytest.raises(Iso9283Error, match="no rows of SMR 3"):
        pose_performance(both, smr=3)


def test_a_sample_stands_at_its_foot_on_the_commanded_path_moving_forward_only():
    line = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    rest = np.array([[0.2, 0.1, 0.0], [0.19, -0.1, 0.0], [0.2, 0.0, 0.3]])  # at rest: noise back and forth
    moving = np.array([[0.5, 0.2, 0.0], [0.8, -0.1, 0.0], [1.3, 0.0, 0.0]])
    c = commanded_along(line, np.vstack([rest, moving]))
    np.testing.assert_allclose(c[:, 1:], 0.0)
    np.testing.assert_allclose(c[:, 0], [0.2, 0.2, 0.2, 0.5, 0.8, 1.0])  # never back, clipped at the end
    # a closed square: the start and the end sit on the same point, yet the samples go round in order
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]], float)
    run = np.array(
        [[0.01, 0.02, 0], [0.5, -0.01, 0], [1.01, 0.5, 0], [0.5, 1.0, 0], [-0.01, 0.5, 0], [0.0, 0.01, 0]]
    )
    c = commanded_along(square, run)
    np.testing.assert_allclose(
        c, [[0.01, 0, 0], [0.5, 0, 0], [1, 0.5, 0], [0.5, 1, 0], [0, 0.5, 0], [0, 0.01, 0]]
    )
    with pytest.raises(Iso9283Error, match="repeats a point"):
        commanded_along(np.array([[0.0, 0, 0], [0.0, 0, 0]]), rest)


def test_the_paths_lie_on_the_cubes_diagonal_plane():
    from procedures.iso9283 import CIRCLE_DIAMETER, Cube, check_speed, path_shapes

    centre, side = np.array([0.5, -0.2, 0.4]), 0.3
    p = cube_poses(centre, side)
    shapes = path_shapes(Cube(centre, side, p, np.zeros((5, 6)), np.eye(3)))
    np.testing.assert_allclose(shapes["line"], p[[1, 3]])  # P2 -> P4
    circle = shapes["circle"]
    np.testing.assert_allclose(circle[0], circle[-1])  # closed
    np.testing.assert_allclose(np.linalg.norm(circle - centre, axis=1), 0.5 * CIRCLE_DIAMETER * side)
    normal = np.cross(p[2] - p[1], p[4] - p[1])
    np.testing.assert_allclose((circle - centre) @ normal, 0.0, atol=1e-12)  # in the plane of the poses
    check_speed(0.5, 0.5)
    with pytest.raises(ValueError, match="give at most 0.548 m/s"):
        check_speed(0.6, 0.5)
