"""The budget of asked states: which distinct states were visited and asked, how many more may be.

The budget counts *distinct states*, not requests: asking the panel about one state costs
one request per panel member, and a state asked once is never charged again (its answers
are in the belief store). Two forms (``[feedback.distill].budget``):

- a **share** ``b`` in ``(0, 1]`` (a float): after ``v`` distinct states were visited, at
  most ``cap(v) = max(1, floor(b * v))`` of them may have been asked;
- a **count** ``n >= 1`` (an integer): at most ``n`` distinct states are ever asked.

The invariant, checked by :meth:`BudgetLedger.ask` and property-tested over random visit
orders, batch sizes and resumes (``tests/distill/test_budget.py``), holds after every
batch: ``asked <= cap(visited)``. For a share that is ``asked <= b * visited``, except
that the very first state may be asked while ``b * visited < 1`` (``asked == 1``): the
model needs one answer before it can answer anything. ``b`` is taken as the decimal it
is written as (``0.3`` is exactly 3/10, :func:`exact_share`) and the product is exact, so
neither binary rounding of ``0.3`` (slightly below 3/10) takes a state away nor float
rounding of a product lets one more in. States of a batch are visited before any of them
is asked, so a batch of new states raises the cap before the selection admits its share
of them.

A resumed ledger credits the cap only with states it can vouch for: the states asked
(charged, so a made-up one only spends budget) and the states visited in this process. The
visited states read from a state file are kept (a state seen before is not new) but raise
the cap only when they are visited again, so a state file cannot grow the budget the
scenario sets: edited to hold made-up visited states, it holds no more than the honest file
would (the cap of a resumed run starts lower and climbs back as the states are seen again).

Pure Python; :class:`BudgetLedger` is what :class:`~amuled_ma.distill.source.DistilledSource`
consults and what its state file keeps, so a resumed run starts with the budget it
already spent.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from fractions import Fraction
from typing import Any

from amuled_ma.errors import AmuledError


class BudgetExceeded(AmuledError, RuntimeError):
    """More distinct states were to be asked than the budget allows (a bug, never expected)."""


def check_budget(budget: object, where: str = "[feedback.distill].budget") -> float | int:
    """Return ``budget`` if it is a share in ``(0, 1]`` (float) or a count ``>= 1`` (int).

    Args:
        budget: The setting.
        where: What to name in the error.

    Returns:
        The setting, unchanged.

    Raises:
        AmuledError: Anything else (a bool, a string, 0, 1.5, NaN, -3).

    """
    if isinstance(budget, bool) or not isinstance(budget, int | float):
        raise AmuledError(
            f"{where} expects a share in (0, 1] (a float) or a count >= 1 (an integer), "
            f"found {type(budget).__name__} ({budget!r})"
        )
    if isinstance(budget, int):
        if budget < 1:
            raise AmuledError(f"{where} expects a count >= 1 (an integer), found {budget!r}")
        return budget
    if not (math.isfinite(budget) and 0.0 < budget <= 1.0):
        raise AmuledError(f"{where} expects a share in (0, 1] (a float), found {budget!r}")
    return budget


def exact_share(share: float) -> Fraction:
    """A share as the decimal it is written as: ``0.3`` -> ``Fraction(3, 10)``.

    ``repr`` of a float is the shortest decimal that reads back as the same float, i.e.
    what a scenario file says; the binary value of ``0.3`` is slightly below 3/10.
    """
    return Fraction(repr(float(share)))


def budget_cap(budget: float | int, visited: int) -> int:
    """Most distinct states that may have been asked after ``visited`` were visited.

    Args:
        budget: A share in ``(0, 1]`` (float) or a count ``>= 1`` (int).
        visited: Distinct states visited so far.

    Returns:
        ``budget`` for a count; ``max(1, floor(budget * visited))`` for a share (exact
        arithmetic on the decimal written, :func:`exact_share`).

    """
    if isinstance(budget, int) and not isinstance(budget, bool):
        return budget
    return max(1, math.floor(exact_share(budget) * visited))


class BudgetLedger:
    """The distinct states a run visited and asked, against its budget.

    Args:
        budget: A share in ``(0, 1]`` (float) or a count ``>= 1`` (int); see the module.

    Attributes:
        budget: The setting.
        visited: Keys of every distinct state visited (a state file's included).
        credited: Keys of the states the cap counts: asked, or visited by this process.
        asked: Keys of the states asked, in the order they were asked.

    """

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
        """Most states that may be asked now (:func:`budget_cap` of the credited count)."""
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
        """Record states as asked, within the budget.

        Args:
            keys: Visited states not asked yet.

        Raises:
            BudgetExceeded: A key was not visited or was already asked, or there are more
                keys than :meth:`allowed`; nothing is recorded then.

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
        data: object,
        where: str = "budget state",
        budget: float | int | None = None,
    ) -> BudgetLedger:
        """Rebuild a ledger from :meth:`to_dict`, under the scenario's budget.

        Args:
            data: What :meth:`to_dict` gave (read from a state file).
            where: What to name in an error (the file).
            budget: The scenario's budget: the ledger's must be the same (a state file
                edited to raise it is refused). None: the ledger's own (tests).

        Returns:
            The ledger; its cap credits the asked states only (see the module), until the
            visited ones are visited again.

        Raises:
            AmuledError: The data is malformed (keys not strings, a budget of another
                value or type than the scenario's) or breaks the invariant (an asked state
                not visited, asked twice, or more asked than the budget allows of the
                file's visited states): ``where`` is named, and ``--force``.

        """
        if not isinstance(data, Mapping):
            raise AmuledError(f"{where}: 'ledger' is not a table; start over with --force")
        saved = data.get("budget")
        if budget is not None and (type(saved) is not type(budget) or saved != budget):
            raise AmuledError(
                f"{where}: ledger.budget is {saved!r} but the scenario's [feedback.distill]."
                f"budget is {budget!r} (the file was edited or is another run's); start the "
                "fine-tune over with --force"
            )
        visited, asked = data.get("visited"), data.get("asked")
        if not (
            isinstance(visited, list)
            and isinstance(asked, list)
            and all(type(k) is str for k in visited)
            and all(type(k) is str for k in asked)
        ):
            raise AmuledError(
                f"{where}: ledger.visited and ledger.asked must be lists of state keys "
                "(strings); start over with --force"
            )
        try:
            ledger = cls(check_budget(saved) if budget is None else budget)
        except AmuledError as error:
            raise AmuledError(
                f"{where}: not a budget state ({error}); start over with --force"
            ) from error
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
