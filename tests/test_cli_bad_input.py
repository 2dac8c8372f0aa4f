"""Every bad option value, path or file is refused before any work: `hil <command>: <what is wrong>` and
`  what to do: <remedy>` on stderr, exit 2.

Table-driven over calibrate, diagnose and predict, run in-process (hil.cli.main) so the table stays fast.
"""

import argparse
import json

import pandas as pd
import pytest
from calib_data import synthetic

from hil.analysis.calibration.solve import calibrate
from hil.cli import build_parser, main

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad_input")
    _, df, _ = synthetic(n=80, seed=3)
    df.to_csv(d / "data.csv", index=False)
    df.drop(columns=["x_mm", "y_mm", "z_mm"]).to_csv(d / "joints.csv", index=False)
    calibrate(df, "ur10").model.save(d / "model.json")
    text = (d / "model.json").read_text()
    (d / "truncated.json").write_text(text[: len(text) // 2])
    (d / "foreign.json").write_text(json.dumps({"effects_added": [], "stages": []}))
    (d / "binary.json").write_bytes(bytes(range(256)))
    df.drop(columns=["q3_rad"]).to_csv(d / "no_q3.csv", index=False)
    metres = df.copy()
    metres[["x_mm", "y_mm", "z_mm"]] /= 1000.0
    metres.to_csv(d / "metres.csv", index=False)
    three = pd.concat([df.head(20).assign(smr=k, x_mm=df.head(20)["x_mm"] + 50.0 * k) for k in (1, 2, 3)])
    three.to_csv(d / "three_smrs.csv", index=False)  # 60 rows, but only 20 poses
    return d


# (command line, text the one-line error must contain)
CASES = [
    ("calibrate missing.csv -o m.json", "file not found: missing.csv"),
    ("calibrate data.csv -o nowhere/m.json", "folder nowhere does not exist"),
    ("calibrate data.csv -o data.csv", "would be overwritten"),
    ("calibrate data.csv -o m.json --residuals m.json", "same file"),
    ("calibrate data.csv -o m.json --tool-mm 1,2", "--tool-mm"),
    ("calibrate data.csv -o m.json --tool-mm 5000,0,0", "more than 1 m"),
    ("calibrate data.csv -o m.json --tool-mm 1,nan,0", "--tool-mm"),
    ("calibrate data.csv -o m.json --solver newton", "--solver"),
    ("calibrate data.csv -o m.json --robot ur99", "--robot"),
    ("calibrate data.csv -o m.json --robot nowhere.toml", "robot file not found: nowhere.toml"),
    ("diagnose data.csv --json r.json --robot data.csv", "--robot"),
    ("calibrate no_q3.csv -o m.json", "q3_rad"),
    ("calibrate . -o m.json", "not a file"),
    ("calibrate metres.csv -o m.json", "look like metres"),
    ("calibrate data.csv -o m.json --robot irb2600", "beyond the irb2600 limits"),
    ("diagnose data.csv --json r.json --alpha -1", "--alpha"),
    ("diagnose data.csv --json r.json --alpha 0", "--alpha"),
    ("diagnose data.csv --json r.json --alpha nan", "--alpha"),
    ("diagnose data.csv --json r.json --alpha 2", "--alpha"),
    ("diagnose data.csv --json r.json --folds 1", "--folds"),
    ("diagnose three_smrs.csv --json r.json", "20 distinct poses (60 rows) are too few for 5-fold"),
    ("diagnose data.csv --json r.json --folds five", "--folds"),
    ("diagnose data.csv --json r.json --repeatability-mm -0.5", "--repeatability-mm"),
    ("diagnose data.csv --json r.json --tracker-mpe-um=0,0", "--tracker-mpe-um"),
    ("diagnose data.csv --json r.json --tracker-mpe-um=15,-6", "--tracker-mpe-um"),
    ("diagnose data.csv --json r.json --tracker-mpe-um=15,6,1", "--tracker-mpe-um"),
    ("calibrate data.csv -o m.json --orientation-convention zyz", "--orientation-convention"),
    ("calibrate data.csv -o m.json --probe-angle-noise-deg 0", "--probe-angle-noise-deg"),
    ("diagnose data.csv --json r.json --orientation-convention zyz", "--orientation-convention"),
    ("diagnose data.csv --json r.json --probe-angle-noise-deg -1", "--probe-angle-noise-deg"),
    ("diagnose data.csv --json r.json --families gravity,cyclic", "--families"),
    ("diagnose data.csv --json r.json --families ,", "--families"),
    ("diagnose data.csv --json nowhere/r.json", "folder nowhere does not exist"),
    ("diagnose data.csv --json r.json --html nowhere/r.html", "--html"),
    ("diagnose data.csv --json r.json -o nowhere/m.json", "--output"),
    ("diagnose data.csv --json data.csv", "would be overwritten"),
    ("diagnose data.csv --json r.json --validate missing.csv", "--validate: file not found"),
    ("diagnose data.csv --json r.json --validate joints.csv --html joints.csv", "would be overwritten"),
    ("diagnose data.csv --json r.json -o r.json", "same file"),
    ("diagnose data.csv --json r.json --folds 20", "too few"),
    ("diagnose data.csv --json r.json --validate-reregister base", "needs --validate"),
    (
        "diagnose data.csv --json r.json --validate data.csv --validate-reregister tool",
        "--validate-reregister",
    ),
    ("predict model.json joints.csv -o joints.csv", "would be overwritten"),
    ("predict model.json joints.csv -o model.json", "would be overwritten"),
    ("predict missing.json joints.csv -o p.csv", "file not found: missing.json"),
    ("predict truncated.json joints.csv -o p.csv", "truncated.json: truncated"),
    ("predict foreign.json joints.csv -o p.csv", "foreign.json: not a calibrated model"),
    ("predict binary.json joints.csv -o p.csv", "binary.json: not a model file"),
    ("predict model.json no_q3.csv -o p.csv", "q3_rad"),
    ("predict model.json joints.csv -o nowhere/p.csv", "folder nowhere does not exist"),
]


@pytest.mark.parametrize(("line", "expected"), CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_refused_before_the_work(files, monkeypatch, capsys, line, expected):
    monkeypatch.chdir(files)
    before = {p.name: p.stat().st_mtime_ns for p in files.iterdir()}
    try:
        code = main(line.split())
    except SystemExit as exc:  # argparse usage errors
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    lines = err.splitlines()
    assert len(lines) == 2 and lines[0].startswith("hil "), err  # the CLI convention: what is wrong ...
    assert lines[1].startswith("  what to do: ") and len(lines[1]) > 16, err  # ... and what to do
    assert expected in err
    assert {p.name: p.stat().st_mtime_ns for p in files.iterdir()} == before  # nothing written


def test_version_and_every_default_in_the_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("hil ")
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in ("calibrate", "diagnose", "predict"):
        p = sub.choices[name]
        text = "".join(p.format_help().split())  # help wraps long defaults anywhere
        for action in p._actions:
            if action.option_strings and action.default not in (None, argparse.SUPPRESS, False):
                assert f"(default:{action.default})" in text, (name, action.dest)


def test_model_rows_count_from_one(files):
    df = pd.read_csv(files / "data.csv")
    df.loc[9, "z_mm"] += 3.0  # data row 10
    result = calibrate(df, "ur10")
    assert 10 in result.model.info["outlier_rows"] and 10 in result.to_dict()["outlier_rows"]
