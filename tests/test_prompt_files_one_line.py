"""Prompt files that are not UTF-8 are one line naming the file (docs/trust.md).

The last input of the trust table without a test of its failure line: ``system.md`` and a
state prompt template, as a ``prompts/`` folder given in place of the shipped one.
"""

from __future__ import annotations

import pytest
from sparse_files import sparse

from amuled_ma.clusters.prompting import fewshot_messages, render_system_prompt
from amuled_ma.errors import ClusterDefinitionError, PromptError
from amuled_ma.files.resources import MAX_PROMPT_BYTES
from amuled_ma.tasks.prompts import parse_template


def test_a_system_prompt_that_is_not_utf8_is_one_line(tmp_path):
    (tmp_path / "system.md").write_bytes(b"\xff\xfe{clusters}\n")
    with pytest.raises(PromptError) as info:
        render_system_prompt(prompts=tmp_path)
    message = str(info.value)
    assert message.startswith(f"{tmp_path / 'system.md'}: the system prompt is not UTF-8 text")
    assert "save it as UTF-8" in message and "\n" not in message


def test_a_state_template_that_is_not_utf8_is_one_line(tmp_path):
    path = tmp_path / "findmilk.md"
    path.write_bytes(b"## prompt\n\x80 robot at {x}\n")
    with pytest.raises(PromptError) as info:
        parse_template(path)
    message = str(info.value)
    assert message.startswith(f"{path}: the state prompt template is not UTF-8 text")
    assert "\n" not in message


def _refused_unread(message: str, path, what: str) -> None:
    assert "\n" not in message
    assert message.startswith(f"{path}: the {what} is {MAX_PROMPT_BYTES + 1:,} bytes, more than ")
    assert f"the {MAX_PROMPT_BYTES:,} a {what} may be" in message and "it is not read" in message


def test_prompt_files_over_1_mb_are_refused_unread(tmp_path):
    assert MAX_PROMPT_BYTES == 1_000_000
    (tmp_path / "system.md").write_text("{clusters}\n")
    sparse(tmp_path / "system.md", MAX_PROMPT_BYTES + 1)
    with pytest.raises(PromptError) as info:
        render_system_prompt(prompts=tmp_path)
    _refused_unread(str(info.value), tmp_path / "system.md", "system prompt")

    template = tmp_path / "findmilk.md"
    sparse(template, MAX_PROMPT_BYTES + 1)
    with pytest.raises(PromptError) as info:
        parse_template(template)
    _refused_unread(str(info.value), template, "state prompt template")

    (tmp_path / "fewshot").mkdir()
    fewshot = tmp_path / "fewshot" / "default.toml"
    sparse(fewshot, MAX_PROMPT_BYTES + 1)
    with pytest.raises(ClusterDefinitionError) as info:
        fewshot_messages("findmilk", prompts=tmp_path)
    _refused_unread(str(info.value), fewshot, "few-shot file")


def test_a_prompt_file_at_the_cap_is_read(tmp_path):
    path = tmp_path / "system.md"
    path.write_text("{clusters}" + " " * (MAX_PROMPT_BYTES - len("{clusters}")))
    assert render_system_prompt([], prompts=tmp_path) == " " * (MAX_PROMPT_BYTES - 10)


def test_a_few_shot_file_nested_thousands_deep_is_one_line(tmp_path):
    (tmp_path / "fewshot").mkdir()
    path = tmp_path / "fewshot" / "default.toml"
    path.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ClusterDefinitionError) as info:
        fewshot_messages("findmilk", prompts=tmp_path)
    message = str(info.value)
    assert message.startswith(f"{path}: cannot read few-shot examples: nested deeper")
    assert "\n" not in message
