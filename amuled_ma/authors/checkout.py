"""Import everything usable from a checkout of the authors' repository ``temetski/moral_agent``.

What becomes what, and when an output is left alone or refused: docs/authors.md.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from amuled_ma.authors.caches import ConvertedCache, convert_cache, model_slug, task_of_folder
from amuled_ma.authors.pinned import REPOSITORY
from amuled_ma.authors.policies import (
    AUTHORS_BASE_ITERATIONS,
    AUTHORS_SEED,
    TRAIN_CFG,
    authors_changes,
    build_checkpoint,
    cleanrl_shape,
    last_checkpoint,
    read_cleanrl,
    write_variant,
)
from amuled_ma.errors import AuthorsImportError
from amuled_ma.files.hashing import sha256_file
from amuled_ma.files.safe import check_write_targets, write_text_atomic
from amuled_ma.records.variants import Variant

if TYPE_CHECKING:
    from amuled_ma.scenario import Scenario

#: Sub-folder of ``--runs`` that receives the converted policies.
RUNS_SUBDIR = "authors"
#: Where caches are looked for, relative to the checkout (``models/`` first).
CACHE_GLOBS = ("models/*/*_llm_cache.pickle", "PickleCacheAndBaseModels/*/*_llm_cache.pickle")
#: Suffix of a fused-only cache whose plain name is taken by a full one.
FUSED_ONLY_SUFFIX = "-fused-only"


@dataclass
class Output:
    """One file or folder the import writes (``status``: new, unchanged, replaced, conflict)."""

    kind: str
    source: str
    target: Path
    status: str = "new"
    detail: str = ""


@dataclass
class ImportReport:
    """What `import_authors` did: every output in order, and notes on files not converted."""

    checkout: Path
    recordings_dir: Path
    runs_dir: Path
    outputs: list[Output] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def of_kind(self, kind: str) -> list[Output]:
        """The outputs of one kind (``recording``, ``policy``)."""
        return [o for o in self.outputs if o.kind == kind]


def _status(same: bool, force: bool) -> str:
    """An existing output's status: ``unchanged`` (``same`` content), else by ``force``."""
    return "unchanged" if same else "replaced" if force else "conflict"


def _rel(path: Path, root: Path) -> str:
    return str(path.relative_to(root))  # a glob's match, always below its root


#: One CleanRL policy to convert: task, output folder, file, ``N`` of ``ppo_<N>``, model (None:
#: the base).
PolicyFile = tuple[str, str, Path, int, str | None]


def find_policies(checkout: Path, notes: list[str]) -> list[PolicyFile]:
    """The base and last fine-tuned policy of every run; ``notes`` gets the others."""
    checkout = Path(checkout)
    out: list[PolicyFile] = []
    seen: set[Path] = set()
    for run in sorted(p for p in (checkout / "models").glob(f"*_{AUTHORS_SEED}") if p.is_dir()):
        task = task_of_folder(run.name)
        if task is None:
            continue
        base = run / "base.cleanrl_model"
        if base.is_file():
            out.append((task, "base", base, AUTHORS_BASE_ITERATIONS, None))
            seen.add(base)
        for folder in sorted(run.glob("moral_llm_*")):
            last = last_checkpoint(folder)
            if last is None:
                continue
            model = folder.name[len("moral_llm_") :]
            out.append((task, f"amuled-{model_slug(model)}", last[0], last[1], model))
            seen.update(folder.glob("ppo_*.cleanrl_model"))
    for path in sorted(checkout.glob("**/*.cleanrl_model")):
        if path not in seen:
            notes.append(
                f"not converted: {_rel(path, checkout)} (not a published base or a "
                "moral_llm_<model>/ppo_<N> fine-tune)"
            )
    return out


