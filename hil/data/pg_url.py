"""A campaign in the shared PostgreSQL store, named by a URL: postgresql://USER@HOST[:PORT]/DATABASE?campaign=NAME.

The URL carries no password: a password in it is refused, since a campaign name is shown in reports, logs and
the inputs table and kept in shell histories. The password comes from the environment (PGPASSWORD, or libpq's
PGPASSFILE) or from a password file the cell config names (store.password_file).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

SCHEMES = ("postgresql", "postgres")


class CampaignURLError(ValueError):
    """A campaign URL that cannot be used; the message says what to write instead."""


def is_campaign_url(name: str | Path) -> bool:
    """True when `name` names a campaign in a PostgreSQL database rather than a file."""
    return isinstance(name, str) and name.split("://", 1)[0].lower() in SCHEMES and "://" in name


@dataclass(frozen=True)
class CampaignURL:
    """Where a shared campaign lives: `conninfo` for the driver (no campaign, no password), `campaign` (its
    label, or its UUID), `shown` (the URL as reports and messages print it)."""

    conninfo: str
    campaign: str
    shown: str
    password_file: Path | None = None

    @classmethod
    def parse(cls, url: str, password_file: str | Path | None = None) -> CampaignURL:
        parts = urlsplit(url)
        if parts.password is not None:
            raise CampaignURLError(
                f"{redacted(url)}: a password in a campaign URL is refused (it would be shown in reports, "
                "logs and shell histories); set PGPASSWORD, or name a password file (store.password_file in "
                "the cell config, or PGPASSFILE)"
            )
        query = parse_qsl(parts.query, keep_blank_values=True)
        names = [v for k, v in query if k == "campaign"]
        if len(names) != 1 or not names[0].strip():
            raise CampaignURLError(
                f"{url}: name the campaign in the URL, e.g. {urlunsplit(parts._replace(query='campaign=cell7-2026-11'))}"
            )
        if not parts.hostname or not parts.path.strip("/"):
            raise CampaignURLError(
                f"{url}: give the server and the database, postgresql://USER@HOST/DATABASE"
            )
        rest = urlencode([(k, v) for k, v in query if k != "campaign"])
        conninfo = urlunsplit(parts._replace(query=rest, fragment=""))
        return cls(conninfo, names[0].strip(), url, None if password_file is None else Path(password_file))

    def with_campaign(self, campaign: str) -> CampaignURL:
        """The same database, another campaign."""
        parts = urlsplit(self.conninfo)
        query = urlencode([*parse_qsl(parts.query), ("campaign", campaign)])
        return CampaignURL(
            self.conninfo, campaign, urlunsplit(parts._replace(query=query)), self.password_file
        )

    @property
    def database(self) -> str:
        """USER@HOST:PORT/DATABASE, for messages about the server rather than one campaign."""
        parts = urlsplit(self.conninfo)
        return f"{parts.netloc}{parts.path}"


def with_default_campaign(url: str, label: str) -> str:
    """`url` with ?campaign=`label` added when it names no campaign."""
    parts = urlsplit(url)
    if any(k == "campaign" for k, _ in parse_qsl(parts.query)):
        return url
    return urlunsplit(parts._replace(query=urlencode([*parse_qsl(parts.query), ("campaign", label)])))


def redacted(url: str) -> str:
    """`url` with any password replaced by ***."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.netloc.rsplit("@", 1)[1]
    return urlunsplit(parts._replace(netloc=f"{parts.username or ''}:***@{host}"))
