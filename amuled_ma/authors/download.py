"""Fetch the paper authors' pinned files on first use; convert them as ``amuled import authors``.

Each file is kept only when its SHA-256 matches; offline use and the environment variables:
docs/authors.md.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Collection, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from amuled_ma.authors.pinned import (
    BASE_POLICIES,
    COMMIT,
    PINNED,
    RAW_BASE,
    REPOSITORY,
    PinnedFile,
)
from amuled_ma.errors import AuthorsFetchError
from amuled_ma.files.hashing import sha256_file

if TYPE_CHECKING:
    from amuled_ma.scenario import FeedbackConfig

#: Set to 1 (or true, yes, on) to never fetch, as ``--offline``.
OFFLINE_ENV = "AMULED_OFFLINE"
#: Replaces `RAW_BASE` (a mirror; the tests' loopback server).
URL_ENV = "AMULED_AUTHORS_URL"
#: Replaces the cache root (shared with the Ollama server's state, `servers.local_server`).
CACHE_ENV = "AMULED_CACHE"
#: Seconds to connect, and between two reads of a download, before it is abandoned.
CONNECT_TIMEOUT_S = 10.0
READ_TIMEOUT_S = 60.0
#: What a fetch says of the files' terms (the authors' repository has no licence file).
TERMS = "from the paper authors' own repository, under their terms (it has no licence file)"


def cache_folder() -> Path:
    """Where fetched files are kept: ``<cache root>/authors/<commit[:12]>/``."""
    env = os.environ.get(CACHE_ENV)
    if env:
        root = Path(env).expanduser()
    else:
        import platformdirs

        root = Path(platformdirs.user_cache_dir("amuled-ma", appauthor=False))
    return root / "authors" / COMMIT[:12]


def _mb(size: int) -> str:
    """A size for a message: MB from 1 MB (one decimal), else kB."""
    return f"{size / 1e6:.1f} MB" if size >= 1e6 else f"{size / 1e3:.0f} kB"


def pinned_recording(value: str, pinned: Sequence[PinnedFile] = PINNED) -> PinnedFile | None:
    """The pinned file a recording value (a name or a path, ``.json`` optional) comes from."""
    name = Path(value).name.removesuffix(".json")
    return next((pin for pin in pinned if pin.recording == name), None)


def replayed_recordings(feedback: FeedbackConfig) -> list[str]:
    """The recordings a fine-tune replays, each once: ``[feedback]``'s, then its agents' tables'."""
    values = [feedback.recording] if feedback.source == "replay" else []
    for spec in feedback.agents.values():
        if spec.source == "replay":
            values.append(getattr(spec, "recording", "") or feedback.recording)
    return list(dict.fromkeys(v for v in values if v.strip()))


def models_ablation_recordings(
    feedback: FeedbackConfig, task: str, resolve: Callable[[str], Path]
) -> list[str]:
    """The recordings to fetch before the ``models`` ablation is planned.

    When the scenario replays a pinned recording found nowhere here, every pinned recording
    of its task (converted side by side); else none (the ablation compares those found).
    """
    own = feedback.recording
    if feedback.source != "replay" or pinned_recording(own) is None:
        return []
    if _found_locally(resolve, own):
        return []
    return [pin.recording for pin in PINNED if pin.recording.startswith(f"{task}-")]


def _found_locally(resolve: Callable[[str], Path], value: str) -> bool:
    from amuled_ma.scenario.paths import find_recording

    return find_recording(value, resolve, where="[feedback].recording").is_file()


def _cached(pin: PinnedFile, cache: Path) -> bool:
    path = cache / pin.path
    return path.is_file() and path.stat().st_size == pin.size and sha256_file(path) == pin.sha256


def manual_route(names: Collection[str]) -> str:
    """The ways to get recordings without fetching, for messages."""
    files = ", ".join(f"{n}.json" for n in names)
    return (
        f"'git clone {REPOSITORY}' then 'amuled import authors PATH' (PATH = the clone), "
        f"or set AMULED_RECORDINGS to a folder holding {files}"
    )


