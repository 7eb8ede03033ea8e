"""One declaration per setting: a config dataclass's fields carry their unit, range, text,
card rule and whether they may change while running, and everything else is read from there.

    @dataclass
    class LoopConfig:
        bandwidth_hz: float | None = param(
            None, unit="Hz", range=(10.0, 5000.0), doc="-3 dB bandwidth of the loop",
            rule=Rule("PWM/10", lambda card, cfg: card.pwm_hz / 10),
            limit=Limit("at most PWM/4", lambda card, decimation: (None, card.pwm_hz / 4)),
        )

From the fields (`specs`):
- `check_fields(cfg, src)`: every field's type, range or choices; the one line names the key;
- `resolve(cfg, card)`: a copy with every field left None filled by its card rule;
- `ranges(cls, card, decimation)`: what is accepted, the static range narrowed by the limits
  that follow from the card or the decimation (what a ROS node declares as its descriptor
  range: `fluxdrive_ros.params`);
- `markdown_table(cls)`: the parameter table in the docs (`./fluxdrive docs params`);
- `option(ap, "--flag", cls)`: a command-line option ranged by a field (a value outside
  the range: ConfigError naming the option, one line where the command catches it);
- `Parser`: the argument parser every command uses: any `type=float` option takes finite
  numbers only, `type=int` refuses what does not fit in int64, and a bad option is one line
  (`prog: argument --x: ...`, exit 2) instead of argparse's usage block.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from fluxdrive.core.errors import ConfigError

SCHEMA = "fluxdrive.schema"  # the key of a field's Spec in its dataclass field metadata


@dataclass(frozen=True)
class Rule:
    """How `resolve(cfg, card)` fills a field left None: the text for the docs and the value
    from the machine card (and the config itself, e.g. its variant)."""

    text: str
    value: Callable[[Any, Any], Any]  # (card, cfg) -> value


@dataclass(frozen=True)
class Limit:
    """A bound that follows from the machine card or the decimation and narrows the static
    range: `bounds(card, decimation)` -> (lo, hi), None keeping the static one."""

    text: str
    bounds: Callable[[Any, int], tuple[float | None, float | None]]


@dataclass(frozen=True)
class Spec:
    """What one setting is: unit ("-" dimensionless, "" for text and switches), doc text,
    static range or choices, card rule, card-dependent limit, live (may change while the
    drive runs) or fixed for a run."""

    name: str
    # float, int, bool, str, tuple (a list of strings), dict (a mapping) or list (of mappings:
    # what they hold is the owner's to check)
    kind: type
    unit: str
    doc: str
    lo: float | None = None
    hi: float | None = None
    choices: tuple[str, ...] | None = None
    rule: Rule | None = None
    limit: Limit | None = None
    live: bool = True
    # None stands for "the machine card's value of this attribute" (a model parameter)
    card_default: str | None = None
    # None stands for "off"; where a number is required (a ROS parameter) 0 is written for it
    none_is_zero: bool = False

    @property
    def numeric(self) -> bool:
        return self.kind in (int, float)

    @property
    def optional(self) -> bool:
        """May the field be None (before `resolve` or for good)?"""
        return self.rule is not None or self.card_default is not None or self.none_is_zero

    def range_text(self) -> str:
        if self.choices:
            return ", ".join(self.choices)
        if self.lo is None or self.hi is None:
            return ""
        if self.kind is int:  # every digit: a seed's 4294967295, not 4.29497e+09
            text = f"[{int(self.lo)}, {int(self.hi)}]"
        else:
            text = f"[{self.lo:g}, {self.hi:g}]"
        return text + (f", {self.limit.text}" if self.limit else "")


def param(
    default: Any,
    *,
    unit: str,
    doc: str,
    range: tuple[float, float] | None = None,  # noqa: A002 - the word the schema uses
    choices: tuple[str, ...] | None = None,
    rule: Rule | None = None,
    limit: Limit | None = None,
    live: bool = True,
    card_default: str | None = None,
    none_is_zero: bool = False,
    kind: type | None = None,
) -> Any:
    """A dataclass field declared once: default, unit, range or choices, doc text, card rule,
    live or not (the kind is read from the default, or given for a None default)."""
    if kind is None:
        kind = (
            tuple  # a list of strings (a tuple of numbers: per phase, checked per element)
            if isinstance(default, tuple) and all(isinstance(x, str) for x in default)
            else str
            if choices is not None or isinstance(default, str)
            else bool
            if isinstance(default, bool)
            else int
            if isinstance(default, int)
            else float
        )
    lo, hi = range if range is not None else (None, None)
    spec = Spec("", kind, unit, doc, lo, hi, choices, rule, limit, live, card_default, none_is_zero)
    return field(default=default, metadata={SCHEMA: spec})


def specs(cls_or_cfg: Any) -> dict[str, Spec]:
    """{field name: Spec} of every declared field, in declaration order."""
    out = {}
    for f in dataclasses.fields(cls_or_cfg):
        s = f.metadata.get(SCHEMA)
        if s is not None:
            out[f.name] = dataclasses.replace(s, name=f.name)
    return out


def ranges(
    cls_or_cfg: Any, card: Any = None, decimation: int = 1
) -> dict[str, tuple[float, float]]:
    """{field: (lo, hi)} of every numeric field: the static range, narrowed on `card` by the
    limits that follow from it and from the decimation."""
    out = {}
    for name, s in specs(cls_or_cfg).items():
        if s.lo is None or s.hi is None:
            continue
        lo, hi = s.lo, s.hi
        if s.limit is not None and card is not None:
            lim_lo, lim_hi = s.limit.bounds(card, int(decimation))
            lo = lo if lim_lo is None else max(lo, lim_lo)
            hi = hi if lim_hi is None else min(hi, lim_hi)
        out[name] = (lo, hi)
    return out


def check_value(s: Spec, v: Any, where: str) -> None:
    """Raise ConfigError naming `where` (e.g. 'control: current_bandwidth_hz') unless `v` is
    what the spec accepts (None where the spec allows it)."""
    if v is None:
        if s.optional:
            return
        raise ConfigError(f"{where} must be set, got None")
    if s.kind is bool:
        if not isinstance(v, bool):
            raise ConfigError(f"{where} must be true/false, got {v!r}")
    elif s.kind is tuple:
        if not isinstance(v, (list, tuple)) or not all(isinstance(x, str) for x in v):
            raise ConfigError(f"{where} must be a list of strings, got {v!r}")
    elif s.kind in (dict, list):
        if not isinstance(v, s.kind):
            what = "a mapping" if s.kind is dict else "a list"
            raise ConfigError(f"{where} must be {what}, got {type(v).__name__}")
    elif s.kind is str:
        if not isinstance(v, str) or (s.choices is not None and v not in s.choices):
            what = f"one of {list(s.choices)}" if s.choices is not None else "a string"
            raise ConfigError(f"{where} must be {what}, got {v!r}")
    elif (
        isinstance(v, bool)
        or not isinstance(v, (int, float))
        or not math.isfinite(v)
        or (s.lo is not None and s.hi is not None and not s.lo <= v <= s.hi)
    ):
        what = "an integer" if s.kind is int else "a number"
        raise ConfigError(f"{where} must be {what} in [{s.lo}, {s.hi}], got {v!r}")
    elif s.kind is int and v != int(v):
        raise ConfigError(f"{where} must be an integer in [{s.lo}, {s.hi}], got {v!r}")


def check_fields(cfg: Any, src: str, skip: tuple[str, ...] = ()) -> None:
    """Every declared field of `cfg` checked against its spec; the first bad one raises
    ConfigError '<src>: <key> must be ...'."""
    for name, s in specs(cfg).items():
        if name not in skip:
            check_value(s, getattr(cfg, name), f"{src}: {name}")


def check_limits(cfg: Any, card: Any, decimation: int, src: str) -> None:
    """The fields whose range follows from the card or the decimation checked against it:
    ConfigError '<src>: <key> <value> must be <the limit's text> (...)'."""
    table = specs(cfg)
    for name, (lo, hi) in ranges(cfg, card, decimation).items():
        s, v = table[name], getattr(cfg, name)
        if s.limit is not None and v is not None and not lo <= v <= hi:
            raise ConfigError(
                f"{src}: {name} {v:g} {s.unit} must be {s.limit.text} "
                f"([{lo:g}, {hi:g}] {s.unit} on this card at decimation {int(decimation)})"
            )


