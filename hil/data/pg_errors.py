"""The shared store's failures, apart from its driver: the command line catches them without loading psycopg."""

from __future__ import annotations

from hil.data.store import CampaignError
from hil.errors import ActionableError


class CampaignStoreLost(ActionableError, CampaignError):  # noqa: N818 - reads as what happened
    """The campaign database cannot be reached (never reached, or lost mid-run). Everything committed before is
    kept; the same command resumes where it stopped once the server answers again."""

    remedy = "start the database server or restore the network, then run the same command again to resume"


class CampaignLoginRefused(CampaignError):  # noqa: N818 - reads as what happened
    """The database refused the login (a wrong or missing password, an unknown user)."""
