"""Fuzz the input doors: scenarios, cluster files, recordings, JSONL rows, caches, ``--set``.

A bounded number of generated cases (hypothesis, a fixed seed, a small ``max_examples``)
goes through the real loading functions in process, and a few through the real command
line: each ends in a value or an ``AmuledError`` (one line at the command line), never
another exception, a traceback or a hang.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st

from amuled_ma.errors import AmuledError

REPO = Path(__file__).resolve().parents[1]
FUZZ = settings(
    max_examples=25,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)

#: JSON-like values: the leaves include lone surrogates, huge and non-finite numbers.
leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(alphabet=st.characters(codec=None), max_size=20),
    st.sampled_from(["\ud800", "\x1b[2J", "findmilk", "care", "ok", "up"]),
)
values = st.recursive(
    leaves,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
toml_values = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1).map(str),
    st.floats(allow_nan=True).map(lambda f: repr(f).replace("nan", "nan").replace("inf", "inf")),
    st.text(max_size=10).map(json.dumps),
    st.sampled_from(["true", "[1, [2]]", '{layout="evil"}', "", "[" * 200 + "]" * 200, "-5"]),
)
keys = st.sampled_from(
    [
        "task.options", "task.max_steps", "task.seed", "ppo.gamma", "ppo.device", "base.num_envs",
        "finetune.iterations", "feedback.source", "feedback.recording", "output.name", "x.y",
    ]
)  # fmt: skip


def _ok_or_amuled(call) -> None:
    try:
        call()
    except AmuledError as error:
        assert str(error).strip()


@seed(24)
@FUZZ
@given(key=keys, value=toml_values)
def test_set_overrides(key: str, value: str) -> None:
    from amuled_ma.scenario import load_scenario
    from amuled_ma.scenario.overrides import parse_set

    def apply() -> None:
        section, name, parsed = parse_set(f"{key}={value}")
        load_scenario("findmilk").replace(section, **{name: parsed})

    _ok_or_amuled(apply)


@seed(24)
@FUZZ
@given(text=st.one_of(st.text(max_size=200), values.map(lambda v: f"a = {json.dumps(v)}")))
def test_scenario_files(tmp_path_factory, text: str) -> None:
    from amuled_ma.scenario import load_scenario

    path = tmp_path_factory.mktemp("scenario") / "s.toml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    _ok_or_amuled(lambda: load_scenario(path))


@seed(24)
@FUZZ
@given(data=values, raw=st.binary(max_size=64))
def test_recordings(tmp_path_factory, data, raw: bytes) -> None:
    from amuled_ma.beliefs.sources.replay import Recording

    folder = tmp_path_factory.mktemp("recording")
    as_json = folder / "r.json"
    as_json.write_text(json.dumps(data), encoding="utf-8", errors="surrogatepass")
    _ok_or_amuled(lambda: Recording(as_json))
    as_bytes = folder / "b.json"
    as_bytes.write_bytes(raw)
    _ok_or_amuled(lambda: Recording(as_bytes))


@seed(24)
@FUZZ
@given(row=st.fixed_dictionaries({}, optional={
    k: values for k in ("key", "source", "identity", "task", "cluster", "obs", "actions",
                        "belief", "status", "raw", "messages", "extra", "attempts")
}))  # fmt: skip
def test_jsonl_rows(row: dict) -> None:
    from amuled_ma.beliefs.store.interchange import parse_line

    line = json.dumps(row)
    _ok_or_amuled(lambda: parse_line(line, "fuzz.jsonl:1", verify=True))
    _ok_or_amuled(lambda: parse_line(line, "fuzz.jsonl:1", verify=False))


@seed(24)
@FUZZ
@given(text=st.text(max_size=200))
def test_cluster_files(tmp_path_factory, text: str) -> None:
    from amuled_ma.clusters.loader import load_cluster

    path = tmp_path_factory.mktemp("clusters") / "c.toml"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    _ok_or_amuled(lambda: load_cluster(path))


#: Values of the kinds the authors' caches hold (tuples of numpy scalars, strings, dicts),
#: and arrays of every dtype kind (object, void, strings: refused, never built).
cache_values = st.recursive(
    st.one_of(
        leaves.filter(lambda v: not (isinstance(v, str) and "\ud800" in v)),
        st.floats(width=32).map(np.float32),
        st.integers(min_value=-(2**31), max_value=2**31 - 1).map(np.int64),
        st.sampled_from(["f4", "i8", "u1", "c8", "?", "V4", "S3", "U2", "O"]).map(
            lambda kind: np.zeros(3, dtype=kind)
        ),
    ),
    lambda inner: (
        st.lists(inner, max_size=4).map(tuple)
        | st.frozensets(st.text(max_size=4), max_size=3)
        | st.dictionaries(st.one_of(st.text(max_size=6), st.integers()), inner, max_size=4)
    ),
    max_leaves=12,
)


@seed(24)
@FUZZ
@given(value=cache_values, flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255))))
def test_authors_caches(tmp_path_factory, value, flips: list[tuple[int, int]]) -> None:
    """A cache pickle, whole or with bytes changed, loads or is refused with one line."""
    from amuled_ma.authors.unpickle import load_pickle

    data = bytearray(pickle.dumps(value, protocol=4))
    folder = tmp_path_factory.mktemp("caches")
    whole = folder / "whole_llm_cache.pickle"
    whole.write_bytes(bytes(data))
    _ok_or_amuled(lambda: load_pickle(whole))
    for position, byte in flips:
        data[position % len(data)] = byte
    changed = folder / "changed_llm_cache.pickle"
    changed.write_bytes(bytes(data))
    _ok_or_amuled(lambda: load_pickle(changed))


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "findmilk", "--set", "task.options=" + "{a=" * 3000 + "1" + "}" * 3000],
        ["train", "findmilk", "--set", "ppo.gamma=nan"],
        ["beliefs", "import", "--store", "{tmp}/s.sqlite", "{tmp}/junk.jsonl"],
        ["view", "{tmp}", "--serve", "--serve-seconds", "inf"],
        ["explain", "findmilk", "--obs", "\x1b[2J,nan"],
    ],
)
def test_command_line_cases_end_in_one_line(tmp_path: Path, argv: list[str], capsys) -> None:
    """In process (``amuled_ma.cli.main``), as the generated command lines below are."""
    from amuled_ma.cli import main

    (tmp_path / "junk.jsonl").write_bytes(b'{"key": "\\ud800"}\n\xff\xfe\n')
    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    if args[0] == "train":
        args += ["--run-dir", str(tmp_path / "run")]
    try:
        code = main(args)
    except SystemExit as usage:  # argparse's usage error
        code = usage.code
    err = capsys.readouterr().err
    assert code in (1, 2), err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1].startswith("amuled: error: ")


def test_a_command_line_case_ends_in_one_line_in_a_real_process(tmp_path: Path) -> None:
    """The real interpreter's standard error (its encoding set as a terminal's): one line."""
    (tmp_path / "junk.jsonl").write_bytes(b'{"key": "\\ud800"}\n\xff\xfe\n')
    done = subprocess.run(
        [sys.executable, "-m", "amuled_ma", "beliefs", "import", "--store",
         str(tmp_path / "s.sqlite"), str(tmp_path / "junk.jsonl")],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        env={**os.environ, "PYTHONIOENCODING": "utf-8:backslashreplace"},
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines()[-1].startswith("amuled: error: ")


#: Commands that read input files and never train, with their fixed arguments; the fuzz
#: adds generated arguments after them (``{tmp}``: the example's folder).
QUIET_COMMANDS = [
    ["explain", "findmilk", "--feedback", "rules"],
    ["evaluate", "{tmp}/run"],
    ["view", "{tmp}/run"],
    ["beliefs", "stats", "--store", "{tmp}/s.sqlite"],
    ["beliefs", "import", "--store", "{tmp}/s.sqlite", "{tmp}/in.jsonl"],
    ["import", "authors", "{tmp}/checkout", "--runs", "{tmp}/runs", "--to", "{tmp}/rec"],
    ["clusters", "list", "--clusters-dir", "{tmp}/clusters"],
]
#: Flags and values of those commands, and values any argument may take. A real argv
#: holds no NUL character; bytes that are not UTF-8 reach Python as lone surrogates.
cli_words = st.one_of(
    st.sampled_from([
        "--obs", "--state-from", "--variant", "--step", "--episodes", "--seed", "--set",
        "--run-dir", "--no-verify", "--clusters-dir", "--allow-plugin", "--debug", "-h",
        "--feedback", "--fusion", "--out", "1e12", "-5", "nan", "0,0,0,0,0,0,0,0",
        "subprocess:Popen", "ppo.gamma=nan", "task.options={layout=1}", "{tmp}/run",
        "{tmp}/in.jsonl", "\udcff\udcfe", "\x1b[2J", "../..", "",
    ]),
    st.text(alphabet=st.characters(blacklist_characters="\x00"), max_size=12),
)  # fmt: skip


@seed(24)
@settings(FUZZ, max_examples=20)
@given(command=st.sampled_from(QUIET_COMMANDS), extra=st.lists(cli_words, max_size=5),
       jsonl=st.binary(max_size=80))  # fmt: skip
def test_generated_command_lines(tmp_path_factory, command, extra, jsonl: bytes) -> None:
    """Generated arguments of the real command line: an exit status, never a traceback.

    In process (``amuled_ma.cli.main``), with standard output strict UTF-8 as a terminal's
    and standard error writing escapes, as Python sets them up.
    """
    import contextlib
    import io

    from amuled_ma.cli import main

    tmp = tmp_path_factory.mktemp("cli")
    (tmp / "in.jsonl").write_bytes(jsonl)
    (tmp / "run").mkdir()
    (tmp / "clusters").mkdir()
    (tmp / "clusters" / "c.toml").write_bytes(jsonl)
    argv = [word.replace("{tmp}", str(tmp)) for word in [*command, *extra]]
    out = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors="strict", write_through=True)
    err = io.TextIOWrapper(
        io.BytesIO(), encoding="utf-8", errors="backslashreplace", write_through=True
    )
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as stop:  # argparse: --help (0) or a usage error (2)
            code = stop.code
    text = err.buffer.getvalue().decode("utf-8")
    assert code in (0, 1, 2), (argv, code, text)
    assert "Traceback" not in text or "--debug" in argv, (argv, text)
    if code == 1:
        assert text.strip().splitlines()[-1].startswith("amuled: error: "), (argv, text)


# -- a distilled fine-tune's state files ----------------------------------------------------
class _Panel:
    """A panel source of two members: a fixed belief for every request (no store)."""

    name = "fuzz-panel"
    needs_messages = False

    def identity(self) -> dict:
        return {"source": self.name}

    def beliefs(self, requests):
        from amuled_ma.beliefs.types import BeliefResult

        return [BeliefResult(np.array([0.7, 0.1, 0.1, 0.1]), "ok", self.name) for _ in requests]

    def close(self) -> None:
        pass


def _requests(states):
    from amuled_ma.beliefs.types import BeliefRequest

    return [
        BeliefRequest("findmilk", member, (float(s), 0.0), ("up", "down", "left", "right"), ())
        for s in states
        for member in ("care", "virtue")
    ]


def _distilled(folder: Path, *, resume: bool):
    from amuled_ma.distill import DistilledSource

    return DistilledSource(
        _Panel(), budget=0.25, ensemble=2, hidden=4, fit_steps=5, seed=1,
        state_dir=folder, resume=resume,
    )  # fmt: skip


_HONEST: dict[str, bytes] = {}


def _honest_files() -> dict[str, bytes]:
    """The two state files of a fine-tune that visited 8 states and asked 2 (made once)."""
    if not _HONEST:
        import tempfile

        from amuled_ma.distill.state import EXAMPLES_FILE, LEDGER_FILE

        with tempfile.TemporaryDirectory() as name:
            source = _distilled(Path(name), resume=False)
            source.beliefs(_requests(range(8)))
            source.close()
            for file in (LEDGER_FILE, EXAMPLES_FILE):
                _HONEST[file] = (Path(name) / file).read_bytes()
    return _HONEST


def _paths(value, prefix=()):
    """Every path to a value of a JSON document (tables and lists walked)."""
    yield prefix
    if isinstance(value, dict):
        for key, inner in value.items():
            yield from _paths(inner, (*prefix, key))
    elif isinstance(value, list):
        for i, inner in enumerate(value[:3]):
            yield from _paths(inner, (*prefix, i))


def _replaced(document, path, new):
    if not path:
        return new
    head, *rest = path
    document[head] = _replaced(document[head], tuple(rest), new)
    return document


def _resume_ok_or_amuled(folder: Path) -> None:
    """Resume from the files: a refusal, or a source that keeps within the budget."""

    def resume() -> None:
        source = _distilled(folder, resume=True)
        source.beliefs(_requests(range(8, 16)))
        ledger = source.ledger
        assert ledger.asked_count <= max(ledger.cap(), 2)  # 2: the honest run's asked
        assert source.report()["requests_forwarded"] <= 2 * 2 + 2 * 8

    _ok_or_amuled(resume)


@seed(24)
@FUZZ
@given(choice=st.integers(0, 10**6), new=values)
def test_distill_ledgers(tmp_path_factory, choice: int, new) -> None:
    """``distill.json`` with one value anywhere replaced: resumed within budget, or one line."""
    from amuled_ma.distill.state import EXAMPLES_FILE, LEDGER_FILE

    honest = _honest_files()
    document = json.loads(honest[LEDGER_FILE])
    paths = list(_paths(document))
    document = _replaced(document, paths[choice % len(paths)], new)
    folder = tmp_path_factory.mktemp("distill")
    (folder / LEDGER_FILE).write_text(json.dumps(document), errors="surrogatepass")
    (folder / EXAMPLES_FILE).write_bytes(honest[EXAMPLES_FILE])
    _resume_ok_or_amuled(folder)


@seed(24)
@FUZZ
@given(choice=st.integers(0, 10**6), new=values, raw=st.binary(max_size=40))
def test_distill_training_pairs(tmp_path_factory, choice: int, new, raw: bytes) -> None:
    """``distill-examples.jsonl`` with a value replaced and bytes added: resumed, or one line."""
    from amuled_ma.distill.state import EXAMPLES_FILE, LEDGER_FILE

    honest = _honest_files()
    lines = honest[EXAMPLES_FILE].decode().splitlines()
    record = json.loads(lines[0])
    paths = list(_paths(record))
    record = _replaced(record, paths[choice % len(paths)], new)
    text = json.dumps(record) + "\n" + "\n".join(lines[1:]) + "\n"
    folder = tmp_path_factory.mktemp("distill")
    (folder / LEDGER_FILE).write_bytes(honest[LEDGER_FILE])
    (folder / EXAMPLES_FILE).write_bytes(text.encode("utf-8", "surrogatepass") + raw)
    _resume_ok_or_amuled(folder)


#: ``--set`` values of a list key: TOML lists, broken ones, and names of every kind.
set_lists = st.one_of(
    st.lists(st.text(max_size=8), max_size=4).map(lambda items: json.dumps(items)),
    st.lists(st.text(max_size=8), max_size=4).map(lambda items: "[" + ",".join(items)),
    st.text(alphabet="[]{},'\"= abc\u2800\ufe0f", max_size=20),
    st.sampled_from(["[]", "['care','care']", "['care','CARE']", "['care'", "[care]"]),
)


@seed(24)
@FUZZ
@given(key=st.sampled_from(["feedback.clusters", "feedback.hosts", "evaluation.modes",
                            "ppo.hidden_dims", "feedback.fusion", "fedback.clusters"]),
       value=set_lists)  # fmt: skip
def test_set_lists(key: str, value: str) -> None:
    """A ``--set`` of a list, parsed and applied: a scenario, or one ``AmuledError`` line."""
    from amuled_ma.scenario import load_scenario
    from amuled_ma.scenario.overrides import parse_set

    def apply() -> None:
        section, name, parsed = parse_set(f"{key}={value}")
        load_scenario("findmilk").replace(section, **{name: parsed})

    try:
        apply()
    except AmuledError as error:
        assert "\n" not in str(error).strip()


#: Bodies a study participant's browser could send: JSON-like values (dicts with the
#: fields' names among their keys), raw bytes, and well-formed answers with generated fields.
study_fields = st.sampled_from(["participant", "token", "item", "choice", "ms", "ratings",
                                "prolific", "judged", "source"])  # fmt: skip
study_bodies = st.one_of(
    st.binary(max_size=80),
    values.map(lambda v: json.dumps(v).encode("utf-8", "surrogatepass")),
    st.dictionaries(study_fields, values, max_size=6).map(
        lambda d: json.dumps(d).encode("utf-8", "surrogatepass")
    ),
)


@pytest.fixture
def study_client(tmp_path_factory):
    """The real study app, started once, with one participant's session: ``(client, own)``."""
    sys.path.insert(0, str(REPO / "tests" / "study"))
    from starlette.testclient import TestClient
    from study_fixtures import hand_study

    from amuled_ma.study.server import StudyApp

    study = StudyApp(hand_study(tmp_path_factory.mktemp("study") / "s"))
    with TestClient(study.app, raise_server_exceptions=False) as client:
        me = client.post("/api/session", json={}).json()
        yield client, {"participant": me["participant"], "token": me["token"], "item": "q001"}


