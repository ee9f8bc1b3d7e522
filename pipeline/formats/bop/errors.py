"""The one exception type of the BOP format layer."""

from __future__ import annotations


class BopFormatError(ValueError):
    """A BOP file is missing, malformed, or lacks a field.

    The message always starts with the file path and names, when known, the entry (or
    line) and the field, so a user can open the file and find the problem directly.
    """
