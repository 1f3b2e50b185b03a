"""Exit statuses, one-line refusals, did-you-mean and fast ``view`` refusals of the CLI.

The exit statuses expected are read from the table of docs/trust.md ("Exit codes"), not
from the code under test.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from tiny_cli import one_line

from amuled_ma.cli import main, report_failure
from amuled_ma.errors import BackendUnavailable, ScenarioError, Terminated
from amuled_ma.servers.hosts import TINY_MODEL, preflight
from amuled_ma.tasks import canonical_name

REPO = Path(__file__).resolve().parents[1]


def documented_codes() -> dict[str, int]:
    """Exit status of each meaning, from the "Exit codes" table of docs/trust.md."""
    text = (REPO / "docs" / "trust.md").read_text(encoding="utf-8")
    section = text.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| (\d+) \| ([^|]+?) \|$", section, flags=re.MULTILINE)
    return {meaning.split(":")[0].split(" (")[0]: int(code) for code, meaning in rows}


def test_the_documented_table_is_the_help_epilog(capsys) -> None:
    codes = documented_codes()
    assert codes == {
        "done": 0,
        "an input or a run refused": 1,
        "a usage error": 2,
        "interrupted": 130,
        "terminated": 143,
    }
    with pytest.raises(SystemExit):
        main(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    for meaning, code in codes.items():
        assert f"{code} {meaning}" in help_text


def test_each_kind_of_failure_has_its_documented_status(tmp_path: Path, capsys) -> None:
    codes = documented_codes()
    assert main(["view", str(tmp_path / "nope")]) == codes["an input or a run refused"]
    one_line(capsys.readouterr().err)
    with pytest.raises(SystemExit) as usage:
        main(["view", str(tmp_path), "--no-such-option"])
    assert usage.value.code == codes["a usage error"]
    one_line(capsys.readouterr().err)
    missing = FileNotFoundError(2, "No such file or directory", str(tmp_path / "x"))
    for error, meaning in [
        (ScenarioError("x.toml: key [ppo].gamma"), "an input or a run refused"),
        (missing, "an input or a run refused"),
        (KeyboardInterrupt(), "interrupted"),
        (Terminated(15), "terminated"),
    ]:
        try:
            raise error
        except BaseException as caught:  # the CLI catches these too
            assert report_failure(caught) == codes[meaning], error


def test_a_multi_line_refusal_prints_one_line(capsys) -> None:
    try:
        raise ScenarioError("3 jobs cannot start:\n  - job a: bad\n  - job b: worse\n")
    except ScenarioError as error:
        assert report_failure(error) == 1
    line = one_line(capsys.readouterr().err)
    assert line == "amuled: error: 3 jobs cannot start: job a: bad; job b: worse"


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["run", "findmik"], "findmik"),
        (["clusters", "show", "care", "--task", "findmik"], "did you mean findmilk?"),
        (["clusters", "show", "care", "--task", "drving"], "did you mean driving?"),
        (["train", "findmilk", "--seed", "-5"], "--seed"),
        (
            ["explain", "findmilk", "--obs", "2,3,7,7,2,2,1,1", "--feedback", "cluster:car"],
            "no moral cluster 'car' (did you mean care?)",
        ),
        (
            [
                "explain",
                "findmilk",
                "--obs",
                "2,3,7,7,2,2,1,1",
                "--set",
                "feedback.clusters=['care','virtu']",
            ],
            "no moral cluster 'virtu' (did you mean virtue?)",
        ),
    ],
)
def test_sample_refusals_are_one_line(args: list[str], needle: str, capsys) -> None:
    try:
        code = main(args)
    except SystemExit as usage:
        code = usage.code
    assert code in (1, 2)
    assert needle in one_line(capsys.readouterr().err)


def test_unknown_task_names_the_closest() -> None:
    with pytest.raises(ScenarioError, match=r"did you mean findmilk\?"):
        canonical_name("find-milk")
    with pytest.raises(ScenarioError) as far:
        canonical_name("zzz")
    assert "did you mean" not in str(far.value)


@pytest.mark.parametrize(
    ("model", "advice"),
    [(TINY_MODEL, "'amuled ollama up --tiny'"), ("llama3.1:8b", "'amuled ollama up'")],
)
def test_unreachable_server_advice_names_tiny_for_the_tiny_model(model: str, advice: str):
    # port 1 on the loopback: nothing listens, the connection is refused at once
    with pytest.raises(BackendUnavailable) as refused:
        preflight("http://127.0.0.1:1", model, timeout=2.0)
    assert advice in str(refused.value)


def test_view_of_a_missing_folder_imports_neither_torch_nor_matplotlib(tmp_path: Path):
    code = (
        "import sys; from amuled_ma.cli import main; "
        f"rc = main(['view', {str(tmp_path / 'nope')!r}]); "
        "print(rc, 'torch' in sys.modules, 'matplotlib' in sys.modules)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60
    )
    assert done.stdout.split() == ["1", "False", "False"], done.stderr
    assert "is not a run directory" in one_line(done.stderr)


#: A command whose SIGTERM lands inside a finalizer (``__del__``), where Python drops the
#: handler's exception ("Exception ignored in ..."), then works on for 20 s.
LOST_IN_A_FINALIZER = """
import argparse, os, signal, sys, time
from amuled_ma import cli

class Finalized:
    def __del__(self):
        os.kill(os.getpid(), signal.{name})
        for _ in range(100_000):  # the handler runs in here; its exception is dropped
            pass

def command(_args):
    Finalized()  # dropped at once: __del__ runs now
    end = time.monotonic() + 20
    while time.monotonic() < end:
        time.sleep(0.01)
    print("worked on")
    return 0

parser = argparse.ArgumentParser()
parser.set_defaults(handler=command, debug=False)
cli.build_parser = lambda: parser
sys.exit(cli.main([]))
"""


@pytest.mark.parametrize(
    ("name", "meaning"), [("SIGTERM", "terminated"), ("SIGINT", "interrupted")]
)
def test_a_signal_whose_exception_a_finalizer_drops_still_stops_the_command(
    name: str, meaning: str
) -> None:
    script = LOST_IN_A_FINALIZER.replace("{name}", name)
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=REPO,
        # as a terminal's foreground command: a test run started in the background of a
        # non-interactive shell would hand it SIGINT ignored, and Python would keep it so
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    assert "worked on" not in done.stdout
    assert done.returncode == documented_codes()[meaning]
    line = {"terminated": "amuled: terminated (SIGTERM)", "interrupted": "amuled: interrupted"}
    assert done.stderr.splitlines() == [line[meaning]], done.stderr