def resolve(cfg: Any, card: Any) -> Any:
    """A copy of `cfg` with every field left None that has a card rule filled from `card`
    (every rule reads the card, never another field's explicit value)."""
    kw = {
        name: s.rule.value(card, cfg)
        for name, s in specs(cfg).items()
        if s.rule is not None and getattr(cfg, name) is None
    }
    return dataclasses.replace(cfg, **kw) if kw else cfg


def rule_texts(cls_or_cfg: Any) -> dict[str, str]:
    """{field: text of its card rule} of every field a card rule fills."""
    return {n: s.rule.text for n, s in specs(cls_or_cfg).items() if s.rule is not None}


def _default_text(s: Spec, default: Any) -> str:
    if s.rule is not None:
        return "card rule"
    if s.card_default is not None:
        return f"card `{s.card_default}`"
    if default is None:
        return "off" if s.none_is_zero else "-"
    if isinstance(default, float):
        return f"{default:g}"
    if s.kind is tuple:
        return ", ".join(f"`{x}`" for x in default if x) or "none"
    return str(default).lower() if isinstance(default, bool) else str(default)


def markdown_table(cls: Any) -> str:
    """The docs' table of a config block: key, default, unit, range (or choices and the
    limits from the card), live, what it is (and the card rule that fills it)."""
    rows = [
        "| key | default | unit | range / choices | live | description |",
        "|---|---|---|---|---|---|",
    ]
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    for name, s in specs(cls).items():
        doc = s.doc + (f" (unset: {s.rule.text})" if s.rule is not None else "")
        cells = (
            f"`{name}`",
            _default_text(s, defaults[name]),
            s.unit,
            s.range_text(),
            "yes" if s.live else "no",
            doc,
        )
        rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(rows)


