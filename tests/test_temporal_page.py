"""The page's temporal fusion switch and how many frames the range is fused over, in Chromium.

The expected figure comes from the daemon's own published frames (frames per pixel), read from
Python, and from the configuration the switch must leave behind.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from tests.served import Server
from tests.test_api import small_config
from tests.test_page import browser, displayed, open_page  # noqa: F401 (the browser fixture)
from tests.waiting import wait_for

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def server():
    # A still scene (seabed with the patch, the vehicle holding station): every pixel fuses to the cap.
    with Server(small_config()) as s:
        assert wait_for(lambda: s.daemon.pipeline.latest is not None, 60.0)
        yield s


def test_the_switch_fuses_frames_and_the_range_view_says_over_how_many(server, browser):  # noqa: F811
    page = open_page(browser, server.url + "/", server.url)
    pipeline = server.daemon.pipeline
    try:
        assert wait_for(lambda: displayed(page) > 0 and page.locator("#temporal-on").is_enabled(), 20.0)
        assert not page.locator("#temporal-on").is_checked()
        assert page.inner_text("#range-label") == "range"
        page.click("#temporal-on")
        assert wait_for(lambda: pipeline.processing.temporal is not None, 10.0)
        assert pipeline.processing.temporal.max_frames == 32
        # The label follows the status: the median over the pixels with a range, from the frames published.
        assert wait_for(lambda: page.inner_text("#range-label") == "range · fused over 32 frames", 30.0, 0.2), \
            page.inner_text("#range-label")
        frames = pipeline.latest.frames
        assert np.median(frames[frames > 0]) == 32
        figures = page.inner_text("#figures")
        assert re.search(r"fusion\s+32 frames per pixel \(median, at most 32\)", figures), figures
        page.check("#show-sigma")
        assert wait_for(lambda: page.inner_text("#range-label") == "σ of range · fused over 32 frames", 10.0, 0.2)
        page.uncheck("#show-sigma")
        page.click("#temporal-on")
        assert wait_for(lambda: pipeline.processing.temporal is None, 10.0)
        assert wait_for(lambda: page.inner_text("#range-label") == "range", 10.0, 0.2)
        assert "fusion" not in page.inner_text("#figures")
        assert page.errors == [] and page.outside == []
    finally:
        page.close()
        server.http.patch("/api/v1/config", json={"temporal": None})
