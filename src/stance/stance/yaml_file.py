"""Reading the project's YAML documents (scenes, limit files, stacks, teleop paths, graph
files): PyYAML's YAML 1.1 rules plus exponents without a dot read as floats, and errors
that name the file."""

from __future__ import annotations

import re
from pathlib import Path

import yaml


class _Loader(yaml.SafeLoader):
    """yaml.SafeLoader that also reads exponents without a dot as floats, as YAML 1.2
    does: PyYAML's YAML 1.1 rules read `1e-3` and `1e308` as strings. The rest stays
    YAML 1.1 (`017` is octal, `yes` a bool)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def load_yaml(text: str):
    """The document of a YAML text (yaml.YAMLError when it is not valid YAML)."""
    return yaml.load(text, Loader=_Loader)


def load_yaml_file(path: Path, error: type[Exception]):
    """The document of a UTF-8 YAML file; `error` naming the file when it is not UTF-8 text
    or not valid YAML."""
    try:
        return load_yaml(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as cause:
        raise error(f"{path}: not a YAML text file (not UTF-8: byte {cause.start})") \
            from cause
    except yaml.YAMLError as cause:
        raise error(f"{path}: not valid YAML: {cause}") from cause