class _Ranged(argparse.Action):
    """Stores an option's value once its schema field accepts it; else ConfigError
    '--flag must be ... in [lo, hi], got v' (the commands print it as one line, exit 2)."""

    def __init__(self, *args: Any, spec: Spec, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.spec = spec

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None):
        check_value(self.spec, values, option_string or self.dest)
        setattr(namespace, self.dest, values)


def option(
    ap: Any,
    flag: str,
    cls: Any,
    name: str | None = None,
    help: str | None = None,
    short: str | None = None,
    **kw: Any,
) -> argparse.Action:
    """Add the numeric option `flag` to the argparse parser `ap`, declared by the field `name`
    (default: the flag's, e.g. --watchdog-s -> watchdog_s) of the schema dataclass `cls`: of
    the field's kind, its default unless `default` is given, its help (the field's doc unless
    given) ending in unit and range, a value outside the range refused as it is parsed."""
    name = name or flag.lstrip("-").replace("-", "_")
    spec = specs(cls)[name]
    if not spec.numeric:
        raise TypeError(f"{cls.__name__}.{name}: an option takes a numeric field")
    if "default" not in kw:
        kw["default"] = {f.name: f.default for f in dataclasses.fields(cls)}[name]
    unit = f" [{spec.unit}]" if spec.unit not in ("", "-") else ""
    text = f"{help or spec.doc}{unit}; range {spec.range_text()}".replace("%", "%%")
    kind = _as_float if spec.kind is float else int64 if spec.kind is int else spec.kind
    flags = (short, flag) if short else (flag,)
    return ap.add_argument(*flags, type=kind, action=_Ranged, spec=spec, help=text, **kw)


def _as_float(text: str) -> float:
    """A ranged option's float: NaN and inf pass to its range check, which names the range."""
    return float(text)


_as_float.__name__ = "float"


INT64_MAX = 2**63 - 1


def finite_float(text: str) -> float:
    """argparse type for every float option (`Parser`): NaN and ±inf refused."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


def int64(text: str) -> int:
    """argparse type for every int option (`Parser`): at most 20 digits, within int64."""
    t = text.strip()
    if len(t) > 20:
        raise argparse.ArgumentTypeError(f"must be an integer within int64, got {t[:24]!r}...")
    try:
        v = int(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not -INT64_MAX - 1 <= v <= INT64_MAX:
        raise argparse.ArgumentTypeError(f"must be an integer within int64, got {text!r}")
    return v


class Parser(argparse.ArgumentParser):
    """argparse with the project's rules for bad input: finite floats, int64 ints, one line
    on a bad option (subcommand parsers inherit it)."""

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.register("type", float, finite_float)
        self.register("type", int, int64)

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: {message.splitlines()[0] if message else 'bad option'}\n")
