"""A campaign by its name, file or shared database: `open_campaign` and the contract both back-ends keep.

A name that is a postgresql:// URL opens the campaign in the shared PostgreSQL store (hil.data.pg_store);
anything else is a campaign file (hil.data.store), the default. Both keep `hil.data.store.Campaign`, the file
store's public interface, so the session, the engine and the analysis use either.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path

from hil.data.campaign_lock import CampaignLock, Holder
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


def campaign_lock(
    name: str | Path, holder: Holder, *, password_file: str | Path | None = None
) -> AbstractContextManager:
    """The lock that makes `holder` the campaign's one driver: an advisory lock in the shared store for a
    URL (hil.data.pg_campaign_lock), a lock file beside a campaign file (hil.data.campaign_lock)."""
    if is_campaign_url(name):
        from hil.data.pg_campaign_lock import PgCampaignLock

        return PgCampaignLock(str(name), holder, password_file)
    return CampaignLock(name, holder)
