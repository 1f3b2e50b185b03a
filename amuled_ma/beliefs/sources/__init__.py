"""Belief sources by kind (Ollama, replay, rules, terminal, policy, routed) and their registry."""
