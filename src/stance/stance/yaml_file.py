"""Reading the library's YAML files (scenes, limit files) with errors that name the file."""

from __future__ import annotations

from pathlib import Path

import yaml


def load_yaml_file(path: Path, error: type[Exception]):
    """The document of a UTF-8 YAML file; `error` naming the file when it is not UTF-8 text
    or not valid YAML."""
    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as cause:
        raise error(f"{path}: not a YAML text file (not UTF-8: byte {cause.start})") \
            from cause
    except yaml.YAMLError as cause:
        raise error(f"{path}: not valid YAML: {cause}") from cause