@seed(24)
@settings(FUZZ, max_examples=25)
@given(path=st.sampled_from(["/api/session", "/api/answer"]), body=study_bodies,
       fields=st.dictionaries(study_fields, values, max_size=4))  # fmt: skip
def test_study_requests(study_client, path: str, body: bytes, fields: dict) -> None:
    """A request to the real study app: 200 or a 4xx with a short error, never a 500."""
    client, own = study_client
    answer = {**own, "choice": "A", "ms": 5, "ratings": {"A": 1, "B": 2}, **fields}
    for sent in (body, json.dumps(answer).encode("utf-8", "surrogatepass")):
        reply = client.post(path, content=sent)
        assert reply.status_code < 500, (sent[:80], reply.text[:200])
        if reply.status_code >= 400:
            error = reply.json()["error"]
            assert isinstance(error, str) and 0 < len(error) < 500, error


_TABLE: bytes | None = None


def _npy(shape: tuple[int, ...], descr: str) -> bytes:
    import io

    buffer = io.BytesIO()
    np.lib.format.write_array_header_2_0(
        buffer, {"descr": descr, "fortran_order": False, "shape": shape}
    )
    return buffer.getvalue()


@seed(24)
@settings(FUZZ, max_examples=30)
@given(flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=4),
       shape=st.lists(st.integers(0, 2**62), min_size=0, max_size=3).map(tuple),
       descr=st.sampled_from(["<i8", "<f4", "|O", "<U8", "|V16", "<i8,<i8", "x"]),
       member=st.sampled_from(["states.npy", "counts.npy", "task.npy", "settings.npy"]),
       tail=st.binary(max_size=64))  # fmt: skip
