"""Belief sources (Ollama, replay, rules), reply parsing, and the persistent belief store."""

from amuled_ma.beliefs.types import BeliefRequest, BeliefResult, BeliefSource

__all__ = ["BeliefRequest", "BeliefResult", "BeliefSource"]
