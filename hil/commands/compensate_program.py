"""`hil compensate MODEL PROGRAM.script -o OUT.script`: a URScript program whose poses the real robot reaches.

Every constant pose target of the program (movej, movel, movep, movec to pose literals, to variables assigned
from them, PolyScope's `get_inverse_kin(Waypoint_n_p, qnear=Waypoint_n_q)` and `pose_trans` of a constant
feature) is written as the joints the calibrated model puts the TCP there with; every other line is kept as
it is. Targets computed at run time are listed with their line numbers and left unchanged.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from hil.commands.errors import CliError
from hil.compensation.program import (
    CompensatedProgram,
    ProgramOptions,
    compensate_program,
    has_backlash,
    payload_unmodelled,
)
from hil.compensation.urscript import PoseTarget, ProgramError, ProgramMotions, read_program
from hil.model.calibrated_model import CalibratedModel

PROGRAM_SUFFIXES = (".script", ".urscript", ".urp")


def is_program(path: str) -> bool:
    """True for a URScript program (or a PolyScope .urp, which is refused with its remedy)."""
    return Path(path).suffix.lower() in PROGRAM_SUFFIXES


def run_program(args: argparse.Namespace, temperature_of: object) -> int:
    """Read, compensate and write the program; `temperature_of(model, frame)` gives the per-target temperatures
    as `hil compensate` takes them for a CSV (its --temperature-c, the thermal effect's reference)."""
    if Path(args.targets).suffix.lower() == ".urp":
        raise CliError(
            f"{args.targets} is a PolyScope .urp program (compressed XML), not URScript",
            "on the teach pendant save the program, then give the .script file PolyScope writes beside it",
        )
    if args.frame == "tracker" or args.step is not None or args.path:
        raise CliError(
            "a program's poses are in the robot's base frame and its order is its own: --frame tracker, "
            "--step and --path do not apply",
            "drop those options",
        )
    text = Path(args.targets).read_text(encoding="utf-8", errors="replace")
    try:
        model = CalibratedModel.load(args.model)
        motions = read_program(text, args.targets)
        temperature = _temperature(model, motions, args, temperature_of)
        options = ProgramOptions(args.smr, args.threshold_mm / 1000.0, args.max_iter, temperature)
        done = compensate_program(model, motions, options)
    except ProgramError as exc:
        raise CliError(
            str(exc), "fix the program or the model named above and run the command again"
        ) from exc
    except (ValueError, OSError, KeyError) as exc:
        raise CliError.from_text(str(exc)) from exc
    Path(args.output).write_text(done.text, encoding="utf-8")
    _print_summary(args, model, motions, done)
    return 0


def _temperature(
    model: CalibratedModel, motions: ProgramMotions, args: argparse.Namespace, temperature_of: object
) -> float | None:
    n = max(len(motions.pose_targets), 1)
    drivers = temperature_of(model, pd.DataFrame(index=range(n)), args.temperature_c, None)  # type: ignore[operator]
    temp = drivers.get("temperature_c")
    return None if temp is None else float(np.asarray(temp)[0])


def _print_summary(
    args: argparse.Namespace, model: CalibratedModel, motions: ProgramMotions, done: CompensatedProgram
) -> None:
    """What was rewritten on stdout; what was left alone, and why, on stderr."""
    if done.result is None:
        print(f"no constant pose target in {args.targets}: {args.output} is the program unchanged")
    else:
        s = done.result.summary()
        statuses = ", ".join(f"{k} {v}" for k, v in sorted(s["statuses"].items()))
        kept = sum(1 for _ in motions.motions) - len(done.targets)
        print(
            f"{len(done.targets)} pose targets compensated ({statuses}); predicted error mean "
            f"{s['mean_error_mm_before']:.4f} -> {s['mean_error_mm']:.4f} mm, max {s['max_error_mm']:.4f} mm; "
            f"{kept} joint targets kept; written to {args.output}"
        )
        failed = [t for t, ok in zip(done.targets, done.result.ok, strict=True) if not ok]
        for t in failed:
            print(
                f"warning: line {t.line}: {t.command} target not compensated below the threshold",
                file=sys.stderr,
            )
    first = motions.motions[0] if motions.motions else None
    if done.result is not None and isinstance(first, PoseTarget) and has_backlash(model):
        print(
            f"warning: line {first.line}: the program starts with a pose target, so the joints it starts from "
            "are unknown: its approach directions (the model's backlash) are taken as unknown (mid-gap) there; "
            "start the program with a taught joint position (movej([...])) to fix them",
            file=sys.stderr,
        )
    if payload_unmodelled(model, motions):
        print(
            "warning: the program sets a payload, and the model's gravity yield is not the torque form of the "
            "robot file's link masses: the payload's sag is not compensated; diagnose with a robot file that "
            "gives mass_kg",
            file=sys.stderr,
        )
    if motions.runtime:
        print(
            f"warning: {len(motions.runtime)} motion target(s) are computed at run time and were left unchanged "
            "(not compensated):",
            file=sys.stderr,
        )
        for r in motions.runtime:
            print(f"  line {r.line}: {r.command}({r.text}): {r.why}", file=sys.stderr)
    for line in motions.runtime_tcp_lines:
        print(f"warning: line {line}: set_tcp of a value known only at run time", file=sys.stderr)
