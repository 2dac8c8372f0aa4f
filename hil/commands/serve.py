"""`hil serve --cell cell.toml [--campaigns DIR] [--host 127.0.0.1] [--port 8036] [--token T]`: the operator
console, a web page on the engine `hil run` uses.

Loopback by default. Any other address needs a token (--token, or [console] token in the cell config): the
console refuses every request without it, and without one the command refuses to start before it binds.
"""

from __future__ import annotations

import argparse
import ipaddress
from pathlib import Path

from hil.commands.errors import CliError

DEFAULT_PORT = 8036


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="the operator console: start procedures, watch them live, answer prompts, find every campaign",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--cell", required=True, help="cell configuration (TOML)")
    parser.add_argument(
        "--campaigns", default=".", help="folder of the campaign files (default: the current folder)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1, loopback)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT})")
    parser.add_argument(
        "--token", default=None, help="token every request must carry (required off loopback)"
    )
    parser.set_defaults(func=run)


def is_loopback(host: str) -> bool:
    """True for a loopback address (127.0.0.0/8, ::1) or the name localhost."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def run(args: argparse.Namespace) -> int:
    from hil.runner.cell_config import CellConfigError, load_cell_config

    try:
        config = load_cell_config(args.cell)
    except CellConfigError as exc:
        raise CliError(str(exc), "fix the keys named above (hil cell check shows the same list)") from exc
    token = args.token or config.console_token
    if not is_loopback(args.host) and not token:
        raise CliError(
            f"--host {args.host} is not a loopback address and the console has no token",
            "give --token (or [console] token in the cell config); nothing was bound",
        )
    folder = Path(args.campaigns)
    if not folder.is_dir():
        raise CliError(f"--campaigns {folder}: no such folder", "create it or give another one")
    if not 0 <= args.port <= 65535:
        raise CliError(f"--port {args.port} is not a port", "give 1..65535 (0: any free port)")

    import uvicorn

    from hil.console.app import LOOPBACK_NAMES, ConsoleOptions, build_app
    from hil.console.station import Station

    url = f"http://{args.host}:{args.port}/"
    station = Station(config, folder.resolve(), address=url)
    hosts = ("*",) if token else tuple(dict.fromkeys((*LOOPBACK_NAMES, args.host)))
    app = build_app(station, ConsoleOptions(token=token, allowed_hosts=hosts))
    print(f"hil console for {config.source} at {url}" + (" (token required)" if token else ""), flush=True)
    uvicorn.Server(
        uvicorn.Config(app, host=args.host, port=args.port, log_level="warning", timeout_graceful_shutdown=2)
    ).run()
    return 0
