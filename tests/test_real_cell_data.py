"""Data as a real cell gives it: spreadsheet exports, degree columns, duplicates, wrong units or robot."""

import warnings

import numpy as np
import pandas as pd
import pytest
from calib_data import synthetic

from hil.analysis.calibration.solve import calibrate
from hil.cli import main
from hil.data.dataset import DatasetError, load_dataset

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def campaign():
    _, df, _ = synthetic(n=80, seed=7)
    return df


def test_semicolons_and_decimal_commas_are_read(campaign, tmp_path):
    campaign.to_csv(tmp_path / "excel.csv", sep=";", decimal=",", index=False)
    assert "," in (tmp_path / "excel.csv").read_text().splitlines()[1]  # really decimal commas
    df = load_dataset(tmp_path / "excel.csv")
    np.testing.assert_allclose(df[campaign.columns].to_numpy(float), campaign.to_numpy(float), rtol=1e-12)


def test_decimal_commas_in_a_comma_separated_file_are_named(campaign, tmp_path):
    text = campaign.head(3).to_csv(index=False, float_format="%.4f")
    (tmp_path / "bad.csv").write_text(text.replace(".", ","))  # the header has no '.'; numbers do
    with pytest.raises(DatasetError, match="decimal commas"):
        load_dataset(tmp_path / "bad.csv")


def test_joint_columns_in_degrees_when_labelled_so(campaign, tmp_path):
    deg = campaign.copy()
    for i in range(1, 7):
        deg[f"q{i}_deg"] = np.rad2deg(deg.pop(f"q{i}_rad"))
    deg.to_csv(tmp_path / "deg.csv", index=False)
    df = load_dataset(tmp_path / "deg.csv")
    np.testing.assert_allclose(df["q2_rad"], campaign["q2_rad"], rtol=1e-12)


def test_positions_in_metres_are_named(campaign, tmp_path):
    m = campaign.copy()
    m[["x_mm", "y_mm", "z_mm"]] /= 1000.0
    m.to_csv(tmp_path / "m.csv", index=False)
    with pytest.raises(DatasetError, match="look like metres"):
        load_dataset(tmp_path / "m.csv")
    m.rename(columns={"x_mm": "x_m", "y_mm": "y_m", "z_mm": "z_m"}).to_csv(tmp_path / "m2.csv", index=False)
    np.testing.assert_allclose(load_dataset(tmp_path / "m2.csv")["x_mm"], campaign["x_mm"], rtol=1e-12)


def test_duplicate_rows_are_reported_and_counted_once(campaign, tmp_path):
    dup = pd.concat([campaign.iloc[:30], campaign.iloc[[3, 4]], campaign.iloc[30:]], ignore_index=True)
    dup.loc[60, "z_mm"] += 3.0  # a blunder in data row 61 of the file
    dup.to_csv(tmp_path / "dup.csv", index=False)
    with pytest.warns(UserWarning, match=r"2 duplicated row\(s\) \(data rows 31, 32\)"):
        df = load_dataset(tmp_path / "dup.csv")
    assert len(df) == len(campaign) and df.attrs["duplicate_rows"] == [31, 32]
    result = calibrate(df, "ur10")
    assert result.outlier_rows == [61]  # numbered as in the file, duplicates included


def test_wrong_robot_model_is_named(campaign):
    result = calibrate(campaign, "ur5")  # UR10 data
    assert any("a2" in n and "ur5 nominal" in n for n in result.notes)
    assert not calibrate(campaign, "ur10").notes


def test_joints_beyond_the_robots_limits_are_named(campaign):
    deg = campaign.copy()
    deg["q3_rad"] = 2.5  # beyond the IRB 2600's joint 3 limit (75 deg)
    with pytest.raises(ValueError, match="joint 3 in data row 1 is 2.500 rad, beyond the irb2600 limits"):
        calibrate(deg, "irb2600")


