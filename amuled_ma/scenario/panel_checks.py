"""``[feedback].clusters`` and ``[feedback].fusion``: checked when the scenario is read."""

from __future__ import annotations

import difflib
import re
from collections.abc import Mapping, Sequence
from types import MappingProxyType

from amuled_ma.errors import ScenarioError
from amuled_ma.scenario.names import identity_key, odd_character

#: The fusion rules a scenario may name, and whether each takes a parameter after ``:``:
#: the rules `amuled_ma.fusion` ships, and every rule registered since
#: (`amuled_ma.fusion.register_rule` calls `allow_fusion_rule`;
#: ``tests/test_scenario_panel_checks.py`` holds the two equal).
_FUSION_RULES: dict[str, bool] = {
    "bjs-dst": False,
    "mean": False,
    "max": False,
    "vote": False,
    "single": True,
    "mec": False,
    "nash-vote": False,
    "variance-vote": False,
    "borda": False,
}
FUSION_RULES: Mapping[str, bool] = MappingProxyType(_FUSION_RULES)
#: The rules of `FUSION_RULES` that take a member prior (``[feedback].weights``):
#: ``bjs-dst`` multiplies Xiao's credibility by it, the moral-uncertainty rules read it as
#: their credences (registered with ``takes_prior``; the same test holds the two equal).
_PRIOR_RULES: set[str] = {"bjs-dst", "mec", "nash-vote", "variance-vote", "borda"}
#: Longest cluster name [characters] (a file name of the cluster folder).
MAX_CLUSTER_NAME = 100


def allow_fusion_rule(name: str, takes_param: bool = False, takes_prior: bool = False) -> None:
    """Let scenarios name a fusion rule registered in code (``name``, or ``name:<param>``)."""
    _FUSION_RULES[name] = takes_param
    if takes_prior:
        _PRIOR_RULES.add(name)
    else:
        _PRIOR_RULES.discard(name)


def forget_fusion_rule(name: str) -> None:
    """Stop scenarios naming a rule no longer registered (none of that name: nothing)."""
    _FUSION_RULES.pop(name, None)
    _PRIOR_RULES.discard(name)


def prior_rules() -> tuple[str, ...]:
    """The fusion rules that take a member prior, in the order of `FUSION_RULES`."""
    return tuple(n for n in FUSION_RULES if n in _PRIOR_RULES)


def check_clusters(value: list[str], source: str) -> list[str]:
    """Return ``[feedback].clusters`` if it is a panel: non-empty, distinct, visible names.

    Raises:
        ScenarioError: No name; a name empty, too long or odd; two of one `identity_key`.
    """
    head = f"{source}: key [feedback].clusters"
    if not value:
        raise ScenarioError(
            f"{head} expects at least one moral cluster, found []; e.g. --set "
            "\"feedback.clusters=['care','virtue']\" (amuled clusters list shows them)"
        )
    seen: dict[str, str] = {}
    for name in value:
        if not name.strip() or len(name) > MAX_CLUSTER_NAME:
            raise ScenarioError(
                f"{head} expects names of 1 to {MAX_CLUSTER_NAME} characters, found "
                f"{name[:40]!r}" + ("..." if len(name) > 40 else "")
            )
        odd = odd_character(name)
        if odd is not None:
            raise ScenarioError(
                f"{head} expects names of visible characters, found {name!r} holding {odd}, "
                "which prints as nothing or changes how another character looks; remove it"
            )
        key = identity_key(name)
        if key in seen:
            raise ScenarioError(
                f"{head} names one cluster twice: {seen[key]!r} and {name!r} read alike "
                "(names compare ignoring case, width, '_', '-' and look-alike letters); "
                "keep one"
            )
        seen[key] = name
    return value


def check_fusion(value: str, clusters: Sequence[str] | None, source: str) -> str:
    """Return ``[feedback].fusion`` if it names a rule of `FUSION_RULES` as it takes.

    Raises:
        ScenarioError: An unknown rule, a parameter missing or unexpected, or a ``single:<i>``
            index outside ``clusters`` (negative from the end).
    """
    head = f"{source}: key [feedback].fusion"
    name, sep, param = value.partition(":")
    takes = FUSION_RULES.get(name)
    if takes is None:
        close = difflib.get_close_matches(name, list(FUSION_RULES), n=1)
        rules = ", ".join(f"{n}:<i>" if p else n for n, p in FUSION_RULES.items())
        raise ScenarioError(
            f"{head} expects a fusion rule, found {value[:60]!r}"
            f"{f' (did you mean {close[0]!r}?)' if close else ''}; "
            f"the rules: {rules} (docs/fusion.md)"
        )
    if takes and not sep:
        raise ScenarioError(f"{head} expects {name}:<i> (a member's index), found {value!r}")
    if not takes and sep:
        raise ScenarioError(f"{head}: rule {name!r} takes no parameter, found {value!r}")
    if name == "single" and clusters is not None:
        k = len(clusters)
        if not re.fullmatch(r"-?[0-9]{1,9}", param) or not -k <= int(param) < k:
            raise ScenarioError(
                f"{head} expects single:<i> with i an integer in [{-k}, {k - 1}] (the index of "
                f"a member of [feedback].clusters, {', '.join(clusters)}), found {value[:60]!r}"
            )
    return value
