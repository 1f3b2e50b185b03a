"""Where a belief comes from: `sources`, `replies` (parsing, the one check), `store`."""

from amuled_ma.beliefs.replies.parsing import ParsedBelief, belief_schema, parse_belief, uniform
from amuled_ma.beliefs.replies.validate import (
    SUM_TOLERANCE,
    InvalidBeliefError,
    check_belief,
    checked_result,
    validate_belief,
)
from amuled_ma.beliefs.sources.registry import make_source, register_source, source_kinds
from amuled_ma.beliefs.sources.replay import ReplaySource
from amuled_ma.beliefs.sources.rules import RulesSource, ScriptedSource
from amuled_ma.beliefs.types import STATUSES, BeliefRequest, BeliefResult, BeliefSource

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