def pin_route(pin: PinnedFile) -> str:
    """The way to get one pinned file without fetching (a recording's, or a base policy's)."""
    if pin.path.endswith(".cleanrl_model"):
        return (
            f"'git clone {REPOSITORY}' then 'amuled import authors PATH --only policies' "
            f"(PATH = the clone), which writes runs/{pin.recording}"
        )
    return manual_route([pin.recording])


class _CappedFile:
    """A writable file that refuses to grow past the pinned size (a server serving more)."""

    def __init__(self, raw: BinaryIO, limit: int, url: str) -> None:
        self.raw, self.limit, self.url, self.written = raw, limit, url, 0

    def write(self, chunk: bytes) -> int:
        self.written += len(chunk)
        if self.written > self.limit:
            raise AuthorsFetchError(
                f"refusing {self.url}: it sends more than the pinned {self.limit:,} bytes; "
                "the download was deleted"
            )
        return self.raw.write(chunk)

    def flush(self) -> None:
        self.raw.flush()


@contextlib.contextmanager
def _quiet_pooch() -> Iterator[None]:
    """Pooch's own "Downloading file ..." lines off: the fetch says its one line itself."""
    import pooch

    logger = pooch.get_logger()
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def fetch_pinned(
    pins: Sequence[PinnedFile],
    *,
    cache: Path | None = None,
    base: str | None = None,
    say: Callable[[str], None] = print,
) -> Path:
    """Fetch the pinned files not in the cache, each checked by SHA-256; return the cache folder.

    Says one line first (what, from where, how large, under whose terms) when anything is fetched.

    Raises:
        AuthorsFetchError: A file could not be fetched or was refused (SHA-256, size); names
            the file, the URL and the manual route. Nothing partial stays.
    """
    import pooch
    import requests

    cache = cache or cache_folder()
    base = (base or os.environ.get(URL_ENV) or RAW_BASE).rstrip("/")
    wanted = [pin for pin in pins if not _cached(pin, cache)]
    if not wanted:
        return cache
    say(
        f"fetching {len(wanted)} file(s), {_mb(sum(pin.size for pin in wanted))}: "
        f"{', '.join(pin.path for pin in wanted)} from {base}/{COMMIT[:12]}/ "
        f"(pinned commit, each checked against its SHA-256) into {cache}; {TERMS}"
    )
    pup = pooch.create(
        path=cache,
        base_url=f"{base}/{COMMIT}/",
        registry={pin.path: f"sha256:{pin.sha256}" for pin in pins},
    )
    http = pooch.HTTPDownloader(progressbar=False, timeout=(CONNECT_TIMEOUT_S, READ_TIMEOUT_S))
    for pin in wanted:
        url = f"{base}/{COMMIT}/{pin.path}"
        route = pin_route(pin)

        def download(url: str, output_file: str, pup: object, size: int = pin.size) -> None:
            with open(output_file, "wb") as raw:  # written through `_CappedFile`: size at most
                http(url, _CappedFile(raw, size, url), pup)

        try:
            with _quiet_pooch():
                pup.fetch(pin.path, downloader=download)
        except AuthorsFetchError as error:
            raise AuthorsFetchError(
                f"{error}; nothing was kept in {cache}. Else: {route}"
            ) from None
        except ValueError:  # pooch: the SHA-256 differs (the temporary file is deleted)
            raise AuthorsFetchError(
                f"refusing {url}: its SHA-256 is not the pinned {pin.sha256} "
                f"(amuled_ma/authors/pinned.py); the download was deleted, nothing was kept "
                f"in {cache}. Try again later, or: {route}"
            ) from None
        except requests.RequestException as error:
            reason = type(error).__name__
            raise AuthorsFetchError(
                f"could not fetch {url} ({reason}: {str(error)[:200]}); without network: {route}"
            ) from None
        except OSError as error:
            raise AuthorsFetchError(
                f"could not write {pin.path} into the cache folder {cache}: {error}; set "
                f"{CACHE_ENV} to a writable folder, or: {route}"
            ) from None
    return cache