def _recording_outputs(
    checkout: Path, to: Path, force: bool, notes: list[str], only: Collection[str] | None
) -> list[tuple[Output, ConvertedCache]]:
    planned: list[tuple[Output, ConvertedCache]] = []
    taken: set[str] = set()
    caches = [p for glob in CACHE_GLOBS for p in sorted(checkout.glob(glob)) if p.is_file()]
    for path in caches:  # ``models/`` first
        if only is not None and _rel(path, checkout) not in only:
            continue
        converted = convert_cache(path)
        name = f"{converted.task}-{model_slug(converted.model)}"
        if name in taken:
            if not converted.fused_only:
                notes.append(
                    f"not converted: {_rel(path, checkout)} (a second cache for "
                    f"{name}.json, and it is not fused-only)"
                )
                continue
            name += FUSED_ONLY_SUFFIX
        taken.add(name)
        output = Output(
            "recording", _rel(path, checkout), to / f"{name}.json", detail=converted.detail
        )
        if output.target.exists():
            new = converted.to_json().encode()
            same = output.target.is_file() and output.target.read_bytes() == new
            output.status = _status(same, force)
        planned.append((output, converted))
    return planned


def _existing_source(folder: Path) -> str | None:
    """The source SHA-256 recorded by an imported checkpoint in ``folder``, if any."""
    from amuled_ma.learn.checkpoints import LAST, checkpoint_infos

    infos = checkpoint_infos(folder / LAST)
    authors = (infos or {}).get("authors") or {}
    return authors.get("sha256") if isinstance(authors, dict) else None


class _Converted(NamedTuple):
    """A converted policy: its checkpoint, variant scenario, run scenario, training record."""

    checkpoint: dict[str, Any]
    scenario: Scenario
    run_scenario: Scenario
    training: dict[str, Any]


def _policy_outputs(
    checkout: Path, runs: Path, force: bool, notes: list[str]
) -> list[tuple[Output, _Converted]]:
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.scenario import load_scenario

    planned: list[tuple[Output, _Converted]] = []
    sources = find_policies(checkout, notes)
    bases = {task for task, *_, model in sources if model is None}
    for task, folder, path, iteration, model in sources:
        state = read_cleanrl(path)
        _obs_dim, hidden, _actions = cleanrl_shape(state, path)
        run_scenario = load_scenario(task).changed(authors_changes(hidden))
        scenario = run_scenario
        run_dir = runs / task
        out_dir = run_dir / folder
        rel = _rel(path, checkout)
        sha = sha256_file(path)
        variant, base, what = Variant("base"), None, "base policy"
        if model is not None:
            variant = Variant.finetune("amuled")
            what = f"AMULED fine-tune with {model}, ppo_{iteration}"
            scenario = scenario.replace(
                "feedback",
                recording=f"{task}-{model_slug(model)}",
                model=model,
            )
            base = (run_dir / "base" / LAST).resolve() if task in bases else None
        checkpoint = build_checkpoint(
            state,
            scenario.ppo,
            scenario.finetune,
            scenario_name=scenario.name,
            variant=variant,
            iteration=iteration,
            base_checkpoint=base,
            source={
                "repository": REPOSITORY,
                "file": rel,
                "sha256": sha,
                "checkpoint": iteration if model is not None else None,
                "model": model,
            },
        )
        training = {
            "variant": str(variant),
            "seed": AUTHORS_SEED,
            "iterations": iteration,
            "trained_by": f"the authors' CleanRL scripts ({REPOSITORY})",
            "authors_file": rel,
            "authors_sha256": sha,
        }
        output = Output("policy", rel, out_dir, detail=what)
        if (out_dir / LAST).exists():
            output.status = _status(_existing_source(out_dir) == sha, force)
        planned.append((output, _Converted(checkpoint, scenario, run_scenario, training)))
    return planned


def _run_config_status(run_dir: Path, force: bool) -> str:
    """``new``, ``unchanged`` (an import wrote it), ``replaced`` or ``conflict``."""
    from amuled_ma.errors import AmuledError
    from amuled_ma.experiments.run_folder import CONFIG, read_record

    if not (run_dir / CONFIG).exists():
        return "new"
    try:
        saved = read_record(run_dir, checkpoint=False)
    except AmuledError:
        saved = None
    return _status(saved is not None and saved.authors is not None, force)


