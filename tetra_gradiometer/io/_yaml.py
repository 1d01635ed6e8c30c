"""Reading a YAML file with errors that name the file and what it was meant to be."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml


def read_yaml(path: str | os.PathLike, what: str, error: type[ValueError]) -> Any:
    """The parsed document at ``path``; ``error`` (e.g. ParamsError) says
    "<what> file not found: PATH" or "<what> file PATH is not valid YAML: ..."."""
    path = Path(path)
    try:
        return yaml.safe_load(path.read_text(encoding='utf-8'))
    except FileNotFoundError:
        raise error(f'{what} file not found: {path}') from None
    except yaml.YAMLError as problem:
        raise error(f'{what} file {path} is not valid YAML: {problem}') from None
