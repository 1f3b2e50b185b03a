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
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest
from study_fixtures import tiny_run

from amuled_ma.study.answers import read_refusals
from amuled_ma.study.build import build_study

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
ROOT = Path(__file__).parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(study: Path, port: int) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-m", "amuled_ma", "study", "serve", str(study), "--port", str(port)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    for _ in range(300):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=1).status_code == 200:
                return proc
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise AssertionError(f"the server never answered: {proc.stderr.read().decode()[-2000:]}")


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("study")
    run = tiny_run(folder)
    build_study([run], ["amuled", "base", "human"], folder / "s", items=12, seed=2, attention=2)
    return folder / "s"


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
            r = self.post("/api/answer", {**form, "choice": choice, "ms": 850})
            self.codes.append(r.status_code)
            if r.status_code == 200:
                self.accepted.append(shown["id"])
            time.sleep(0.1)


def browser_participant(base: str, expected: dict, url_id: str, reload_after: int | None):
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.skip(f"no browser: {', '.join(missing)} missing; apt-get install chromium "
                    "chromium-driver (.ci/setup does)")  # fmt: skip
    webdriver = pytest.importorskip("selenium.webdriver", reason="pip install -e '.[test]'")
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1000,1100"):  # fmt: skip
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    answered: list[str] = []
    try:
        driver.get(f"{base}/?PROLIFIC_PID={url_id}")

        def wait_state():
            for _ in range(400):
                state = driver.execute_script("return document.body.dataset.state")
                if state in ("consent", "item", "done"):
                    return state
                time.sleep(0.025)
            raise AssertionError(f"page stuck in {state}")

        shots = []
        while True:
            state = wait_state()
            if state == "done":
                break
            if state == "consent":
                driver.find_element(
                    By.CSS_SELECTOR, "#jspsych-html-button-response-button-0 button"
                ).click()
                time.sleep(0.1)
                continue
            item = driver.execute_script("return document.body.dataset.item")
            if item in answered:  # the page moves on after the click: wait for it
                time.sleep(0.025)
                continue
            if not shots:
                shots.append(driver.get_screenshot_as_png())
            labels = [b.text for b in driver.find_elements(By.CSS_SELECTOR, ".jspsych-btn")]
            index = 0 if expected[item] in (None, "A") else 1
            assert labels[index].startswith("AB"[index])
            driver.find_element(
                By.CSS_SELECTOR, f"#jspsych-html-button-response-button-{index} button"
            ).click()
            answered.append(item)
            if reload_after is not None and len(answered) == reload_after:
                for _ in range(200):  # the answer's request has been answered
                    if driver.execute_script("return document.body.dataset.pending") == "0":
                        break
                    time.sleep(0.025)
                driver.refresh()
        for _ in range(200):
            if driver.execute_script("return document.body.dataset.pending || '0'") == "0":
                break
            time.sleep(0.025)
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
        (Path(os.environ.get("AMULED_ARTIFACTS") or tmp_path) / "study-page.png").write_bytes(
            shots[0]
        )
        for name in ("PROLIFIC-2", "PROLIFIC-3"):
            assert len(browser_participant(base, expected, name, None)[0]) == n_items

        # a double submission, a tampered form
        p = people[0]
        first = expected and next(iter(expected))
        body = {"participant": p.id, "token": p.token, "item": first, "choice": "A", "ms": 10}
        assert httpx.post(base + "/api/answer", json=body).status_code == 409
        other = Participant(base, "tamper")
        me = other.post("/api/session", {}).json()
        own = {"participant": me["participant"], "token": me["token"], "ms": 5}
        tampered = [
            ({**own, "item": "q999", "choice": "A"}, 400),
            ({**own, "item": first, "choice": "C"}, 400),
            ({**own, "item": first, "choice": "A", "token": p.token}, 403),
            ({**own, "participant": p.id, "item": first, "choice": "B"}, 403),
            ({**own, "item": first, "choice": "A", "ms": "fast"}, 400),
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
    for reason in ("unknown item", "unknown choice", "wrong token", "bad time", "already answered"):
        assert reason in reasons
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
