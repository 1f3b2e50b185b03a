"""What the report says each variant is, from the run records (or ``results.json`` without one)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

from amuled_ma.evaluate.numbers import markdown_table
from amuled_ma.evaluate.results import Results
from amuled_ma.records.run_record import PanelRecord, RunRecord
from amuled_ma.records.variants import Variant

#: The KL-anchor recipes a record names, by the text a panel entry holds.
_RECIPES: dict[str, Literal["equation", "authors"]] = {"equation": "equation", "authors": "authors"}
#: The feedbacks of a demonstrator (no panel of LLM agents).
_DEMONSTRATORS = {"human": "the synthetic human", "human:rules": "our human rule"}


def variant_records(
    results: Results, records: Mapping[str, RunRecord] | None = None
) -> dict[str, RunRecord | None]:
    """``{variant: record}``: its first seed folder's, else one from its ``panel`` entry or None."""
    records = records or {}
    out: dict[str, RunRecord | None] = {}
    for name, entry in results.variants.items():
        found = records.get(name)
        if found is None:
            found = next((r for r in records.values() if r.name == name), None)
        if found is None and (panel := entry.panel) is not None:  # what results.json says
            feedback = panel.feedback or "amuled"
            found = RunRecord(
                variant=Variant.finetune(feedback),
                name=name,
                seed=panel.seed,
                training={"inputs": panel.inputs} if panel.inputs else None,
                panel=PanelRecord(
                    feedback=feedback,
                    members=list(panel.agents or []),
                    agent_sources=dict(panel.agent_sources or {}),
                    **panel.model_dump(
                        include={"source", "model", "recording", "fusion", "distill"}
                    ),
                ),
                recipe=_RECIPES.get(panel.recipe or ""),
                lambda_kl=panel.lambda_kl,
                base_checkpoint=panel.base_checkpoint,
                iterations_planned=panel.iterations,
            )
        out[name] = found
    return out


def finetune_names(results: Results, described: Mapping[str, RunRecord | None]) -> list[str]:
    """The fine-tunes: by their record, else by a ``finetune*`` name."""
    out = []
    for name in results.variants:
        record = described.get(name)
        tuned = record.finetuning if record is not None and record.variant else None
        if tuned or (tuned is None and name.startswith("finetune")):
            out.append(name)
    return out


def iterations_text(record: RunRecord) -> str:
    """``20``, or ``interrupted at 0 of 20``, ``failed at 3 of 20``."""
    planned = record.iterations_planned
    done = record.iterations_done
    if record.unfinished:
        shown = "?" if done is None else str(done)
        return f"{record.state} at {shown} of {'?' if planned is None else planned}"
    value = done if done is not None else planned
    return "-" if value is None else str(value)


def unfinished_lines(described: Mapping[str, RunRecord | None]) -> list[str]:
    """One line per variant whose training was interrupted or failed."""
    lines = []
    for name, record in described.items():
        if record is not None and record.unfinished:
            lines.append(
                f"- **{name} is {record.state} at iteration {record.iterations_done} of "
                f"{record.iterations_planned}**: its checkpoint is unfinished, and what is "
                "evaluated is that checkpoint (resume it with `--resume`)."
            )
    return lines


def imported_table(described: Mapping[str, RunRecord | None]) -> str:
    """A Markdown table of the policies imported from the paper's authors (``""``: none)."""
    rows = []
    for name, record in described.items():
        if record is None or not record.imported or record.authors is None:
            continue
        what = "fine-tune" if record.finetuning else "base policy"
        model = record.panel.model if record.panel is not None else None
        if record.finetuning and model:
            what += f" on the authors' LLM panel ({model})"
        iteration = record.authors.checkpoint
        if iteration is None:
            iteration = record.iterations_done
        rows.append(
            [name, what, f"`{record.authors.file}`", str(iteration), f"`{record.authors.sha256}`"]
        )
    head = ["variant", "what", "the authors' file", "checkpoint iteration", "sha256"]
    return markdown_table(head, rows)