def test_demonstrator_tables(tmp_path_factory, flips, shape, descr: str, member: str, tail) -> None:
    """A demonstrator ``.npz``: a table, or one ``AmuledError`` line; never MemoryError."""
    import zipfile

    import torch

    from amuled_ma.tasks.demonstrators import DemonstratorBelief

    folder = tmp_path_factory.mktemp("npz")
    global _TABLE
    if _TABLE is None:  # one honest table's bytes (saving fsyncs: not once per example)
        table = DemonstratorBelief(
            "findmilk", torch.arange(3, dtype=torch.int64), torch.ones(3, 4, dtype=torch.int64),
            {"task": "findmilk", "seed": 1, "episodes": 1},
        )  # fmt: skip
        _TABLE = table.save(folder / "honest.npz").read_bytes()
    flipped = bytearray(_TABLE)
    for at, byte in flips:
        flipped[at % len(flipped)] = byte
    (folder / "flipped.npz").write_bytes(bytes(flipped))
    try:
        header = _npy(shape, descr)
    except ValueError:  # a dtype numpy cannot describe in a header
        header = b"\x93NUMPY" + tail
    with zipfile.ZipFile(folder / "claims.npz", "w") as archive:
        archive.writestr(member, header + tail)
    for name in ("flipped.npz", "claims.npz"):
        _ok_or_amuled(lambda name=name: DemonstratorBelief.load(folder / name))
