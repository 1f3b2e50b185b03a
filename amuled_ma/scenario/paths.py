"""Paths of a scenario: safe folder names, the user data folder, recordings by name."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.ranges import found

#: Longest name accepted as a path component.
MAX_NAME_LENGTH = 100

#: What `check_path_component` allows, quoted in its errors.
NAME_RULE = (
    f"1 to {MAX_NAME_LENGTH} characters; no '/', '\\', ':' or '..'; no control "
    "characters; not starting with '.' or '-'; no leading or trailing space"
)


#: Folder name of our files in the XDG data folder (``~/.local/share/amuled-ma``).
USER_DATA_NAME = "amuled-ma"


def user_data_dir() -> Path:
    """The user data folder: ``$AMULED_DATA``, else ``$XDG_DATA_HOME/amuled-ma``."""
    env = os.environ.get("AMULED_DATA")
    if env:
        return Path(os.path.expanduser(env))
    xdg = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(os.path.expanduser(xdg)) / USER_DATA_NAME


def user_recordings_dir() -> Path:
    """Folder of the user's recordings: ``<user_data_dir()>/recordings``."""
    return user_data_dir() / "recordings"


def _component_problem(name: str) -> str | None:
    """What makes ``name`` unsafe as one path component (None: nothing)."""
    if not name:
        return "it is empty"
    if len(name) > MAX_NAME_LENGTH:
        return f"it has {len(name)} characters"
    for bad in ("/", "\\", ":", os.sep, os.altsep or "/"):
        if bad in name:
            return f"it contains {bad!r}"
    if ".." in name:
        return "it contains '..'"
    for ch in name:
        if ord(ch) < 32 or 127 <= ord(ch) < 160:
            return f"it contains the control character U+{ord(ch):04X}"
    if name[0] in ".-":
        return f"it starts with {name[0]!r}"
    if name != name.strip():
        return "it has a leading or trailing space"
    return None


def check_path_component(name: object, where: str) -> str:
    """Return ``name`` if it can be used as one folder name (``where``: file and key, for errors).

    Raises:
        ScenarioError: Not a string, empty, too long, or holding a path separator, ``..``, a
            colon, a control character, a leading ``.``/``-`` or edge spaces.
    """
    if not isinstance(name, str):
        raise ScenarioError(f"{where} expects string, found {found(name)}")
    problem = _component_problem(name)
    if problem:
        raise ScenarioError(
            f"{where} is used as a folder name and must be one safe path component "
            f"({NAME_RULE}); found {name!r}: {problem}"
        )
    return name


def safe_child(root: str | os.PathLike[str], name: str, *, what: str = "name") -> Path:
    """``root / name``, directly inside ``root``: ``name`` is one safe path component.

    Raises:
        ScenarioError: ``name`` fails `check_path_component`.
    """
    return Path(root) / check_path_component(name, what)


def find_recording(
    value: str,
    resolve: Callable[[str], Path],
    *,
    where: str,
    required: bool = False,
    key: str = "[feedback].recording",
) -> Path:
    """Find a recording file by path or by name (see `Scenario.recording_path`)."""
    as_given = resolve(value)
    if not value.strip():
        if required:
            raise ScenarioError(
                f"{where}: {key} is empty; name a recording file, or a "
                "recording by name such as 'findmilk-gpt-4o-mini'"
            )
        return as_given
    names = [Path(value).name]
    if not value.endswith(".json"):
        names.append(f"{names[0]}.json")
    given = [as_given.with_name(n) for n in names]
    env = os.environ.get("AMULED_RECORDINGS")
    cwd = Path.cwd().resolve()
    root = next((d for d in (cwd, *cwd.parents) if (d / ".git").exists()), None)
    folders = [
        ("$AMULED_RECORDINGS", Path(os.path.expanduser(env)) if env else None, "not set"),
        ("the user data folder", user_recordings_dir(), ""),
        (
            "beside the checkout",
            root.parent / "shared" / "amuled-recordings" if root else None,
            "the current directory is in no checkout",
        ),
    ]
    candidates = given + [f / n for _, f, _ in folders if f is not None for n in names]
    for path in candidates:
        if path.is_file():
            return path
    if not required:
        return as_given
    looked = "; ".join(
        [f"as given (relative to the scenario file): {' or '.join(map(str, given))}"]
        + [
            f"{label}: {folder / names[-1] if folder is not None else f'({why})'}"
            for label, folder, why in folders
        ]
    )
    raise ScenarioError(
        f"{where}: {key} {value!r} not found; looked in: {looked}. Fix: "
        "convert the AMULED authors' recordings with 'amuled import authors PATH' "
        "(PATH = a checkout of https://github.com/temetski/moral_agent), or set "
        f"AMULED_RECORDINGS to the folder holding {names[-1]}"
    )
