"""Building nested frozen config dataclasses from YAML mappings, with errors that name file and key."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import yaml


def build_dataclass(cls: type, data: Any, where: str, error: type[Exception] = ValueError) -> Any:
    """An instance of dataclass ``cls`` from the mapping ``data``; missing keys keep their defaults.

    Nested dataclass fields are built recursively, YAML lists become tuples where the default is a
    tuple, and an unknown key raises ``error`` naming ``where`` (the file) and the key's path.
    """
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise error(f"{where}: expected a mapping, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise error(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(names)}")
    defaults = cls()
    kwargs = {}
    for k, v in data.items():
        d = getattr(defaults, k)
        if dataclasses.is_dataclass(d):
            kwargs[k] = build_dataclass(type(d), v, f"{where}.{k}", error)
        elif isinstance(d, tuple) and isinstance(v, list):
            kwargs[k] = tuple(v)
        else:
            kwargs[k] = v
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise error(f"{where}: {e}") from None


def yaml_problem(e: Exception) -> str:
    """One line for a YAML parse or file error (PyYAML's own message spans several, with a caret
    drawing): the problem and where it is."""
    if isinstance(e, yaml.MarkedYAMLError) and e.problem_mark is not None:
        m = e.problem_mark
        return f"{e.problem or e.context} at line {m.line + 1}, column {m.column + 1}"
    return " ".join(str(e).split())


def read_config_yaml(path: str | Path, kind: str, what: str, error: type[Exception]) -> tuple[Path, Any]:
    """(resolved path, parsed YAML) of a config file; a bare name like ``lite`` means
    ``configs/<kind>/lite.yaml``. Unreadable files raise ``error`` naming the file and ``what`` it is."""
    from surftrack.paths import configs_dir

    p = Path(path)
    if not p.suffix and not p.exists():
        p = configs_dir() / kind / f"{path}.yaml"
        if not p.is_file():
            names = ", ".join(sorted(f.stem for f in (configs_dir() / kind).glob("*.yaml")))
            raise error(f"{path}: no such {what} (a YAML file, or one of the bundled: {names})")
    try:
        return p, yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise error(f"{p}: cannot read {what}: {yaml_problem(e)}") from None
