"""amuled study serve, end to end: 20 participants at once, a kill -9, nothing lost.

17 participants answer over plain HTTP from threads and 3 in Debian's headless chromium
(selenium, as the viewer's tests; skipped with the reason when absent), through the real
server started as ``amuled study serve`` in its own process. One HTTP participant fails
its attention check, one submits an answer twice, one tampers with its forms; the server
is killed with SIGKILL while the HTTP participants are answering and started again; one
browser participant reloads the page in the middle.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import threading
import time
from pathlib import Path

import httpx
import pytest
from sparse_files import sparse
from study_fixtures import (
    agree_to_consent,
    artifacts,
    browser,
    free_port,
    hand_study,
    start_server,
    tiny_run,
    wait_sent,
    wait_state,
)
from tiny_cli import one_line

from amuled_ma.cli import main
from amuled_ma.study.answers import read_refusals
from amuled_ma.study.build import build_study
from amuled_ma.study.report import write_analysis

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("study")
    run = tiny_run(folder)
    build_study([run], ["amuled", "base", "human"], folder / "s", items=12, seed=2, attention=2)
    return folder / "s"


def ratings_of(n: int) -> dict[str, int]:
    """The ratings a simulated participant gives its n-th answer (both on the 1..7 scale)."""
    return {"A": 1 + n % 7, "B": 7 - n % 4}


class Participant:
    """One HTTP participant: retries through a dead server; keeps what the server said."""

    def __init__(self, base: str, name: str) -> None:
        self.base, self.name = base, name
        self.accepted: list[str] = []
        self.after_error: list[str] = []  # sent, connection lost: stored or not
        self.codes: list[int] = []

    def post(self, path: str, body: dict) -> httpx.Response:
        for _ in range(600):
            try:
                return httpx.post(self.base + path, json=body, timeout=5)
            except httpx.TransportError:
                if path == "/api/answer":
                    self.after_error.append(body["item"])
                time.sleep(0.05)
        raise AssertionError(f"{self.name}: the server never came back")

    def run(self, expected: dict[str, str | None], fail_attention: bool = False) -> None:
        me = self.post("/api/session", {}).json()
        self.id, self.token = me["participant"], me["token"]
        for shown in me["items"]:
            wanted = expected[shown["id"]]
            choice = wanted if wanted else ("A" if len(self.accepted) % 3 else "B")
            if wanted and fail_attention:
                choice = "B" if wanted == "A" else "A"
            form = {"participant": self.id, "token": self.token, "item": shown["id"]}
            ratings = ratings_of(len(self.accepted))
            r = self.post("/api/answer", {**form, "choice": choice, "ms": 850, "ratings": ratings})
            self.codes.append(r.status_code)
            if r.status_code == 200:
                self.accepted.append(shown["id"])
            time.sleep(0.1)


def browser_participant(base: str, expected: dict, url_id: str, reload_after: int | None):
    """Answer every item on the jsPsych page: the choice and both ratings."""
    from selenium.webdriver.common.by import By

    driver = browser()
    answered: list[str] = []
    try:
        driver.get(f"{base}/?PROLIFIC_PID={url_id}")
        shots = []
        while True:
            state = wait_state(driver)
            if state == "done":
                break
            if state == "consent":
                agree_to_consent(driver)
                continue
            item = driver.execute_script("return document.body.dataset.item")
            if item in answered:  # the page moves on after the click: wait for it
                time.sleep(0.025)
                continue
            if not shots:
                shots.append(driver.get_screenshot_as_png())
            labels = [e.text for e in driver.find_elements(By.CSS_SELECTOR, ".option span")]
            choice = expected[item] or "A"
            assert [label[:2] for label in labels] == ["A:", "B:"]
            driver.find_element(By.CSS_SELECTOR, f'input[name="choice"][value="{choice}"]').click()
            for label, rating in ratings_of(len(answered)).items():
                driver.find_element(
                    By.CSS_SELECTOR, f'input[name="rate-{label}"][value="{rating}"]'
                ).click()
            driver.find_element(By.ID, "jspsych-survey-html-form-next").click()
            answered.append(item)
            if reload_after is not None and len(answered) == reload_after:
                wait_sent(driver)  # the answer's request has been answered
                driver.refresh()
        wait_sent(driver)
        return answered, shots
    finally:
        driver.quit()


def test_twenty_participants_a_kill_and_nothing_lost(study, tmp_path):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    manifest = json.loads((study / "study.json").read_text())
    expected = {i["id"]: i["expected"] for i in manifest["items"]}
    n_items = len(expected)
    server = start_server(study, port)
    try:
        people = [Participant(base, f"h{i}") for i in range(17)]
        threads = [
            threading.Thread(target=p.run, args=(expected, i == 3)) for i, p in enumerate(people)
        ]
        for t in threads:
            t.start()
        for _ in range(1000):  # kill it once some answers are in, mid-study
            with sqlite3.connect(study / "answers.sqlite") as db:
                if db.execute("SELECT COUNT(*) FROM answers").fetchone()[0] >= 17:
                    break
            time.sleep(0.01)
        os.kill(server.pid, signal.SIGKILL)
        server.wait()
        with sqlite3.connect(study / "answers.sqlite") as db:
            before = db.execute("SELECT COUNT(*) FROM answers").fetchone()[0]
        assert 0 < before < 17 * n_items  # killed mid-study
        server = start_server(study, port)
        for t in threads:
            t.join(120)
        # a browser participant after the restart, reloading the page after 4 answers
        answered, shots = browser_participant(base, expected, "PROLIFIC-1", reload_after=4)
        assert sorted(answered) == sorted(expected)  # resumed: every item once
        (artifacts(tmp_path) / "study-page-server.png").write_bytes(shots[0])
        for name in ("PROLIFIC-2", "PROLIFIC-3"):
            assert len(browser_participant(base, expected, name, None)[0]) == n_items

        # a double submission, a tampered form
        p = people[0]
        first = expected and next(iter(expected))
        body = {"participant": p.id, "token": p.token, "item": first, "choice": "A", "ms": 10,
                "ratings": {"A": 4, "B": 4}}  # fmt: skip
        assert httpx.post(base + "/api/answer", json=body).status_code == 409
        other = Participant(base, "tamper")
        me = other.post("/api/session", {}).json()
        own = {"participant": me["participant"], "token": me["token"], "ms": 5,
               "ratings": {"A": 2, "B": 6}}  # fmt: skip
        tampered = [
            ({**own, "item": "q999", "choice": "A"}, 400),
            ({**own, "item": first, "choice": "C"}, 400),
            ({**own, "item": first, "choice": "A", "token": p.token}, 403),
            ({**own, "participant": p.id, "item": first, "choice": "B"}, 403),
            ({**own, "item": first, "choice": "A", "ms": "fast"}, 400),
            ({**own, "item": first, "choice": "A", "ratings": {"A": 8, "B": 1}}, 400),
            ({**own, "item": first, "choice": "A", "ratings": {"A": 0, "B": 1}}, 400),
            ({**own, "item": first, "choice": "A", "ratings": {"A": 2, "B": 2, "C": 5}}, 400),
            ({**own, "item": first, "choice": "A", "ratings": {"A": 2}}, 400),
        ]
        for claim in ({"participant": p.id}, {"participant": p.id, "source": "assigned"}):
            assert httpx.post(base + "/api/session", json=claim).status_code == 403
        for form, code in tampered:
            assert httpx.post(base + "/api/answer", json=form).status_code == code
        ok = httpx.post(base + "/api/answer", json={**own, "item": first, "choice": "A"})
        assert ok.status_code == 200
        assert (
            httpx.post(base + "/api/answer", json={**own, "item": first, "choice": "B"}).status_code
            == 409
        )
    finally:
        server.kill()
        server.wait()

    db = sqlite3.connect(study / "answers.sqlite")
    rows = db.execute("SELECT participant, item, choice, correct, ms FROM answers").fetchall()
    stored: dict[str, set[str]] = {}
    for pid, item, _, _, _ in rows:
        stored.setdefault(pid, set()).add(item)
    # every answer the server accepted is there; nothing else (an answer in flight at the
    # kill may have been stored: the retry then met 409)
    for person in people:
        assert set(person.accepted) <= stored[person.id]
        assert stored[person.id] <= set(person.accepted) | set(person.after_error)
        assert stored[person.id] == set(expected)  # each finished, each item once
        assert all(code in (200, 409) for code in person.codes)
    assert len(stored) == 17 + 3 + 1
    assert len(rows) == 20 * n_items + 1
    assert {pid for pid in stored if pid.startswith("PROLIFIC-")} == {
        f"PROLIFIC-{i}" for i in (1, 2, 3)
    }
    failed = {r[0] for r in rows if r[3] == 0}
    assert failed == {people[3].id}
    assert all(r[4] >= 0 for r in rows)
    reasons = [r[3] for r in read_refusals(study / "answers.sqlite")]
    for reason in ("unknown item", "unknown choice", "wrong token", "bad time", "already answered",
                   "rating outside the scale", "rating for an option not shown",
                   "ratings missing"):  # fmt: skip
        assert reason in reasons
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    # every stored answer has its two ratings on the scale; the tamperer's is the one sent
    ratings = db.execute("SELECT participant, rating_a, rating_b FROM answers").fetchall()
    assert all(1 <= a <= 7 and 1 <= b <= 7 for _, a, b in ratings)
    assert [(a, b) for pid, a, b in ratings if pid == me["participant"]] == [(2, 6)]
    db.close()
    # the report of these twenty participants (its figure is the doc's study_analysis.png)
    report = write_analysis(study).read_text()
    summary = json.loads((study / "analysis" / "summary.json").read_text())
    assert summary["participants"] == 21 and summary["kept"] == 20
    assert summary["answers_rated"] == summary["pairs_answered"]
    assert "## Acceptability" in report
    (artifacts(tmp_path) / "study-analysis.png").write_bytes(
        (study / "analysis" / "strengths.png").read_bytes()
    )


# ---------------------------------------------------------------------------------------
# Size caps: the folder's files and the participants' bodies, bounded


def test_a_picture_or_consent_page_over_its_cap_stops_the_start_with_one_line(tmp_path, capsys):
    from amuled_ma.study.server import MAX_CONSENT_BYTES, MAX_PICTURE_BYTES

    assert (MAX_PICTURE_BYTES, MAX_CONSENT_BYTES) == (4 * 2**20, 16 * 2**20)
    port = str(free_port())
    folder = hand_study(tmp_path / "s")
    picture = sparse(folder / "states" / "q001.svg", 10 * 2**30)
    capsys.readouterr()
    assert main(["study", "serve", str(folder), "--port", port]) == 1
    assert one_line(capsys.readouterr().err) == (
        f"amuled: error: {picture}: the state picture is 10,737,418,240 bytes, more than the "
        "4,194,304 a state picture may be (a drawn state is about 3 KB); it is not read; is "
        "it the right folder? Rebuild the study with 'amuled study build'"
    )
    folder = hand_study(tmp_path / "t")
    consent = sparse(folder / "consent.html", 10 * 2**30)
    assert main(["study", "serve", str(folder), "--port", port]) == 1
    assert one_line(capsys.readouterr().err) == (
        f"amuled: error: {consent}: the consent page is 10,737,418,240 bytes, more than the "
        "16,777,216 a consent page may be (the shipped templates are about 2 KB); it is not "
        "read; is it the right file? Edit it down, or rebuild the study to get the template"
    )


def test_a_consent_page_grown_past_its_cap_and_a_long_body_are_refused_unread(tmp_path, capsys):
    import asyncio

    from amuled_ma.study.server import CONSENT_REFUSED, MAX_BODY_BYTES, StudyApp

    assert MAX_BODY_BYTES == 64 * 2**10
    folder = hand_study(tmp_path / "s")
    study = StudyApp(folder)

    async def visit() -> None:
        transport = httpx.ASGITransport(app=study.app)
        async with httpx.AsyncClient(transport=transport, base_url="http://study") as client:
            assert (await client.get("/consent")).text == "<p>my own words</p>"  # as before
            sparse(folder / "consent.html", 10 * 2**30)  # edited while the study runs
            answer = await client.get("/consent")
            assert answer.status_code == 500 and answer.text == CONSENT_REFUSED
            assert str(folder) not in answer.text  # the participant is not shown the path
            me = (await client.post("/api/session", json={})).json()
            body = {"participant": me["participant"], "token": me["token"], "item": "q001",
                    "choice": "A", "ms": 1000, "ratings": {"A": 2, "B": 5}}  # fmt: skip
            pad = "x" * MAX_BODY_BYTES
            assert (await client.post("/api/answer", json={**body, "pad": pad})).status_code == 413
            assert (await client.post("/api/session", json={"pad": pad})).status_code == 413

            async def chunks():  # no Content-Length: counted as it comes
                for _ in range(3):
                    yield b" " * (MAX_BODY_BYTES // 2)

            assert (await client.post("/api/session", content=chunks())).status_code == 413
            assert (await client.post("/api/answer", json=body)).status_code == 200

    try:
        asyncio.run(visit())
    finally:
        study.store.close()
    assert "the consent page is 10,737,418,240 bytes" in capsys.readouterr().err
    assert read_refusals(folder / "answers.sqlite") == [
        (None, None, None, "answer: body too large")
    ]
