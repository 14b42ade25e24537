"""User-facing exception types: each message names the file (or field) and the fix."""
from __future__ import annotations


class ProceduralizeError(Exception):
    """Base class of every error a user can act on."""


class InputError(ProceduralizeError):
    """A material map (or scribble image) is missing, unreadable or invalid."""


class ManifestError(ProceduralizeError):
    """A job manifest is malformed; carries every problem found at once."""

    def __init__(self, problems: list[str] | str, path: str | None = None):
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        self.path = path
        head = f"{path}: " if path else ""
        super().__init__(head + "; ".join(self.problems))


class GraphError(ProceduralizeError):
    """A procedural material file is malformed or of an unsupported version."""


class DatabaseError(ProceduralizeError):
    """A PPTBF database folder is missing, incomplete or of another version."""
