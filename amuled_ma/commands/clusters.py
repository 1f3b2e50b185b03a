"""``amuled clusters list``: the moral-cluster agents and code-backed agents available."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled clusters`` and its ``list`` sub-command."""
    parser = subparsers.add_parser(
        "clusters",
        help="list the moral-cluster agents (TOML files) and code-backed agents",
        description=(
            "Moral clusters are TOML files: the shipped ones (prompts/clusters) plus any "
            "--clusters-dir. Code-backed agents come from the 'amuled_ma.agents' entry-point "
            "group. See docs/clusters.md."
        ),
    )
    actions = parser.add_subparsers(dest="clusters_action", metavar="ACTION")
    listing = actions.add_parser(
        "list",
        help="list every cluster agent with its kind, file and theories",
        description="List every cluster agent (shipped and user) and code-backed agent.",
    )
    listing.add_argument("--json", action="store_true", help="print JSON instead of a table")
    listing.set_defaults(handler=list_clusters)
    show = actions.add_parser(
        "show",
        help="print the chat a cluster agent receives (system prompt, few-shot, state)",
        description=(
            "Print the three blocks sent to one cluster agent: the system prompt, the few-shot "
            "examples of the task, and the state prompt (a placeholder unless --state is given) "
            "ending with the agent's credence sentence."
        ),
    )
    show.add_argument("name", help="cluster name or alias")
    show.add_argument("--task", default="findmilk", help="task (selects the few-shot file)")
    show.add_argument("--state", default="<STATE PROMPT>", help="state prompt text")
    show.set_defaults(handler=show_cluster)
    for sub in (listing, show):
        sub.add_argument(
            "--clusters-dir",
            action="append",
            type=Path,
            default=[],
            metavar="DIR",
            help="a directory of extra cluster TOML files (repeatable; later ones win)",
        )
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)


def list_clusters(args: argparse.Namespace) -> int:
    """Print the clusters of the shipped and user directories, and the plug-in agents."""
    from amuled_ma.clusters import ClusterRegistry, agent_entry_points, credence_vector

    registry = ClusterRegistry.load(args.clusters_dir)
    panel = registry.panel()
    plugins = agent_entry_points()
    rows: list[dict[str, Any]] = []
    for cluster in registry.all():
        vector = credence_vector(cluster, panel, registry=registry)
        rows.append(
            {
                "name": cluster.name,
                "kind": cluster.kind,
                "title": cluster.title,
                "aliases": list(cluster.aliases),
                "theories": [t.name for t in cluster.theories],
                "credences": vector,
                "file": str(cluster.path),
            }
        )
    overridden = [
        {"name": o.name, "replaced": str(o.old_path), "by": str(o.new_path)}
        for o in registry.overridden
    ]
    if args.json:
        entry_points = {name: ep.value for name, ep in sorted(plugins.items())}
        out = {"clusters": rows, "agents": entry_points, "overridden": overridden}
        print(json.dumps(out, indent=2))
        return 0
    for o in overridden:
        print(f"note: {o['by']} overrides the cluster {o['name']!r} of {o['replaced']}")
    width = max(len(r["name"]) for r in rows) if rows else 4
    print(f"{'NAME':<{width}}  {'KIND':<10}  {'TITLE':<34}  FILE")
    for row in rows:
        print(f"{row['name']:<{width}}  {row['kind']:<10}  {row['title']:<34}  {row['file']}")
        if row["theories"]:
            print(f"{'':<{width}}  {'':<10}  theories: {', '.join(row['theories'])}")
        if row["kind"] == "mixture" and row["credences"]:
            mix = ", ".join(f"{k}: {v}" for k, v in row["credences"].items() if v)
            print(f"{'':<{width}}  {'':<10}  credences: {mix}")
    print()
    if plugins:
        print("Code-backed agents (entry-point group 'amuled_ma.agents'):")
        for name, ep in sorted(plugins.items()):
            print(f"  {name:<{width}}  {ep.value}")
    else:
        print("Code-backed agents (entry-point group 'amuled_ma.agents'): none installed")
    return 0


def show_cluster(args: argparse.Namespace) -> int:
    """Print the messages one cluster agent receives."""
    from amuled_ma.clusters import ClusterRegistry, build_messages
    from amuled_ma.tasks import canonical_name

    canonical_name(args.task)  # an unknown task is an error, not the default few-shot file
    registry = ClusterRegistry.load(args.clusters_dir)
    messages = build_messages(args.name, args.task, args.state, registry=registry)
    for role, content in messages:
        print(f"----- {role} -----")
        print(content)
    return 0