def _fetch_unless_offline(
    pins: Sequence[PinnedFile],
    missing: str,
    route: str,
    offline: bool,
    cache: Path | None,
    base: str | None,
    say: Callable[[str], None],
) -> Path:
    """`fetch_pinned`; offline with a pin not cached: one line (``missing``, then ``route``).

    Raises:
        AuthorsFetchError: Offline with a file not cached, or the fetch failed.
    """
    cache = cache or cache_folder()
    off = offline or os.environ.get(OFFLINE_ENV, "").strip().lower() in ("1", "true", "yes", "on")
    if off and not all(_cached(pin, cache) for pin in pins):
        raise AuthorsFetchError(
            f"the paper authors' {missing} and fetching is off (--offline or {OFFLINE_ENV}=1): "
            f"run without it to fetch {_mb(sum(pin.size for pin in pins))} from {REPOSITORY} "
            f"at {COMMIT[:12]} (checked), or {route}"
        )
    return fetch_pinned(pins, cache=cache, base=base, say=say)


def ensure_recordings(
    resolve: Callable[[str], Path],
    values: Sequence[str],
    *,
    offline: bool = False,
    say: Callable[[str], None] = print,
    pinned: Sequence[PinnedFile] = PINNED,
    cache: Path | None = None,
    base: str | None = None,
    to: Path | None = None,
) -> list[Path]:
    """Fetch and convert (into ``to``, None: the user's) the ``pinned`` ``values`` not found here.

    Returns the recordings written (empty: nothing was missing).

    Raises:
        AuthorsFetchError: Offline with a file not cached (one line naming the routes), or
            the fetch failed (:func:`fetch_pinned`).
        AuthorsImportError: The conversion refused a file.
    """
    pins: list[PinnedFile] = []
    for value in values:
        pin = pinned_recording(value, pinned)
        if pin is not None and pin not in pins and not _found_locally(resolve, value):
            pins.append(pin)
    if not pins:
        return []
    names = [pin.recording for pin in pins]
    missing = f"recording {', '.join(names)} is not on this machine"
    cache = _fetch_unless_offline(pins, missing, manual_route(names), offline, cache, base, say)
    from amuled_ma.authors.checkout import import_authors  # here: it imports torch

    report = import_authors(
        cache, to=to, policies=False, only={pin.path for pin in pins}, recordings=True
    )
    written = [output.target for output in report.of_kind("recording")]
    say(f"converted to {', '.join(str(path) for path in written)}")
    return written


def ensure_authors_base(
    task: str,
    *,
    runs: Path,
    offline: bool = False,
    say: Callable[[str], None] = print,
    pinned: dict[str, PinnedFile] = BASE_POLICIES,
    cache: Path | None = None,
    base: str | None = None,
) -> Path | None:
    """The authors' base policy of ``task`` (None: none pinned) in ``<runs>/authors/<task>/base``.

    Raises:
        AuthorsFetchError: Offline with the file not cached, or the fetch failed.
        AuthorsImportError: The conversion refused the file.
    """
    from amuled_ma.learn.checkpoints import LAST

    pin = pinned.get(task)
    if pin is None:
        return None
    folder = Path(runs) / pin.recording
    if (folder / LAST).is_file():
        return folder
    missing = f"published {task} base policy is not in {folder}"
    cache = _fetch_unless_offline([pin], missing, pin_route(pin), offline, cache, base, say)
    from amuled_ma.authors.checkout import import_authors  # here: it imports torch

    import_authors(cache, runs=runs, recordings=False, policies=True)
    say(f"converted to {folder}")
    return folder
