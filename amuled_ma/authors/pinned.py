"""The paper authors' files that ``amuled`` fetches on first use, pinned by commit and SHA-256.

The repository has no licence file: the files are fetched for the user, never shipped. The
two caches over 4 MiB (``models/Driving_42``) are not pinned.
"""

from __future__ import annotations

from dataclasses import dataclass

#: The authors' repository.
REPOSITORY = "https://github.com/temetski/moral_agent"
#: The commit every file is fetched at (their HEAD of 2026-04-15, "Add citation information").
COMMIT = "df3750f5efc95e2ba5be01efaff62f639801600b"
#: Where a file is fetched from: ``<RAW_BASE>/<COMMIT>/<path>``.
RAW_BASE = "https://raw.githubusercontent.com/temetski/moral_agent"


@dataclass(frozen=True)
class PinnedFile:
    """One file of the authors' repository at `COMMIT`; ``recording``: what it becomes."""

    path: str
    sha256: str
    size: int
    recording: str


#: Every pinned file, FindMilk first.
PINNED: tuple[PinnedFile, ...] = (
    PinnedFile(
        "models/FindMilk-v4_42/gpt-4o-mini_llm_cache.pickle",
        "f94abfc05bbabc6f8e126bcd7c4f4e6cf371f652a78b12777ed16f5d620d1158",
        1_535_490,
        "findmilk-gpt-4o-mini",
    ),
    PinnedFile(
        "models/FindMilk-v4_42/llama-3.1-70B_llm_cache.pickle",
        "b765e9e1ca6d44b31ff7d5aa486372095a8739e02ca324d23e2ebb50f9c71559",
        180_843,
        "findmilk-llama-3_1-70b",
    ),
    PinnedFile(
        "models/FindMilk-v4_42/llama-3.1-8B_llm_cache.pickle",
        "989e348ba0457a1e4cbf24f49fe7f920da10cb6b3ffbc447e32dc0f685cd7739",
        114_886,
        "findmilk-llama-3_1-8b",
    ),
    PinnedFile(
        "models/FindMilk-v4_42/mistral-nemo_llm_cache.pickle",
        "c0a4d5d9e6df9ba7bd39dd3110c1faaa22356bc73e35afd976016ee5d99fd2f4",
        75_532,
        "findmilk-mistral-nemo",
    ),
    PinnedFile(
        "PickleCacheAndBaseModels/Drive/gpt-4o-mini_llm_cache.pickle",
        "143f76d31a909bdf3dd1d28e11c4b9650b4d2a26ac4d0a48889946558d5c58b6",
        1_951_760,
        "driving-gpt-4o-mini",
    ),
    PinnedFile(
        "models/Driving_42/llama-3.1-70B_llm_cache.pickle",
        "6d7d8d74b8529956a4cc5bdcdb4780665d80d7fdd1e60be50e589c5bed69f23f",
        1_953_517,
        "driving-llama-3_1-70b",
    ),
    PinnedFile(
        "models/Driving_42/llama-3.1-8B_llm_cache.pickle",
        "0d69b63de28a41995fba218ad2210c38f1cfc6a98526d3c7f64705a461bd6115",
        1_842_899,
        "driving-llama-3_1-8b",
    ),
)


#: The authors' published base policies ``amuled demo`` starts its fine-tunes from, by task:
#: the CleanRL policy file and the folder ``amuled import authors`` converts it into
#: (``<runs>/authors/<task>/base``, its ``recording`` field). Their ``ppo.py`` at 500,000
#: steps, seed 42 (docs/authors.md).
BASE_POLICIES: dict[str, PinnedFile] = {
    "findmilk": PinnedFile(
        "models/FindMilk-v4_42/base.cleanrl_model",
        "da2a629ce68ac73126eaeba679c480dbf91f12e897533ae8134b90612346dc39",
        42_882,
        "authors/findmilk/base",
    ),
}
