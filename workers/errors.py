"""User-facing exception types of the workers: each message names the file (or field) and the fix.

The base class `ProceduralizeError` (and `DatabaseError`) live in `pptbf_db.errors`."""
from __future__ import annotations

from pptbf_db.errors import ProceduralizeError


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
