"""`hil campaign show/export` and campaign files as input of hil calibrate / diagnose / predict."""

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from calib_data import synthetic

from hil.cli import main
from hil.commands.inputs import read_measurements, read_training_and_validation
from hil.data.dataset import joint_columns, load_dataset
from hil.data.store import CampaignStore, MeasurementRecord


def store_dataset(store: CampaignStore, df: pd.DataFrame, step: str, t0: float, procedure="grid_sampling"):
    """Record the rows of a dataset frame as measurements of one step (what a session would do)."""
    q = df[joint_columns()].to_numpy()
    p_m = df[["x_mm", "y_mm", "z_mm"]].to_numpy() / 1000.0
    for i in range(len(df)):
        store.record_measurement(
            MeasurementRecord(
                procedure=procedure,
                step=step,
                point_id=f"{step}{i:03d}",
                q_target_rad=q[i],
                q_rad=q[i],
                T_base_flange=np.eye(4),
                p_tracker_m=p_m[i],
                spread_m=np.full(3, 5e-6),
                std_m=np.full(3, 7e-6),
                shots=5,
                rejected_shots=(),
                smr=1,
                location="nest1",
                temperature_c=21.5,
                pressure_hpa=1010.0,
                humidity_pct=35.0,
                timestamp_s=t0 + 3.0 * i,
            )
        )


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("campaign_cli")
    _, train, make = synthetic(n=90, seed=4)
    q_val, p_val = make(20)
    val = pd.DataFrame(
        np.column_stack([q_val, p_val * 1000]), columns=joint_columns() + ["x_mm", "y_mm", "z_mm"]
    )
    train.to_csv(d / "train.csv", index=False)
    with CampaignStore(d / "c.hilc") as store:
        store.add_snapshot({"robot": {"model": "ur5"}})  # an earlier session start
        store.add_snapshot(  # the shape hil.runner.session writes: cell.toml as read + what the instruments said
            {
                "source": "cell.toml",
                "cell": {
                    "robot": {"model": "ur10", "host": "10.0.0.2"},
                    "tracker": {"url": "socket://10.0.0.3:700"},
                    "tool": {"nests_flange_mm": [[0, 0, 100]]},
                },
                "software": {"python": "3.11.7", "hil": "0.1.0"},
                "station": {"robot_controller_version": "5.11.1", "tracker": {"serial": "AT960-123"}},
            }
        )
        store_dataset(store, train.head(3), "nest_check", 1.7e9 - 60, procedure="registration")
        store_dataset(store, train, "grid", 1.7e9)
        store_dataset(store, val, "validation", 1.7e9 + 1000)
        store.record_event(
            "fault", "protective stop", procedure="grid_sampling", step="grid", point_id="grid007"
        )
        store.record_event("retry", "moved again", procedure="grid_sampling", step="grid", point_id="grid007")
        store.record_event("fault", "target lost", procedure="grid_sampling", step="grid", point_id="grid050")
        store.finish_step("registration", "nest_check", {"ok": True})
        store.finish_step("grid_sampling", "grid", {"points": len(train)})
        store_dataset(store, train.head(2), "cycle", 1.7e9 + 2000, procedure="iso9283")  # no result yet
        store.log("WARNING", "SMR dirty?", "hil.runner.session")
    return d, train, val


def test_show_summarises_the_campaign(files, capsys):
    d, train, val = files
    assert main(["campaign", "show", str(d / "c.hilc")]) == 0
    out = capsys.readouterr().out
    assert f"{len(train) + len(val) + 5} measurements" in out
    # when the points were recorded, by this computer's clock (the instruments' clock said 2023)
    measured = next(line for line in out.splitlines() if "measured from" in line)
    assert "2023-" not in measured and "recorded by this computer's clock" in measured
    assert "station snapshots: 2" in out
    assert "robot     model=ur10 host=10.0.0.2 controller_version=5.11.1" in out
    assert "tracker   url=socket://10.0.0.3:700 serial=AT960-123" in out
    assert "cell      source=cell.toml (+tool)" in out and "hil=0.1.0" in out
    rows = {tuple(line.split()[:4]) for line in out.splitlines()}
    assert ("grid_sampling", "grid", str(len(train)), "finished") in rows
    # a step without a result of its own is done once its procedure recorded one after its last point
    assert ("grid_sampling", "validation", str(len(val)), "done:") in rows
    assert ("iso9283", "cycle", "2", "open") in rows
    assert ("registration", "nest_check", "3", "finished") in rows
    assert "events: fault 2, retry 1" in out
    assert "SMR dirty?" in out


