"""One error hierarchy for the whole package; each error names what, where, and the fix."""

from __future__ import annotations

from typing import ClassVar

#: Exit status of a command that finished.
EXIT_OK = 0
#: Exit status of a refused input or a failed run (an :class:`AmuledError`, a file error).
EXIT_REFUSED = 1
#: Exit status of a usage error: an unknown option or a missing argument (argparse's).
EXIT_USAGE = 2
#: Exit status of a run stopped by Ctrl-C (128 + SIGINT).
EXIT_INTERRUPTED = 130
#: Exit status of a run stopped by SIGTERM (128 + SIGTERM).
EXIT_TERMINATED = 143


class AmuledError(Exception):
    """Base class of every error raised on purpose by amuled-ma; ``exit_code``: the CLI's."""

    exit_code: ClassVar[int] = EXIT_REFUSED


class ScenarioError(AmuledError, ValueError):
    """A scenario file or key is missing, unknown, or of the wrong type."""


class ClusterDefinitionError(AmuledError, ValueError):
    """A moral-cluster file under ``prompts/clusters/`` is malformed."""


class PromptError(AmuledError, ValueError):
    """A prompt file (state template, system prompt, few-shot examples) is missing or malformed."""


class BackendUnavailable(AmuledError, RuntimeError):
    """A belief backend (an Ollama server, say) cannot be reached."""


class ModelNotFound(AmuledError, LookupError):
    """The requested model is not available on the backend."""


class ReplayMiss(AmuledError, KeyError):
    """A replayed recording has no belief for the requested state."""


class AbstentionError(AmuledError, RuntimeError):
    """A panel agent left more states unanswered than ``[feedback].max_abstention`` allows."""


class AuthorsImportError(AmuledError, ValueError):
    """A file of the paper authors' checkout is missing, malformed, or would overwrite data."""


class UnsafePickleError(AuthorsImportError):
    """A pickle needs a global outside the allow-list; nothing from it was run."""


class AuthorsFetchError(AmuledError, RuntimeError):
    """A pinned file of the paper authors could not be fetched, was refused, or fetching is off."""


class CheckpointError(AmuledError, FileNotFoundError):
    """A checkpoint needed by a command is missing or unreadable."""


class Terminated(KeyboardInterrupt):
    """SIGTERM as a :class:`KeyboardInterrupt`, so the Ctrl-C clean-up (checkpoints) runs too."""

    exit_code: ClassVar[int] = EXIT_TERMINATED


class TerminatedWhileStarting(Terminated):
    """SIGTERM while Ray started (``ray.init``), before any work of the command.

    The command line ends the process at once after its line: the interpreter's exit may hang
    in what ``ray.init`` left half-built.
    """


class MemberFailed(AmuledError):
    """One ``member`` (its index) of a training population failed; the others go on."""

    def __init__(self, member: int, message: str) -> None:
        super().__init__(message)
        self.member = member