def test_predict_warns_for_a_model_of_another_robot(campaign, tmp_path, capsys):
    calibrate(campaign, "ur5").model.save(tmp_path / "ur5.json")
    _, other, _ = synthetic(n=40, seed=8)
    other["q1_rad"] += 2.0  # also outside the joint-1 range the model was trained on
    other.to_csv(tmp_path / "ur10.csv", index=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(
            ["predict", str(tmp_path / "ur5.json"), str(tmp_path / "ur10.csv"), "-o", str(tmp_path / "p.csv")]
        )
    err = capsys.readouterr().err
    assert code == 0
    assert "mm RMS off the positions in the file" in err and "model is for ur5" in err
    assert "joint(s) 1" in err and "leave the range the model was trained on" in err


def test_a_model_fitted_with_the_wrong_robot_is_refused_unless_forced(campaign, tmp_path, capsys):
    campaign.to_csv(tmp_path / "ur10.csv", index=False)
    model = tmp_path / "ur5.json"
    code = main(["calibrate", str(tmp_path / "ur10.csv"), "--robot", "ur5", "-o", str(model)])
    err = capsys.readouterr().err
    assert code == 2 and not model.exists()
    assert (
        "error: implausible: a2 moved" in err and "no model written" in err and "--accept-implausible" in err
    )
    argv = [
        "calibrate",
        str(tmp_path / "ur10.csv"),
        "--robot",
        "ur5",
        "-o",
        str(model),
        "--accept-implausible",
    ]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 0 and model.exists() and "warning: implausible: a2 moved" in err
    # the model written is kept: the same command again is refused before any work, --force overwrites
    written = model.read_bytes()
    assert main(argv) == 2 and model.read_bytes() == written
    assert f"--output: {model} exists" in capsys.readouterr().err
    assert main([*argv, "--force"]) == 0


def test_calibrate_prints_changes_in_mm_and_degrees(campaign, tmp_path, capsys):
    campaign.to_csv(tmp_path / "ur10.csv", index=False)
    assert main(["calibrate", str(tmp_path / "ur10.csv"), "-o", str(tmp_path / "m.json")]) == 0
    rows = {
        line.split()[0]: line.split()
        for line in capsys.readouterr().out.splitlines()
        if line[:2] in ("a2", "al")
    }
    table = {r["name"]: r for r in calibrate(campaign, "ur10").parameter_table()}
    assert rows["a2"][-1] == "mm" and float(rows["a2"][1]) == pytest.approx(
        table["a2"]["delta"] * 1e3, abs=2e-5
    )
    assert rows["alpha1"][-1] == "deg"
    assert float(rows["alpha1"][1]) == pytest.approx(np.rad2deg(table["alpha1"]["delta"]), abs=2e-5)


def test_help_shows_no_default_for_required_or_empty_options(capsys):
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: None)" not in text and "(default: False)" not in text
    assert "(default: ridge)" in text


def test_cli_warnings_are_one_line_without_python_internals(campaign, tmp_path, capsys):
    dup = pd.concat([campaign.iloc[:30], campaign.iloc[[3, 4]], campaign.iloc[30:]], ignore_index=True)
    dup.to_csv(tmp_path / "dup.csv", index=False)
    assert main(["calibrate", str(tmp_path / "dup.csv"), "-o", str(tmp_path / "m.json")]) == 0
    err = capsys.readouterr().err
    assert "warning: " in err and "2 duplicated row(s)" in err
    assert "UserWarning" not in err and "dataset.py" not in err and "warnings.warn" not in err


def test_diagnose_needs_no_json_and_refuses_the_wrong_robot_unless_forced(campaign, tmp_path, capsys):
    campaign.to_csv(tmp_path / "ur10.csv", index=False)
    assert (
        main(["diagnose", str(tmp_path / "ur10.csv"), "--folds", "2", "--families", "gravity_compliance"])
        == 0
    )  # README's form
    capsys.readouterr()
    model = tmp_path / "ur5.json"
    argv = [
        "diagnose",
        str(tmp_path / "ur10.csv"),
        "--robot",
        "ur5",
        "--folds",
        "2",
        "--families",
        "gravity_compliance",
        "-o",
        str(model),
    ]
    assert main(argv) == 2 and not model.exists()
    err = capsys.readouterr().err
    assert (
        "error: implausible: a2 moved" in err and "no model written" in err and "--accept-implausible" in err
    )
    assert main([*argv, "--accept-implausible"]) == 0 and model.exists()
    assert "warning: implausible: a2 moved" in capsys.readouterr().err
