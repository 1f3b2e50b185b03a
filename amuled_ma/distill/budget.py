"""The budget of asked states: ``asked <= cap(visited)`` after every batch (docs/distill.md)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from fractions import Fraction
from typing import Any

from amuled_ma.errors import AmuledError


class BudgetExceeded(AmuledError, RuntimeError):
    """More distinct states were to be asked than the budget allows (a bug, never expected)."""


def check_budget(budget: object, where: str = "[feedback.distill].budget") -> float | int:
    """``budget`` if a share in ``(0, 1]`` (float) or a count ``>= 1`` (int); else `AmuledError`."""
    if isinstance(budget, bool) or not isinstance(budget, int | float):
        raise AmuledError(
            f"{where} expects a share in (0, 1] (a float) or a count >= 1 (an integer), "
            f"found {type(budget).__name__} ({budget!r})"
        )
    if isinstance(budget, int) and budget < 1:
        raise AmuledError(f"{where} expects a count >= 1 (an integer), found {budget!r}")
    if isinstance(budget, float) and not (math.isfinite(budget) and 0.0 < budget <= 1.0):
        raise AmuledError(f"{where} expects a share in (0, 1] (a float), found {budget!r}")
    return budget


def budget_cap(budget: float | int, visited: int) -> int:
    """Most distinct states that may have been asked after ``visited`` were visited."""
    if isinstance(budget, int) and not isinstance(budget, bool):
        return budget
    return max(1, math.floor(Fraction(repr(float(budget))) * visited))  # 0.3 as 3/10, not binary


class BudgetLedger:
    """The distinct states a run visited, credited (asked, or visited by this process) and asked."""

    def __init__(self, budget: float | int) -> None:
        self.budget = check_budget(budget)
        self.visited: set[str] = set()
        self.credited: set[str] = set()
        self.asked: list[str] = []
        self._asked: set[str] = set()

    @property
    def visited_count(self) -> int:
        """Distinct states visited."""
        return len(self.visited)

    @property
    def asked_count(self) -> int:
        """Distinct states asked."""
        return len(self.asked)

    def cap(self) -> int:
        """Most states that may be asked now (`budget_cap` of the credited count)."""
        return budget_cap(self.budget, len(self.credited))

    def allowed(self) -> int:
        """How many more distinct states may be asked now (never negative)."""
        return max(0, self.cap() - len(self.asked))

    def is_asked(self, key: str) -> bool:
        """Whether the state ``key`` was asked."""
        return key in self._asked

    def visit(self, keys: Iterable[str]) -> list[str]:
        """Record states as visited; return those visited for the first time (in order)."""
        new = []
        for key in keys:
            self.credited.add(key)
            if key not in self.visited:
                self.visited.add(key)
                new.append(key)
        return new

    def ask(self, keys: Iterable[str]) -> None:
        """Record states as asked, within the budget; nothing recorded on `BudgetExceeded`.

        `BudgetExceeded`: a key not visited or already asked, or more keys than `allowed`.
        """
        keys = list(keys)
        if len(set(keys)) != len(keys):
            raise BudgetExceeded(f"the same state is asked twice in one batch: {keys}")
        for key in keys:
            if key not in self.credited or key in self._asked:
                why = "was already asked" if key in self._asked else "was not visited"
                raise BudgetExceeded(f"state {key} cannot be asked: it {why}")
        if len(keys) > self.allowed():
            raise BudgetExceeded(
                f"{len(keys)} states to ask, but the budget {self.budget!r} allows "
                f"{self.allowed()} more ({len(self.asked)} asked of {len(self.visited)} visited)"
            )
        self.asked.extend(keys)
        self._asked.update(keys)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready state: the budget, the visited keys (sorted) and the asked keys in order."""
        return {"budget": self.budget, "visited": sorted(self.visited), "asked": list(self.asked)}

    @classmethod
    def from_dict(
        cls,
        data: Mapping[str, Any],
        where: str = "budget state",
        budget: float | int | None = None,
    ) -> BudgetLedger:
        """Rebuild a ledger from `to_dict` (a `LedgerTable`) under the scenario's ``budget``.

        ``budget`` None: the ledger's own. The cap credits the asked states only, until the
        visited ones are visited again. `AmuledError`: a budget other than the scenario's, or a
        broken invariant (an asked state not visited, asked twice, more asked than the cap).
        """
        saved = data["budget"]
        if budget is not None and (type(saved) is not type(budget) or saved != budget):
            raise AmuledError(
                f"{where}: ledger.budget is {saved!r} but the scenario's [feedback.distill]."
                f"budget is {budget!r} (the file was edited or is another run's); start the "
                "fine-tune over with --force"
            )
        visited, asked = data["visited"], data["asked"]
        ledger = cls(saved if budget is None else budget)
        ledger.visited = set(visited)
        if len(ledger.visited) != len(visited):
            raise AmuledError(f"{where}: a state visited twice; start over with --force")
        if len(set(asked)) != len(asked) or not set(asked) <= ledger.visited:
            raise AmuledError(
                f"{where}: asked states that were not visited, or asked twice; start over "
                "with --force"
            )
        allowed = budget_cap(ledger.budget, len(ledger.visited))
        if len(asked) > allowed:
            raise AmuledError(
                f"{where}: {len(asked)} states asked but the budget {ledger.budget!r} allows "
                f"{allowed} of {len(visited)} visited; start over with --force"
            )
        ledger.asked = list(asked)
        ledger._asked = set(asked)
        ledger.credited = set(asked)
        return ledger