def test_export_csv_and_parquet(files, capsys, tmp_path):
    d, train, val = files
    assert (
        main(["campaign", "export", str(d / "c.hilc"), "--csv", str(tmp_path / "grid.csv"), "--step", "grid"])
        == 0
    )
    assert f"{len(train)} measurements of grid_sampling/grid" in capsys.readouterr().out
    back = load_dataset(tmp_path / "grid.csv")
    np.testing.assert_allclose(back[["x_mm", "y_mm", "z_mm"]], train[["x_mm", "y_mm", "z_mm"]], rtol=1e-9)
    np.testing.assert_allclose(back["t_s"], 60.0 + 3.0 * np.arange(len(train)))  # since the registration
    assert main(["campaign", "export", str(d / "c.hilc"), "--parquet", str(tmp_path / "all.parquet")]) == 0
    pq = pd.read_parquet(tmp_path / "all.parquet")
    assert list(pq["step_id"].unique()) == ["grid", "validation"] and len(pq) == len(train) + len(val)
    assert (
        main(
            [
                "campaign",
                "export",
                str(d / "c.hilc"),
                "--procedure",
                "registration",
                "--csv",
                str(tmp_path / "reg.csv"),
            ]
        )
        == 0
    )
    assert len(load_dataset(tmp_path / "reg.csv")) == 3


def test_export_never_overwrites_a_file_silently(files, capsys, tmp_path):
    d, train, _ = files
    out = tmp_path / "grid.csv"
    out.write_text("keep me\n")
    assert main(["campaign", "export", str(d / "c.hilc"), "--csv", str(out), "--step", "grid"]) == 2
    err = capsys.readouterr().err
    assert out.read_text() == "keep me\n" and "exists" in err and "--force" in err
    assert (
        main(["campaign", "export", str(d / "c.hilc"), "--csv", str(out), "--step", "grid", "--force"]) == 0
    )
    assert len(load_dataset(out)) == len(train)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["show", "{d}/missing.hilc"], "campaign file not found"),
        (["show", "{d}/train.csv"], "give it to hil calibrate or hil diagnose as it is"),
        (["export", "{d}/missing.hilc", "--csv", "{t}/x.csv"], "campaign file not found"),
        (["export", "{d}/train.csv", "--csv", "{t}/x.csv"], "not a hil campaign file"),
        (["export", "{d}/c.hilc"], "exactly one of --csv OUT or --parquet OUT"),
        (["export", "{d}/c.hilc", "--csv", "{t}/x.csv", "--parquet", "{t}/x.parquet"], "exactly one of"),
        (["export", "{d}/c.hilc", "--csv", "{t}/no_such_dir/x.csv"], "output folder"),
        (["export", "{d}/c.hilc", "--csv", "{d}/c.hilc"], "overwrite the campaign file"),
        (
            ["export", "{d}/c.hilc", "--csv", "{t}/x.csv", "--procedure", "tool_fit"],
            "no measurements of tool_fit",
        ),
    ],
)
def test_cli_errors_are_refused_before_any_work(files, capsys, tmp_path, argv, message):
    d, _, _ = files
    before = (d / "c.hilc").read_bytes()
    argv = [a.format(d=d, t=tmp_path) for a in argv]
    assert main(["campaign", *argv]) == 2
    err = capsys.readouterr().err.strip()
    lines = err.splitlines()
    assert message in err and len(lines) == 2 and lines[0].startswith("hil campaign: ")
    assert lines[1].startswith("  what to do: ")
    assert list(tmp_path.iterdir()) == []  # nothing written
    assert (d / "c.hilc").read_bytes() == before


def test_campaign_files_as_analysis_input(files):
    d, train, val = files
    everything = read_measurements(d / "c.hilc")
    assert len(everything) == len(train) + len(val)  # grid_sampling, all of its steps
    fit, check = read_training_and_validation(d / "c.hilc")  # grid to fit, validation to check
    assert list(fit["step_id"].unique()) == ["grid"] and list(check["step_id"].unique()) == ["validation"]
    fit, check = read_training_and_validation(d / "c.hilc", d / "train.csv")
    assert len(fit) == len(train) and len(check) == len(train)
    fit, check = read_training_and_validation(d / "train.csv", d / "c.hilc")  # never the grid as validation
    assert len(fit) == len(train) and list(check["step_id"].unique()) == ["validation"]
    csv, none = read_training_and_validation(d / "train.csv")
    assert none is None and len(csv) == len(train)


