"""The viewer page renders whatever URL fragment it is opened with (a real browser)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from test_viewer import browser, open_page  # noqa: F401  (the fixture and helper)
from tiny_cli import RULES, TINY

from amuled_ma.cli import main

#: Malformed percent escapes, a lone "%", a huge step, markup, many colons, a long name.
HOSTILE = [
    "%E0%A4%A",
    "%",
    "%zz:3",
    "finetune-amuled:99999999999999999999999",
    "finetune-amuled:-5",
    "<img src=x onerror=document.title='pwned'>",
    ":::",
    "%F0%9F%98" + "a" * 5000,
]


@pytest.fixture(scope="module")
def page(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("fragment") / "findmilk"
    common = ["findmilk", "--run-dir", str(run), *TINY, *RULES]
    assert main(["train", *common]) == 0
    assert main(["finetune", *common]) == 0
    out = run / "view.html"
    assert main(["view", str(run), "-o", str(out)]) == 0
    return out


@pytest.mark.parametrize("fragment", HOSTILE)
def test_any_fragment_still_renders_the_page(browser, page: Path, fragment: str) -> None:  # noqa: F811
    open_page(browser, page, fragment)  # fails unless the page's script finished
    section = None
    for _ in range(100):
        shown = browser.find_elements("css selector", "section[data-step]")
        section = next((s for s in shown if s.is_displayed()), None)
        if section is not None:
            break
        time.sleep(0.02)
    assert section is not None, f"no variant shown with #{fragment[:40]}"
    assert browser.title != "pwned"
    step = int(section.get_attribute("data-step"))
    assert step >= 0
