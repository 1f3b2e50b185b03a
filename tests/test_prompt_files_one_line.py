"""Prompt files that are not UTF-8 are one line naming the file (docs/trust.md, issue 24).

The last input of the trust table without a test of its failure line: ``system.md`` and a
state prompt template, as a ``prompts/`` folder given in place of the shipped one.
"""

from __future__ import annotations

import pytest

from amuled_ma.clusters.prompting import render_system_prompt
from amuled_ma.errors import PromptError
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
