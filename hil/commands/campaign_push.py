"""`hil campaign push FILE URL`: copy a campaign file into the shared store, by its UUID.

A cell without a network keeps its campaign in a file and joins the plant's history later: the file's rows go
into the database under the file's UUID, in one transaction; pushing again adds only what the file recorded
since (nothing, when it has not grown). The label is the URL's ?campaign=NAME, else the file's name.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from hil.commands.errors import CliError
from hil.data.pg_url import CampaignURLError, is_campaign_url, with_default_campaign
from hil.data.store import CampaignError, is_campaign_file


def add_push_parser(sub: argparse._SubParsersAction) -> None:
    push = sub.add_parser(
        "push",
        help="copy a campaign file into the shared PostgreSQL store (by its UUID; pushing again adds nothing)",
    )
    push.add_argument("file", help="campaign file")
    push.add_argument(
        "url", help="postgresql://USER@HOST/DATABASE[?campaign=LABEL] (default label: the file's name)"
    )
    push.add_argument(
        "--password-file", default=None, help="file holding the database password (default: PGPASSWORD)"
    )
    push.set_defaults(func=run_push)


def run_push(args: argparse.Namespace) -> int:
    if not is_campaign_file(args.file):
        raise CliError.from_text(
            f"{args.file} is not a hil campaign file; give the campaign file a session wrote"
        )
    if not is_campaign_url(args.url):
        raise CliError.from_text(f"{args.url} is not a postgresql:// URL; give the shared store's database")
    from hil.data.campaign_copy import read_campaign_copy
    from hil.data.pg_errors import CampaignStoreLost
    from hil.data.pg_store import PgCampaignStore

    try:
        url = with_default_campaign(args.url, Path(args.file).stem)
        copy = read_campaign_copy(args.file)
        with PgCampaignStore(
            url, identity=(copy.uuid, copy.created_s), password_file=args.password_file
        ) as store:
            added = store.receive(copy)
            shown = store.path
    except CampaignStoreLost as exc:
        raise CliError(exc.message, exc.remedy) from exc
    except (CampaignError, CampaignURLError) as exc:
        raise CliError.from_text(str(exc)) from exc
    total = sum(added.values())
    if total == 0:
        print(f"{args.file}: campaign {copy.uuid} is already in {shown}; nothing new to add")
    else:
        counts = ", ".join(f"{n} {table}" for table, n in added.items() if n)
        print(f"{args.file} -> {shown} (campaign {copy.uuid}): added {counts}")
    return 0
