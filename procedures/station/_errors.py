"""Errors of the procedure layer: configuration files, runs, the store."""

from __future__ import annotations


class ConfigError(ValueError):
    """A station or procedure file is invalid. ``problems`` holds one ``file:line: field: what``
    string per problem; ``str()`` joins them, one per line."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


class RunError(RuntimeError):
    """A run cannot be started, resumed or continued (the message says why)."""


class DryRunFailed(RunError):
    """The dry run found problems; ``problems`` lists them. No motion was sent."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("dry run failed:\n  " + "\n  ".join(self.problems))


class ResumeRefused(RunError):
    """A stored run could not be continued now (its devices, plan or records are not ready); its state and
    samples were left exactly as they were, so it can be resumed once the cause is fixed."""


class RunAborted(RunError):
    """The operator (or the cell) aborted the run."""


class RunLocked(RunError):
    """Another live process is running this run (it holds the run's lease)."""


class StateConflict(RunError):
    """The run's state changed under this process (another process, or a lost lease): nothing was written."""
