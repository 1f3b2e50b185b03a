"""The study's pages in Debian's headless chromium, through the real server.

Two participants choose and rate every pair of a study on the jsPsych page; one tampers with a
rating in the page (a radio button's value set to 9): the server refuses it and keeps the
refusal, the page says so, and after a reload the item comes back and is answered. An expert
answers every state of an expert study: the page shows each member's stated reason where
the fixture recording kept one and "no stated reason recorded" elsewhere, and asks how clear
the reasons are only where there is one. What the pages sent is what SQLite holds.
Screenshots of both pages go to ``$AMULED_ARTIFACTS`` (else the test's folder).
"""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import pytest
from study_fixtures import (
    agree_to_consent,
    artifacts,
    browser,
    free_port,
    full_page_png,
    reasoned_run,
    start_server,
    wait_sent,
    wait_state,
)

from amuled_ma.study.answers import read_refusals
from amuled_ma.study.build import build_study
from amuled_ma.study.model import read_study

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]
FRAMEWORKS = ["consequentialist", "deontological", "virtue", "care", "social_justice", "none"]


@pytest.fixture(scope="module")
def studies(tmp_path_factory, recordings_dir) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("browser")
    run = reasoned_run(folder, recordings_dir)
    build_study([run], ["amuled", "base"], folder / "pairs", items=4, seed=5, attention=1)
    build_study([run], ["amuled", "base"], folder / "expert", items=4, seed=3, mode="expert")
    return folder / "pairs", folder / "expert"


def current_item(driver, done: set[str]) -> str | None:
    """The item the page shows once it has moved past those answered (None: finished)."""
    for _ in range(400):
        state = wait_state(driver)
        if state == "done":
            return None
        if state == "consent":
            agree_to_consent(driver)
            continue
        item = driver.execute_script("return document.body.dataset.item")
        if item not in done:
            return item
        time.sleep(0.025)
    raise AssertionError("the page never showed the next item")


def rate_pairs(driver, base: str, url_id: str, expected: dict, tamper: str | None, shots: list):
    """Answer every pair on the page; returns {item: (choice, rating A, rating B)} accepted."""
    from selenium.webdriver.common.by import By

    sent: dict[str, tuple[str, int, int]] = {}
    driver.get(f"{base}/?PROLIFIC_PID={url_id}")
    done: set[str] = set()
    while (item := current_item(driver, done)) is not None:
        labels = [e.text for e in driver.find_elements(By.CSS_SELECTOR, ".option span")]
        assert [label[:2] for label in labels] == ["A:", "B:"]
        assert len(driver.find_elements(By.CSS_SELECTOR, "table.scale input")) == 2 * 7
        number = int(item[1:])
        choice = expected[item] or "AB"[number % 2]
        ratings = (1 + number % 7, 7 - number % 5)
        driver.find_element(By.CSS_SELECTOR, f'input[name="choice"][value="{choice}"]').click()
        for label, rating in zip("AB", ratings, strict=True):
            driver.find_element(
                By.CSS_SELECTOR, f'input[name="rate-{label}"][value="{rating}"]'
            ).click()
        if not shots:
            shots.append(full_page_png(driver))
        tampered = item == tamper
        if tampered:  # the page's own radio button, its value changed to 9
            driver.execute_script(
                "document.querySelector('input[name=\"rate-A\"]:checked').value = '9'"
            )
        driver.find_element(By.ID, "jspsych-survey-html-form-next").click()
        done.add(item)
        wait_sent(driver)
        status = driver.execute_script("return document.body.dataset.last")
        assert status == f"{item}:{400 if tampered else 200}"
        if tampered:
            notice = driver.find_element(By.ID, "notice").text
            assert item in notice and "rating outside the scale" in notice
        else:
            sent[item] = (choice, *ratings)
    return sent


