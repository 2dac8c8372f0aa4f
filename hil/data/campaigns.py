"""A campaign by its name, file or shared database: `open_campaign` and the contract both back-ends keep.

A name that is a postgresql:// URL opens the campaign in the shared PostgreSQL store (hil.data.pg_store);
anything else is a campaign file (hil.data.store), the default. Both keep `hil.data.store.Campaign`, the file
store's public interface, so the session, the engine and the analysis use either.
"""

from __future__ import annotations

from pathlib import Path

from hil.data.pg_url import is_campaign_url
from hil.data.store import Campaign, CampaignStore, is_campaign_file


def open_campaign(
    name: str | Path, *, create: bool = True, password_file: str | Path | None = None
) -> CampaignStore | Campaign:
    """The campaign `name` names: a postgresql:// URL in the shared store (its password from PGPASSWORD or
    `password_file`), else a campaign file. `create`: start it when it does not exist."""
    if is_campaign_url(name):
        from hil.data.pg_store import PgCampaignStore

        return PgCampaignStore(str(name), create=create, password_file=password_file)
    return CampaignStore(name, create=create)


def is_campaign(name: str | Path) -> bool:
    """True when `name` is a campaign URL or a campaign file (a dataset CSV is neither)."""
    return is_campaign_url(name) or is_campaign_file(name)
