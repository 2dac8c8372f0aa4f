"""Honest numbers: parameter uncertainties another campaign agrees with, outlier regions, map spacing."""

import numpy as np
import pytest

from hil.analysis.calibration.solve import calibrate, outlier_regions
from hil.model.grid_frame import location_spacing
from hil.model.residual_maps import make_map

pytestmark = pytest.mark.timeout(120)


def test_parameter_uncertainties_agree_with_another_campaign():
    # Two campaigns of one cell (gravity compliance the geometric model lacks): a grid and random poses.
    from sim_campaigns import grid_joints, held_out_joints

    from fakes.campaign import simulate_campaign
    from fakes.cell import SimCellConfig, SimulatedCell

    cell = SimulatedCell(SimCellConfig(robot="ur10", seed=2))
    a = calibrate(simulate_campaign(cell, grid_joints(cell, step_m=0.12, seed=2)), "ur10")
    b = calibrate(simulate_campaign(cell, held_out_joints(cell, 200, seed=7)), "ur10")
    ta, tb = ({r["name"]: r for r in res.parameter_table()} for res in (a, b))
    geo = [n for n in ta if n in tb and n in a.model.nominal.param_names]
    assert len(geo) > 15
    for t in (ta, tb):
        assert all(t[n]["std"] >= t[n]["std_ls"] > 0 for n in geo)
    z = [abs(ta[n]["value"] - tb[n]["value"]) / np.hypot(ta[n]["std"], tb[n]["std"]) for n in geo]
    assert max(z) < 3.0  # the campaigns differ by what the stated uncertainties allow
    assert any("confounded" in note for note in a.notes)  # the wrist pairs this grid cannot separate
    # the verdict's cautions carry each confounded pair as a field (the diagnosis drops a pair it decides)
    from hil.analysis.diagnosis.pipeline import calibration_notes

    notes = calibration_notes(a)
    assert [n.text for n in notes] == a.notes
    assert [n.pair for n in notes if n.pair] == [(x, y) for x, y, _ in a.confounded] and a.confounded
    assert all(n.pair is None for n in notes if not n.text.startswith("confounded"))


def test_outliers_that_cluster_are_a_region_not_blunders():
    from calib_data import synthetic

    _, df, _ = synthetic(n=300, seed=4)
    p = df[["x_mm", "y_mm", "z_mm"]].to_numpy()
    corner = np.argsort(np.linalg.norm(p - p[0], axis=1))[:12]  # the 12 points nearest one spot
    df.loc[corner, "z_mm"] += 0.8  # e.g. the tracker's beam grazing an obstacle there
    df.loc[250, "x_mm"] += 3.0  # and one real blunder elsewhere
    result = calibrate(df, "ur10")
    assert result.outliers[250]
    regions = result.to_dict()["outlier_regions"]
    assert len(regions) == 1 and regions[0]["count"] >= 6
    assert set(regions[0]["rows"]) <= {int(i) + 1 for i in corner}  # data rows, counted from 1
    assert 251 not in regions[0]["rows"]
    assert any(n.startswith("outlier region") for n in result.notes)
    rng = np.random.default_rng(0)
    scattered = np.zeros(300, bool)
    scattered[rng.choice(300, 8, replace=False)] = True
    assert outlier_regions(p / 1000.0, scattered) == []


def test_repeated_orientations_at_a_node_do_not_shrink_the_map_spacing():
    nodes = np.stack(np.meshgrid(*[np.arange(5) * 0.1] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(1)
    points = np.repeat(nodes, 4, axis=0) + rng.normal(0, 0.5e-3, (4 * len(nodes), 3))  # 4 orientations
    assert location_spacing(points) == pytest.approx(0.1, rel=0.05)
    m = make_map("svr")
    m._remember_volume(points)
    midpoints = nodes[:-1] + 0.05  # interleaved validation points between the nodes
    midpoints = midpoints[np.all(midpoints < 0.4, axis=1)]
    assert not m.outside(midpoints).any()
    assert m.outside(np.array([[0.2, 0.2, 0.75]])).all()  # beyond the grid


@pytest.mark.parametrize("solver", ["ridge", "lm"])
def test_a_big_campaign_converges_on_a_subset_and_finishes_on_every_row(monkeypatch, solver):
    from calib_data import synthetic

    import hil.analysis.calibration.solve as cal

    _, df, _ = synthetic(n=900, seed=6)
    df.loc[[17, 400, 777], "y_mm"] += 2.5  # blunders, one outside any subset of 300 is likely
    direct = calibrate(df, "ur10", solver)
    monkeypatch.setattr(cal, "CONVERGE_ROWS", 300)
    staged = calibrate(df, "ur10", solver)
    assert staged.outlier_rows == direct.outlier_rows and {18, 401, 778} <= set(direct.outlier_rows)
    a, b = ({r["name"]: r for r in res.parameter_table()} for res in (direct, staged))
    for name, row in a.items():
        assert abs(row["value"] - b[name]["value"]) < 0.05 * row["std_ls"], name
