"""`hil tracker`: talk to a laser tracker from the shop floor (state, aim, measure), JSON out."""

from __future__ import annotations

import argparse
import json

from hil.commands.errors import CliError
from hil.commands.help_format import DefaultsHelpFormatter


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "tracker",
        help="laser tracker: state, aim and measure (Leica emScon)",
        description="Connect to an emScon tracker through a pyserial URL (socket://HOST:700, /dev/ttyUSB0, "
        "rfc2217://...), optionally aim at a point and lock the SMR there, measure, print JSON (SI units).",
        formatter_class=DefaultsHelpFormatter,
    )
    parser.add_argument(
        "--url", required=True, help="pyserial URL of the tracker, e.g. socket://192.168.0.1:700"
    )
    parser.add_argument(
        "--shots", type=int, default=0, help="stationary measurements to average (0: measure nothing)"
    )
    parser.add_argument("--meas-time", type=float, default=1.0, help="seconds per stationary measurement")
    parser.add_argument(
        "--aim", type=float, nargs=3, metavar=("X_M", "Y_M", "Z_M"), help="aim here first (tracker frame, m)"
    )
    parser.add_argument(
        "--find", type=float, metavar="DISTANCE_M", help="search for a reflector at this range"
    )
    parser.add_argument("--reflector", help="reflector name to select (default: keep the tracker's)")
    parser.add_argument("--wire-units", choices=["m", "mm"], default="m", help="length unit on the wire")
    parser.add_argument("--wire-angles", choices=["rad", "deg"], default="rad", help="angle unit on the wire")
    parser.add_argument(
        "--coordinates",
        choices=["cartesian", "spherical"],
        default="cartesian",
        help="coordinate system on the wire",
    )
    parser.add_argument(
        "--timeout", type=float, default=10.0, help="seconds to wait for each command's answer"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from contextlib import closing

    from hil.instruments.plugins import PluginError, tracker_driver
    from hil.instruments.tracker import TrackerError

    if args.shots < 0:
        raise CliError(f"--shots {args.shots} is negative", "give 0 (no measurement) or more shots")
    if not 0 < args.meas_time <= 3600:
        raise CliError(
            f"--meas-time {args.meas_time:g} s is outside (0, 3600] s", "give a time in seconds, e.g. 1"
        )
    try:
        emscon = tracker_driver("emscon")
    except PluginError as exc:
        raise CliError(exc.message, exc.remedy) from exc
    settings = {
        "url": args.url,
        "meas_time_s": args.meas_time,
        "reflector": args.reflector,
        "length_unit": args.wire_units,
        "angle_unit": args.wire_angles,
        "coordinate_system": args.coordinates,
        "command_timeout_s": args.timeout,
    }
    out: dict = {}
    try:
        with closing(emscon.open(settings)) as tracker:
            if args.aim:
                tracker.point_at(args.aim)
            if args.find:
                tracker.find_target(args.find)
            state = tracker.state()
            out["state"] = {
                "initialized": state.initialized,
                "target_locked": state.target_locked,
                "reflector_id": state.reflector_id,
                **state.details,
            }
            if args.shots:
                out["measurement"] = tracker.measure(args.shots).to_dict()
    except TrackerError as exc:
        out["error"] = {"type": type(exc).__name__, "message": str(exc)}
    print(json.dumps(out, indent=2))
    return 1 if "error" in out else 0
