"""The one YAML reader of the project (engine, CLI and ROS side alike).

PyYAML resolves scalars by YAML 1.1, where a float needs a dot and a signed exponent:
`1e-4`, `1.0e9` and `5E3` come back as *strings* and then fail a range check far from the
file.  This loader adds YAML 1.2's float pattern (the one JSON and rcl's own parameter
parser accept), so every number a user writes in a config file is a number.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

YAMLError = yaml.YAMLError

# YAML 1.2 core-schema floats: optional sign, digits with an optional fraction (or a
# leading-dot fraction), optional exponent with an optional sign; plus .inf/.nan
_FLOAT_12 = re.compile(
    r"""^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?
                         |[-+]?\.(?:inf|Inf|INF)
                         |\.(?:nan|NaN|NAN))$""",
    re.X,
)


class Loader(yaml.SafeLoader):
    """SafeLoader whose float resolver also takes YAML 1.2 floats (`1e-4`, `1.0e9`)."""


# rebuild the implicit resolvers: YAML 1.1 int first (so `10` stays an int), then 1.2 floats
Loader.yaml_implicit_resolvers = {
    k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _ch in list("-+.0123456789"):
    Loader.yaml_implicit_resolvers[_ch] = [
        (tag, rx)
        for tag, rx in Loader.yaml_implicit_resolvers.get(_ch, [])
        if tag != "tag:yaml.org,2002:float"
    ]
Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+.0123456789"))


def loads(text: str) -> Any:
    """Parse YAML text (safe: plain data only)."""
    return yaml.load(text, Loader=Loader)  # noqa: S506 - Loader is a SafeLoader


def load_file(path: str | Path) -> Any:
    """Read and parse a YAML file; OSError / yaml.YAMLError propagate to the caller, who
    names the file in its message."""
    return loads(Path(path).read_text())


def dumps(data: Any, **kw: Any) -> str:
    """yaml.safe_dump (floats such as 1e-05 are written as `1.0e-05`, which loads back)."""
    return yaml.safe_dump(data, **kw)


def problem_line(exc: BaseException) -> str:
    """' (line N)' of a YAML parse error, '' if it has no position."""
    mark = getattr(exc, "problem_mark", None)
    return f" (line {mark.line + 1})" if mark is not None else ""