def import_authors(
    checkout: str | Path,
    *,
    to: str | Path | None = None,
    runs: str | Path = "runs",
    force: bool = False,
    recordings: bool = True,
    policies: bool = True,
    only: Collection[str] | None = None,
) -> ImportReport:
    """Convert the authors' LLM caches (``only``: these paths in ``checkout``) and policies.

    Raises:
        AuthorsImportError: No authors' files, a file not in their format, or an output that
            exists with other content (nothing written).
        UnsafePathError: An output's place holds a link or a device (nothing written).
        FileWriteError: An output could not be written (a full disk).
        UnsafePickleError: A cache names a global outside the allow-list (nothing ran).
        CheckpointError: A policy cannot be read as weights only, or has another layout.
    """
    from amuled_ma.experiments.run_folder import write_config
    from amuled_ma.learn.checkpoints import LAST
    from amuled_ma.scenario import user_recordings_dir

    checkout = Path(checkout).expanduser()
    if not checkout.is_dir():
        raise AuthorsImportError(
            f"{checkout}: not a folder; give a checkout of {REPOSITORY} "
            "(git clone it, then 'amuled import authors PATH')"
        )
    report = ImportReport(
        checkout=checkout,
        recordings_dir=Path(to).expanduser() if to else user_recordings_dir(),
        runs_dir=Path(runs).expanduser() / RUNS_SUBDIR,
    )
    caches = (
        _recording_outputs(checkout, report.recordings_dir, force, report.notes, only)
        if recordings
        else []
    )
    nets = _policy_outputs(checkout, report.runs_dir, force, report.notes) if policies else []
    if not caches and not nets:
        wanted = [*CACHE_GLOBS] if recordings else []
        if policies:
            wanted += [
                f"models/<Env>_{AUTHORS_SEED}/base.cleanrl_model",
                "moral_llm_<model>/ppo_<N>.cleanrl_model",
            ]
        raise AuthorsImportError(
            f"{checkout}: none of the authors' files found (looked for {', '.join(wanted)}); "
            f"give the root of a checkout of {REPOSITORY}"
        )
    run_configs: dict[Path, Scenario] = {}
    for output, item in nets:
        run_configs.setdefault(output.target.parent, item.run_scenario)
    config_status = {d: _run_config_status(d, force) for d in run_configs}
    conflicts = [o for o, _ in [*caches, *nets] if o.status == "conflict"]
    conflicts += [
        Output("run", "", d / "config.json", "conflict")
        for d, status in config_status.items()
        if status == "conflict"
    ]
    if conflicts:
        shown = "; ".join(f"{o.target} (from {o.source})" for o in conflicts[:5])
        more = f" and {len(conflicts) - 5} more" if len(conflicts) > 5 else ""
        raise AuthorsImportError(
            f"refusing to overwrite {len(conflicts)} existing output(s) with other content: "
            f"{shown}{more}; nothing was written. Move them away, choose other folders "
            "(--to, --runs), or replace them with --force"
        )
    # a link or a device in an output's place is refused before anything is written
    check_write_targets(o.target for o, _ in caches)
    check_write_targets(o.target / name for o, _ in nets for name in (LAST, TRAIN_CFG))
    report.outputs += [output for output, _ in [*caches, *nets]]
    for output, converted in caches:
        if output.status != "unchanged":
            output.target.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(output.target, converted.to_json())
    for output, item in nets:
        if output.status != "unchanged":
            write_variant(
                output.target, item.checkpoint, item.scenario.to_dict(), training=item.training
            )
    # each run's config.json (what ``amuled evaluate`` reads) holds the base scenario
    source = {"repository": REPOSITORY, "checkout": str(checkout.resolve())}
    for run_dir, scenario in run_configs.items():
        if config_status[run_dir] != "unchanged":
            write_config(run_dir, scenario.to_dict(), {"authors": source, "seeds": [AUTHORS_SEED]})
    return report
