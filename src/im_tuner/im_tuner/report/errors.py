"""The report's refusal: one line on stderr and exit code 2 (no numpy, no matplotlib:
the command line is checked before anything heavy is imported)."""

from __future__ import annotations


class ReportError(Exception):
    """The report cannot be made (message says why, in one line)."""
