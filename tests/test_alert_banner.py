"""The operator page's alert banner (uwcam/web/alerts.js) in Debian's Chromium: a daemon whose disk
rule holds from the start and whose simulated seabed is brought close and taken away again; the
banner shows what GET /api/v1/alerts holds, most severe first, and nothing once all are cleared."""

from __future__ import annotations

import pytest

from tests.served import Server
from tests.test_api import small_config
from tests.test_page import browser, open_page  # noqa: F401 (the module's Chromium fixture)
from tests.waiting import wait_for
from uwcam.config import AlertsConfig, RangeAlertConfig

pytestmark = pytest.mark.browser


def banner(page) -> list[str]:
    """The banner's alert lines as shown (none while it is hidden)."""
    box = page.locator("#alert-banner")
    if not box.is_visible():
        return []
    return [t.strip() for t in box.locator(".alert").all_inner_texts()]


@pytest.mark.slow
def test_the_banner_shows_raised_alerts_most_severe_first_and_goes_when_they_clear(browser):  # noqa: F811
    config = small_config().model_copy(update={"alerts": AlertsConfig(
        range=RangeAlertConfig(below_m=1.5, for_s=0.5), disk_free_below_percent=100.0, clear_s=0.5)})
    with Server(config) as s:
        assert wait_for(lambda: s.daemon.pipeline.processed > 3, 60.0)
        page = open_page(browser, s.url + "/", s.url)
        try:
            assert wait_for(lambda: any("recording disk" in line for line in banner(page)), 30.0, 0.2), banner(page)
            (line,) = banner(page)
            assert line.startswith("warning: recording disk ") and "% free (since " in line

            s.daemon.rig.place(1.0)
            assert wait_for(lambda: len(banner(page)) == 2, 30.0, 0.2), banner(page)
            lines = banner(page)
            active = {a["key"]: a for a in s.http.get("/api/v1/alerts").json()["active"]}
            assert lines[0].startswith(f"critical: {active['range']['message']}") and lines[1].startswith("warning: ")
            assert page.locator('#alert-banner .alert[data-key="range"]').evaluate(
                "e => getComputedStyle(e).backgroundColor") != page.locator(
                '#alert-banner .alert[data-key="disk"]').evaluate("e => getComputedStyle(e).backgroundColor")

            s.daemon.rig.place(2.0)
            assert wait_for(lambda: len(banner(page)) == 1, 30.0, 0.2), banner(page)
            assert banner(page)[0].startswith("warning: recording disk")

            # The daemon no longer holds the disk alert (its rule switched off): the banner goes.
            s.daemon.alerts.config = s.daemon.alerts.config.model_copy(update={"disk_free_below_percent": 1e-9})
            assert wait_for(lambda: not page.locator("#alert-banner").is_visible(), 30.0, 0.2), banner(page)
            assert page.errors == []
        finally:
            page.close()
