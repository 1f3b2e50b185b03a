"""Moral clusters as data: cluster files and the prompts sent to them (docs/clusters.md)."""

from amuled_ma.clusters.loader import (
    CREDENCE_INSTRUCTION,
    KINDS,
    Cluster,
    ClusterRegistry,
    Theory,
    default_clusters_dir,
    default_registry,
    load_cluster,
)
from amuled_ma.clusters.plugins import ENTRY_POINT_GROUP, agent_entry_points
from amuled_ma.clusters.prompting import (
    build_messages,
    credence_vector,
    fewshot_messages,
    instruction_text,
    render_system_prompt,
)

__all__ = [
    "CREDENCE_INSTRUCTION",
    "ENTRY_POINT_GROUP",
    "KINDS",
    "Cluster",
    "ClusterRegistry",
    "Theory",
    "agent_entry_points",
    "build_messages",
    "credence_vector",
    "default_clusters_dir",
    "default_registry",
    "fewshot_messages",
    "instruction_text",
    "load_cluster",
    "render_system_prompt",
]