def test_participants_rate_pairs_one_tampers_and_comes_back(studies, tmp_path):
    pairs, _ = studies
    study = read_study(pairs)
    expected = {i.id: i.expected for i in study.items}
    tamper = next(i.id for i in study.items if i.kind == "pair")
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(pairs, port)
    shots: list[bytes] = []
    try:
        driver = browser()
        try:
            first = rate_pairs(driver, base, "PROLIFIC-T", expected, tamper, shots)
            assert tamper not in first and len(first) == len(expected) - 1
            driver.refresh()  # the refused item is offered again
            first |= rate_pairs(driver, base, "PROLIFIC-T", expected, None, shots)
        finally:
            driver.quit()
        driver = browser()
        try:
            second = rate_pairs(driver, base, "PROLIFIC-U", expected, None, shots)
        finally:
            driver.quit()
    finally:
        server.kill()
        server.wait()
    (artifacts(tmp_path) / "study-page.png").write_bytes(shots[0])
    db = sqlite3.connect(pairs / "answers.sqlite")
    rows = db.execute("SELECT participant, item, choice, rating_a, rating_b FROM answers")
    stored = {(p, i): tuple(r) for p, i, *r in rows.fetchall()}
    db.close()
    assert stored == {
        **{("PROLIFIC-T", i): v for i, v in first.items()},
        **{("PROLIFIC-U", i): v for i, v in second.items()},
    }
    assert len(stored) == 2 * len(expected)
    refused = [r for r in read_refusals(pairs / "answers.sqlite") if r[0] == "PROLIFIC-T"]
    assert refused == [("PROLIFIC-T", tamper, first[tamper][0], "rating outside the scale")]


def test_an_expert_answers_the_expert_page(studies, tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    _, folder = studies
    study = read_study(folder)
    items = {i.id: i for i in study.items}
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(folder, port)
    sent = {}
    shot = None
    try:
        driver = browser()
        try:
            driver.get(f"{base}/?participant=expert-1")
            done: set[str] = set()
            while (item_id := current_item(driver, done)) is not None:
                item = items[item_id]
                panel = item.panel
                assert panel is not None
                shown = [e.text for e in driver.find_elements(By.CSS_SELECTOR, ".reasons dd")]
                assert shown == [r or "no stated reason recorded" for r in panel.reasons]
                has_clarity = bool(driver.find_elements(By.CSS_SELECTOR, ".clarity input"))
                assert has_clarity == panel.has_reasons()
                rows = driver.find_elements(By.CSS_SELECTOR, "table.judge tr")[1:]
                assert [r.find_element(By.TAG_NAME, "th").text for r in rows] == [
                    "up", "down", "left", "right"]  # fmt: skip
                number = int(item_id[1:])
                judged = []
                for a in range(4):
                    ok = (a + number) % 3 != 0
                    framework = FRAMEWORKS[(a + number) % 6]
                    value = "yes" if ok else "no"
                    driver.find_element(
                        By.CSS_SELECTOR, f'input[name="ok-{a}"][value="{value}"]'
                    ).click()
                    Select(driver.find_element(By.NAME, f"fw-{a}")).select_by_value(framework)
                    judged.append((a, ok, framework))
                clarity = None
                if has_clarity:
                    clarity = 1 + number % 5
                    driver.find_element(
                        By.CSS_SELECTOR, f'input[name="clarity"][value="{clarity}"]'
                    ).click()
                    if shot is None:
                        shot = full_page_png(driver)
                driver.find_element(By.ID, "jspsych-survey-html-form-next").click()
                done.add(item_id)
                wait_sent(driver)
                assert driver.execute_script("return document.body.dataset.last") == (
                    f"{item_id}:200"
                )
                sent[item_id] = (clarity, judged)
        finally:
            driver.quit()
    finally:
        server.kill()
        server.wait()
    assert shot is not None, "no state with a stated reason: the fixture gives some"
    (artifacts(tmp_path) / "study-expert-page.png").write_bytes(shot)
    assert set(sent) == set(items)
    db = sqlite3.connect(folder / "answers.sqlite")
    clarities = dict(db.execute("SELECT item, clarity FROM expert_answers").fetchall())
    actions = db.execute("SELECT item, action, acceptable, framework FROM expert_actions")
    stored: dict[str, list] = {}
    for item_id, a, ok, framework in actions.fetchall():
        stored.setdefault(item_id, []).append((a, bool(ok), framework))
    db.close()
    assert clarities == {i: c for i, (c, _) in sent.items()}
    assert {i: sorted(v) for i, v in stored.items()} == {i: j for i, (_, j) in sent.items()}
