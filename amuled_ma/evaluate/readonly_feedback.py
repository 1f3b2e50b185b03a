"""A variant's feedback opened to look at a run, with the run's belief store read-only."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from amuled_ma.beliefs.types import BeliefResult
from amuled_ma.errors import AmuledError

if TYPE_CHECKING:
    from amuled_ma.beliefs.store.service import StoreItem
    from amuled_ma.deliberation.feedback_base import Feedback
    from amuled_ma.deliberation.plan import PanelPlan


class ReadOnlyStore:
    """The run's belief store (SQLite ``mode=ro``; a missing file reads empty) behind a feedback."""

    def __init__(self, path: str | Path | None) -> None:
        from amuled_ma.beliefs.store.database import BeliefStore

        self.path = Path(path) if path else None
        self.store = (
            BeliefStore(self.path, read_only=True)
            if self.path is not None and self.path.is_file()
            else None
        )

    def lookup(self, keys: Sequence[str]) -> dict[str, BeliefResult]:
        """Cached answers (``ok``/``repaired`` rows) of ``keys`` in the run's store."""
        return self.store.lookup(keys) if self.store is not None else {}

    def rows(self, keys: Sequence[str]) -> dict[str, Any]:
        """Every row of ``keys``, answers or not (an abstention's raw reply is kept)."""
        return {} if self.store is None else self.store.get_many(keys, cacheable_only=False)

    def put_many(self, items: Sequence[StoreItem]) -> int:
        """Write nothing (looking at a run never changes it)."""
        return 0

    def close(self) -> None:
        """Close the read-only connection."""
        if self.store is not None:
            self.store.close()


def open_feedback(
    plan: PanelPlan, store: str, run_dir: Path | None
) -> tuple[Feedback, ReadOnlyStore]:
    """``(feedback, store)``: a plan's feedback built as training does, the run's store read-only.

    ``store`` is relative to ``run_dir`` (None: no store); an Ollama source still asks its server.
    """
    from amuled_ma.deliberation.build import build_feedback

    run = Path(run_dir) if run_dir is not None else None
    read_only = ReadOnlyStore(run / store if run is not None else None)  # an absolute store wins
    try:
        return build_feedback(plan, read_only, cache_dir=run), read_only
    except BaseException:
        read_only.close()
        raise


def describe_feedback(feedback: Feedback | None) -> str:
    """Where a feedback's beliefs come from, in words (for headers)."""
    from amuled_ma.deliberation.summaries import describe_identity

    source = getattr(feedback, "source", None)
    if source is not None:
        try:
            members = getattr(source, "members", None)
            if members:
                parts = []
                for member, agents in members:
                    who = ", ".join(agents) if agents else "the others"
                    parts.append(f"{who}: {describe_identity(member.identity())}")
                return "; ".join(parts)
            return describe_identity(source.identity())
        except (AmuledError, OSError, AttributeError):
            return str(getattr(source, "name", "source"))
    recording = getattr(feedback, "recording", None)
    if recording is not None:
        return f"replay ({Path(recording.path).name}, fused beliefs only)"
    return str(getattr(feedback, "name", "feedback"))
