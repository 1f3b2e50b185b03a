"""Render the paper's state prompts from the templates in ``prompts/tasks/<task>.md``.

Template syntax (``{name:group}`` fragments, their conditions): docs/tasks.md, "State prompts".
"""

from __future__ import annotations

import functools
import operator
import re
import string
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from amuled_ma.errors import PromptError
from amuled_ma.files.resources import MAX_PROMPT_BYTES, prompts_dir, read_text
from amuled_ma.tasks.names import BUILTIN_TASKS, canonical_name, task_entry_points

__all__ = ["StateTemplate", "load_template", "render_state_prompt", "template_path"]

_HEADING = re.compile(r"^(#{2,3})\s+(.+?)\s*$")
_FENCE = re.compile(r"^```[\w-]*\s*$")
_CONDITION = re.compile(
    r"^(?P<group>[A-Za-z_]\w*)\s+(?:(?P<op>==|!=|<=|>=|<|>)\s*(?P<value>-?\d+(?:\.\d+)?)"
    r"|in\s+(?P<low>-?\d+(?:\.\d+)?)\s*\.\.\s*(?P<high>-?\d+(?:\.\d+)?)"
    r"|(?P<otherwise>otherwise))$"
)
_OPS: dict[str, Callable[[float, float], bool]] = {
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}


#: A template group's conditional text: whether a value selects it, and the text.
_Fragment = tuple[Callable[[Any], bool], str]


@dataclass(frozen=True)
class StateTemplate:
    """A parsed ``prompts/tasks/<task>.md`` file; ``fragments`` by group, in file order."""

    path: Path
    prompt: str
    fragments: dict[str, tuple[_Fragment, ...]]

    def render(self, variables: Mapping[str, Any]) -> str:
        """Fill the template with ``variables``.

        Raises:
            ValueError: A variable is missing, or no fragment matches a value.
        """
        return self._fill(self.prompt, variables, depth=0)

    def _fill(self, text: str, variables: Mapping[str, Any], depth: int) -> str:
        if depth > 8:
            raise PromptError(f"{self.path}: fragments nest too deeply")
        out: list[str] = []
        formatter = string.Formatter()
        for literal, field, spec, conversion in formatter.parse(text):
            out.append(literal)
            if field is None:
                continue
            if field not in variables:
                raise PromptError(
                    f"variables: missing {field!r}, needed by {self.path} "
                    f"(got {', '.join(sorted(variables)) or 'none'})"
                )
            value = variables[field]
            if spec and spec in self.fragments:
                fragment = self._select(spec, field, value)
                out.append(self._fill(fragment, {**variables, "value": value}, depth + 1))
                continue
            out.append(format(formatter.convert_field(value, conversion), spec or ""))
        return "".join(out)

    def _select(self, group: str, field: str, value: object) -> str:
        for test, text in self.fragments[group]:
            if test(value):
                return text
        raise PromptError(
            f"variables: {field}={value!r} matches no fragment of group {group!r} in {self.path}"
        )


def _condition(match: re.Match[str]) -> Callable[[Any], bool]:
    if match["otherwise"]:
        return lambda value: True
    if match["op"]:
        op, ref = _OPS[match["op"]], float(match["value"])
        return lambda value: op(float(value), ref)
    low, high = float(match["low"]), float(match["high"])
    return lambda value: low <= float(value) <= high


def parse_template(path: Path) -> StateTemplate:
    """Parse one template file.

    Raises:
        PromptError: ``path`` cannot be read, is larger than `MAX_PROMPT_BYTES` or is not
            UTF-8; it has no ``## prompt`` block or a malformed fragment heading.
    """
    text = read_text(path, "state prompt template", PromptError, max_bytes=MAX_PROMPT_BYTES)
    rows = iter(text.splitlines())
    prompt: str | None = None
    fragments: dict[str, list[_Fragment]] = {}
    heading: str | None = None
    level = 0
    for line in rows:
        found = _HEADING.match(line)
        if found:
            level, heading = len(found[1]), found[2]
        elif _FENCE.match(line) and heading is not None:
            block = []
            for row in rows:
                if row.rstrip() == "```":
                    break
                block.append(row)
            else:
                raise PromptError(f"{path}: unclosed code block under heading {heading!r}")
            body = "\n".join(block)
            if level == 2 and heading.lower() == "prompt":
                prompt = body
            elif level == 3:
                match = _CONDITION.match(heading)
                if match is None:
                    raise PromptError(
                        f"{path}: fragment heading {heading!r} is not '<group> <condition>' "
                        "(== v, != v, < v, <= v, > v, >= v, in a..b, otherwise)"
                    )
                fragments.setdefault(match["group"], []).append((_condition(match), body))
            heading = None
    if prompt is None:
        raise PromptError(f"{path}: no fenced block under a '## prompt' heading")
    return StateTemplate(path, prompt, {k: tuple(v) for k, v in fragments.items()})


def template_path(task_name: str) -> Path:
    """Return ``prompts/tasks/<task>.md``, or the ``prompt_template`` of an entry-point task."""
    name = canonical_name(task_name)
    if name in BUILTIN_TASKS:
        return prompts_dir() / "tasks" / f"{name}.md"
    own = getattr(task_entry_points()[name].load(), "prompt_template", None)  # its class says
    if own is None:
        raise PromptError(
            f"task {name!r}: its class sets no prompt_template; give the path of its state "
            "prompt template (docs/tasks.md, 'Adding a task')"
        )
    return Path(own)


@functools.lru_cache(maxsize=16)
def _load_cached(path: Path, mtime_ns: int) -> StateTemplate:
    return parse_template(path)


def load_template(task_name: str) -> StateTemplate:
    """Return the parsed template of ``task_name`` (cached until the file changes).

    Raises:
        ValueError: Unknown task.
        PromptError: The template file is missing.
    """
    path = template_path(task_name)
    if not path.is_file():
        raise PromptError(
            f"{path}: the state prompt template of task {task_name!r} is missing; reinstall "
            "amuled-ma, or restore prompts/tasks/ from the repository"
        )
    return _load_cached(path, path.stat().st_mtime_ns)


def render_state_prompt(task_name: str, variables: Mapping[str, Any]) -> str:
    """Render the state prompt of one state, as the paper's authors sent it (no credence sentence).

    Raises:
        ValueError: Unknown task, missing variable, or a value no fragment accepts.
    """
    return load_template(task_name).render(variables)
