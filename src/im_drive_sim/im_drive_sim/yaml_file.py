"""One YAML file read, with a one-line reason when it cannot be: the drive file, the
tuner's parameter file and their like are read here, so each refusal reads the same."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


class YamlFileError(ValueError):
    """A file that is not readable YAML; its text is one line, without the file's name."""


def read_yaml(path: Path) -> tuple[Any, str]:
    """The YAML document of the text file ``path`` and its text. :class:`YamlFileError`:
    ``cannot read the file (REASON)``, ``not a text (UTF-8) file`` or ``YAML syntax error at
    line L, column C: PROBLEM``."""
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as exc:
        raise YamlFileError(f'cannot read the file ({exc.strerror or exc})') from None
    except UnicodeDecodeError:
        raise YamlFileError('not a text (UTF-8) file') from None
    try:
        return yaml.safe_load(text), text
    except yaml.YAMLError as exc:
        mark = getattr(exc, 'problem_mark', None)
        where = '' if mark is None else f' at line {mark.line + 1}, column {mark.column + 1}'
        problem = ' '.join(str(getattr(exc, 'problem', None) or exc).split())
        raise YamlFileError(f'YAML syntax error{where}: {problem}') from None
