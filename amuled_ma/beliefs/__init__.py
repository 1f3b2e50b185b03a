"""Belief sources (Ollama, replay, rules), reply parsing, the belief check, and the store.

See ``docs/beliefs.md``. The Ollama source is imported on demand
(``make_source("ollama", ...)`` or ``amuled_ma.beliefs.ollama``) so that importing this
package stays light.
"""

from amuled_ma.beliefs.parsing import ParsedBelief, belief_schema, parse_belief, uniform
from amuled_ma.beliefs.replay import ReplaySource
from amuled_ma.beliefs.rules import RulesSource, ScriptedSource
from amuled_ma.beliefs.sources import make_source, register_source, source_kinds
from amuled_ma.beliefs.types import STATUSES, BeliefRequest, BeliefResult, BeliefSource
from amuled_ma.beliefs.validate import (
    SUM_TOLERANCE,
    InvalidBeliefError,
    check_belief,
    checked_result,
    validate_belief,
)

__all__ = [
    "STATUSES",
    "SUM_TOLERANCE",
    "BeliefRequest",
    "BeliefResult",
    "BeliefSource",
    "InvalidBeliefError",
    "ParsedBelief",
    "ReplaySource",
    "RulesSource",
    "ScriptedSource",
    "belief_schema",
    "check_belief",
    "checked_result",
    "make_source",
    "parse_belief",
    "register_source",
    "source_kinds",
    "uniform",
    "validate_belief",
]