def _base_label(checkpoint: str | None) -> str:
    """The base a fine-tune started from: its variant folder, or where it lives."""
    if not checkpoint:
        return "-"
    folder = Path(checkpoint).parent
    return f"`{folder}`" if folder.parent.name and "authors" in folder.parts else folder.name


def agents_text(panel: PanelRecord) -> str:
    """Who answered: the panel's members, a demonstrator, or the recorded fused belief."""
    if panel.feedback in _DEMONSTRATORS:
        return _DEMONSTRATORS[panel.feedback]
    if panel.fused_only:
        return "none asked: the recorded fused belief"
    if panel.feedback.startswith(("cluster:", "moral")):
        return panel.feedback
    return ", ".join(panel.members) or "-"


def source_text(panel: PanelRecord) -> str:
    """Where the beliefs came from, in words."""
    source = panel.source or ""
    if panel.fused_only:
        text = f"replay of `{panel.recording}`, fused beliefs only (the authors' recording)"
    elif source == "replay":
        text = f"replay of `{panel.recording}`"
    elif source in ("ollama", "openai", "llm") and panel.model:
        text = f"{source}, model `{panel.model}`"
    elif source == "rules":
        text = "rules (the task's rule; the clusters' text is not read)"
    else:
        text = source
    if panel.agent_sources:
        text += "; " + ", ".join(
            f"{agent}: {spec.get('source', '?')}"
            + (f" `{spec['recording']}`" if spec.get("recording") else "")
            + (f" `{spec['model']}`" if spec.get("model") and _asks_model(spec) else "")
            + (" (the task's rule; its text is not read)" if spec.get("source") == "rules" else "")
            for agent, spec in panel.agent_sources.items()
        )
    return text


def _asks_model(spec: Mapping[str, Any]) -> bool:
    """Whether an agent's source asks a model (not a recording, a rule or a person)."""
    return spec.get("source") not in ("replay", "rules", "terminal", "policy")


def fusion_text(panel: PanelRecord) -> str:
    """The fusion rule, or what stood in for it."""
    if panel.fused_only:
        return "the authors' (recorded)"
    if panel.weights:
        return f"{panel.fusion or '-'}, members weighted by `{panel.weights}`"
    return panel.fusion or "-"


def panels_table(described: Mapping[str, RunRecord | None]) -> str:
    """A Markdown table of what each fine-tune trained here was trained on, row by row."""
    rows = []
    for name, record in described.items():
        if record is None or record.panel is None or record.imported:
            continue
        panel = record.panel
        rows.append(
            [
                name,
                panel.feedback,
                record.recipe or "-",
                "-" if record.lambda_kl is None else f"{record.lambda_kl:g}",
                iterations_text(record),
                agents_text(panel),
                source_text(panel) or "-",
                fusion_text(panel),
                _base_label(record.base_checkpoint),
            ]
        )
    head = [
        "variant",
        "feedback",
        "recipe",
        "lambda_KL",
        "iterations",
        "agents",
        "source",
        "fusion",
        "base",
    ]
    return markdown_table(head, rows)


def _joined(values: Iterable[Any], several: str = " (per variant)") -> str:
    distinct = dict.fromkeys(v for v in values if v is not None and v != "")
    found = [f"{v:g}" if isinstance(v, float) else str(v) for v in distinct]
    if not found:
        return ""
    return found[0] if len(found) == 1 else ", ".join(found) + several


