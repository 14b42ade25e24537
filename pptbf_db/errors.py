"""User-facing exception base and the errors raised by pptbf_db; each message names the file and the fix.

`workers.errors` derives its own error types (InputError, ManifestError, GraphError) from
`ProceduralizeError`: the layering is one-way (workers and service import pptbf_db, never the reverse).
"""
from __future__ import annotations


class ProceduralizeError(Exception):
    """Base class of every error a user can act on."""


class DatabaseError(ProceduralizeError):
    """A PPTBF database folder is missing, incomplete or of another version."""


class WeightsError(ProceduralizeError):
    """The VGG-19 weights of the Gram feature extractor are missing, unreadable or of the wrong shape."""
