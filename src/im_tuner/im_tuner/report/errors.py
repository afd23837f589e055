"""The report's refusal: one line on stderr and this exit code (no numpy, no matplotlib:
the command line is checked before anything heavy is imported)."""

from __future__ import annotations

EXIT_USAGE = 2


class ReportError(Exception):
    """The report cannot be made (message says why, in one line)."""