def test_calibrate_and_predict_read_a_campaign_like_its_csv(files, capsys, tmp_path):
    d, train, _ = files
    assert main(["calibrate", str(d / "train.csv"), "-o", str(tmp_path / "csv.json")]) == 0
    from_csv = capsys.readouterr().out
    d2 = tmp_path / "grid_only.hilc"
    with CampaignStore(d2) as store:
        store_dataset(store, train, "grid", 1.7e9)
    assert main(["calibrate", str(d2), "-o", str(tmp_path / "hilc.json")]) == 0
    from_campaign = capsys.readouterr().out
    strip = [line for line in from_csv.splitlines() if "written to" not in line]
    assert strip == [
        line
        for line in from_campaign.splitlines()
        if "written to" not in line and "recorded in the" not in line
    ]
    assert f"model and summary recorded in the campaign {d2}" in from_campaign  # a CSV has nowhere to keep it
    with CampaignStore(d2) as store:
        (result,) = store.results()
    assert result.kind == "calibration" and result.model == json.loads((tmp_path / "hilc.json").read_text())
    assert result.summary["rms_after_m"] < result.summary["rms_before_m"]
    assert main(["predict", str(tmp_path / "hilc.json"), str(d2), "-o", str(tmp_path / "pred.csv")]) == 0
    pred = pd.read_csv(tmp_path / "pred.csv")
    assert list(pred["point_id"]) == [f"grid{i:03d}" for i in range(len(train))]
    err_mm = np.linalg.norm(
        pred[["x_mm", "y_mm", "z_mm"]].to_numpy() - train[["x_mm", "y_mm", "z_mm"]].to_numpy(), axis=1
    )
    assert np.sqrt(np.mean(err_mm**2)) < 0.1  # synthetic data: 15 um noise, geometric errors only


def test_show_to_a_reader_that_left_ends_quietly(files):
    d, _, _ = files
    process = subprocess.Popen(
        [sys.executable, "-m", "hil", "campaign", "show", str(d / "c.hilc")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    process.stdout.close()  # `| head -1` gone before the first write
    stderr = process.stderr.read().decode()
    assert process.wait(60) == 141 and stderr == "", stderr  # 128 + SIGPIPE, no traceback


def test_show_calls_a_step_finished_once_its_planned_points_are_recorded(files, tmp_path, capsys):
    d, train, _ = files
    path = tmp_path / "plan.hilc"
    with CampaignStore(path) as store:
        store.finish_step(
            "grid_sampling", "plan", {"point_ids": [f"grid{i:03d}" for i in range(5)] + ["validation000"]}
        )
        store_dataset(store, train.head(5), "grid", 1.7e9)
    assert main(["campaign", "show", str(path)]) == 0
    assert "grid                        5  open (5 of 6 planned points)" in capsys.readouterr().out
    with CampaignStore(path) as store:
        store_dataset(store, train.head(1), "validation", 1.7e9 + 100)
    assert main(["campaign", "show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "grid                        5  finished (plan complete)" in out
    assert "validation                  1  finished (plan complete)" in out


def test_diagnose_records_its_model_and_summary_in_the_campaign_it_read(files, capsys, tmp_path):
    d, _, _ = files
    campaign = tmp_path / "c.hilc"
    campaign.write_bytes((d / "c.hilc").read_bytes())  # the module's campaign stays as it was
    model = str(tmp_path / "m.json")
    assert (
        main(["diagnose", str(campaign), "--folds", "2", "--families", "gravity_compliance", "-o", model])
        == 0
    )
    assert f"model and summary recorded in the campaign {campaign}" in capsys.readouterr().out
    with CampaignStore(campaign) as store:
        (result,) = store.results()
    summary = result.summary
    assert result.kind == "diagnosis" and result.model == json.loads((tmp_path / "m.json").read_text())
    assert summary["rms_after_m"] < summary["rms_before_m"] and summary["validation_rms_m"] is not None
    assert summary["errors_on"] == "held-out folds of the training rows"
    assert summary["parameters"] and all(p["std"] > 0 for p in summary["parameters"])
    assert isinstance(summary["effects_found"], list) and isinstance(summary["effects_assumed"], list)