def settings_table(
    results: Results, run: RunRecord | None = None, records: Mapping[str, RunRecord] | None = None
) -> str:
    """The report's header: what was run, as a two-column Markdown table.

    Fine-tune settings come from each fine-tune's record (``(per variant)`` when they differ);
    recipe and lambda_KL only for fine-tunes trained here. ``run`` may be None.
    """
    described = variant_records(results, records)
    tunes = finetune_names(results, described)
    trained = [r for n in tunes if (r := described.get(n)) is not None and not r.imported]
    imported = [r for r in described.values() if r is not None and r.imported]
    scenario = (run.scenario if run is not None else None) or {}
    rows: list[tuple[str, str]] = [
        ("task", f"`{results.task}` (scenario `{results.scenario}`)"),
        (
            "evaluation",
            f"{results.episodes} episodes per variant and mode, seeds from "
            f"{results.seed}, {100 * results.confidence:g}% Student-t intervals",
        ),
    ]
    seeds = run.seeds if run is not None else None
    if seeds:
        rows.append(("training seeds", f"{len(seeds)}: {', '.join(str(s) for s in seeds)}"))
    else:
        most = max((m.n_seeds for v in results.variants.values() for m in v.modes().values()),
                   default=1)  # fmt: skip
        rows.append(("training seeds", str(most)))
    base = scenario.get("base") or {}
    if base.get("total_steps") and not any(not r.finetuning for r in imported):
        rows.append(("base training", f"{int(base['total_steps']):,} env steps per policy"))
    if imported:
        rows.append((
            "imported policies",
            "; ".join(
                f"{r.name}: `{r.authors.file}`, checkpoint iteration "
                f"{r.authors.checkpoint if r.authors.checkpoint is not None else r.iterations_done}"
                for r in imported
                if r.authors is not None
            ) + " (the authors' CleanRL policies, `amuled import authors`)",
        ))  # fmt: skip
    if run is not None and run.ablation:
        rows.append(("ablation", f"`{run.ablation}`"))
    if trained:
        rows.append(("fine-tune recipe", _joined(r.recipe for r in trained)))
        rows.append(("lambda_KL", _joined(r.lambda_kl for r in trained)))
        rows.append(("fine-tune iterations", _joined(iterations_text(r) for r in trained)))
    rows = [(label, value) for label, value in rows if value]
    judged = [r for r in trained if r.panel is not None and r.panel.feedback not in _DEMONSTRATORS]
    if judged:
        amuled = [r for r in judged if r.panel and r.panel.feedback == "amuled"] or judged
        panels = [r.panel for r in amuled if r.panel is not None]
        if all(p.fused_only for p in panels):
            rows.append((
                "panel",
                "none asked: the fused beliefs the authors recorded were replayed as they are "
                "(no agent answered, no fusion of ours)",
            ))  # fmt: skip
        else:
            shown = {
                r.name or "?": ", ".join(r.panel.members)
                + (f"; fusion `{r.panel.fusion}`" if r.panel.fusion else "")
                for r in amuled
                if r.panel is not None and not r.panel.fused_only
            }
            if len(set(shown.values())) == 1:
                rows.append(("panel", next(iter(shown.values()))))
            else:  # each fine-tune its own panel, by name
                rows.append(("panel", "; ".join(f"{n}: {t}" for n, t in shown.items())))
        rows.append((
            "beliefs from", _joined((source_text(r.panel) for r in judged if r.panel), "")
        ))  # fmt: skip
        recordings = []  # `file` sha256 `hash` of every recording the fine-tunes replayed
        for record in judged:
            panel = record.panel
            assert panel is not None
            inputs = (record.training or {}).get("inputs") or {}
            for key, digest in inputs.items():
                if key == "recording_sha256":
                    name = panel.recording
                    if panel.fused_only:
                        name = f"{name}` (fused beliefs only) `"
                elif key.startswith("recording_sha256[") and key.endswith("]"):
                    agent = key[len("recording_sha256[") : -1]
                    name = (
                        f"{(panel.agent_sources.get(agent) or {}).get('recording', '?')} ({agent})"
                    )
                else:
                    continue
                recordings.append(f"`{name}` sha256 `{digest}`".replace(" ``", ""))
            if panel.source == "replay" and "recording_sha256" not in inputs:
                recordings.append(f"`{panel.recording}` (no hash recorded)")
        listed = "; ".join(dict.fromkeys(recordings))  # a replay is listed, hashed or not
        rows.append(("recording", listed or "none (no fine-tune replayed a recording)"))
    return markdown_table(["setting", "value"], rows)
