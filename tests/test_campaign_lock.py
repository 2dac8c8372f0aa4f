"""One driver per campaign: a second holder (in this process or another) is refused with who holds the
campaign; the lock goes with its holder, also when the holder's process dies without letting go."""

from __future__ import annotations

import subprocess
import sys

import pytest

from hil.data.campaign_lock import CampaignBusyError, CampaignLock, Holder, current_holder, lock_path


def test_a_second_holder_is_refused_with_who_holds_it(tmp_path):
    campaign = tmp_path / "c.sqlite"
    with CampaignLock(campaign, Holder.this_process("hil serve registration at http://127.0.0.1:8036/")):
        holder = current_holder(campaign)
        assert holder is not None and holder.what.startswith("hil serve registration")
        with pytest.raises(
            CampaignBusyError, match=r"c\.sqlite is driven by hil serve registration at .* \(process \d+ on "
        ):
            CampaignLock(campaign, Holder.this_process("hil run registration")).acquire()
    assert current_holder(campaign) is None and not lock_path(campaign).exists()
    with CampaignLock(campaign, Holder.this_process("hil run registration")):  # free again
        assert current_holder(campaign).what == "hil run registration"


def test_a_holder_that_dies_leaves_the_campaign_free(tmp_path):
    campaign = tmp_path / "c.sqlite"
    code = (
        "import os, sys; from hil.data.campaign_lock import CampaignLock, Holder; "
        f"CampaignLock({str(campaign)!r}, Holder.this_process('hil run x')).acquire(); os._exit(9)"
    )
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 9
    assert lock_path(campaign).exists()  # left behind by the dead holder, but nobody holds it
    assert current_holder(campaign) is None
    with CampaignLock(campaign, Holder.this_process("hil run y")):
        assert current_holder(campaign).what == "hil run y"
