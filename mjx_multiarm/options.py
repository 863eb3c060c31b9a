"""Typed configurations: frozen dataclasses whose fields carry their own help text.

A configuration is a (nested) frozen dataclass; each field is declared once, with its
default, type and help (:func:`option`), and checked in ``__post_init__`` of the class that
owns it. From that one declaration this module derives what the rest of the project needs:

- :func:`to_dict` / :func:`from_dict`: JSON data and back (unknown keys are an error that
  names them; missing keys take their defaults), e.g. a run's ``config.json``;
- :func:`add_flags` / :func:`overrides`: one command-line flag per leaf field, as
  ``--section.field VALUE`` (always) and ``--field VALUE`` (when the name is unique or the
  field declares its own ``flag``); booleans also take ``--field`` / ``--no-field``;
- :func:`apply`: a configuration with overrides ``{"section.field": value}`` applied and
  checked once (every ``__post_init__`` runs on the final values, not on halfway states).

Field types understood: bool, int, float, str, tuples of those (``1,2,3``), unions with
None (``none``) and ``float | tuple[float, ...]``; ``parse`` in :func:`option` overrides
the parsing of a field's command-line text (e.g. team-size ranges ``1-4``).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import types
import typing


def option(default, help: str, *, flag: str | None = None, parse=None, choices=None):
    """A dataclass field with its help text; ``flag``: its short command-line name (default:
    the field's name); ``parse``: str -> value for the command line; ``choices``: allowed values."""
    return dataclasses.field(default=default, metadata={"help": help, "flag": flag, "parse": parse, "choices": choices})


@dataclasses.dataclass(frozen=True)
class Leaf:
    """One settable field of a nested configuration: ``path`` like ``train.sac.gamma``."""

    path: str
    field: dataclasses.Field
    type: object

    @property
    def name(self) -> str:
        return self.field.metadata.get("flag") or self.field.name


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _is_config(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def leaves(cls, prefix: str = "") -> list[Leaf]:
    """Every settable field of configuration class ``cls``, depth first."""
    found = []
    for f in dataclasses.fields(cls):
        tp = _hints(cls)[f.name]
        if _is_config(tp):
            found += leaves(tp, f"{prefix}{f.name}.")
        else:
            found.append(Leaf(prefix + f.name, f, tp))
    return found


def to_dict(config) -> dict:
    """JSON-ready nested dict of a configuration (tuples as lists)."""
    def plain(value):
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (tuple, list)):
            return [plain(v) for v in value]
        return value

    return plain(dataclasses.asdict(config))


def _coerce(tp, value, where: str):
    """``value`` (JSON data) as type ``tp``: lists become tuples, ints floats where needed."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        sequence = isinstance(value, (list, tuple))
        match = next((a for a in args if a is not type(None) and (typing.get_origin(a) is tuple) == sequence), None)
        if match is None:
            raise ValueError(f"{where}: expected {tp}, got {value!r}")
        return _coerce(match, value, where)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}: expected a list, got {value!r}")
        item = args[0]
        return tuple(_coerce(item, v, where) for v in value)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp in (bool, int, float, str) and not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
        raise ValueError(f"{where}: expected {tp.__name__}, got {value!r}")
    return value


def from_dict(cls, data: dict, where: str = "config"):
    """Configuration ``cls`` from nested JSON data (see the module docstring)."""
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object of {cls.__name__} fields, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {unknown} of {cls.__name__}; known: {sorted(fields)}")
    values = {}
    for name, value in data.items():
        tp = _hints(cls)[name]
        values[name] = from_dict(tp, value, f"{where}.{name}") if _is_config(tp) else _coerce(tp, value, f"{where}.{name}")
    return cls(**values)


def apply(config, changes: dict):
    """``config`` with ``{"a.b": value}`` changes applied, built (and checked) once."""
    data = to_dict(config)
    known = {leaf.path for leaf in leaves(type(config))}
    for path, value in changes.items():
        if path not in known:
            raise ValueError(f"unknown setting {path!r} of {type(config).__name__}")
        *sections, name = path.split(".")
        node = data
        for section in sections:
            node = node[section]
        node[name] = list(value) if isinstance(value, tuple) else value
    return from_dict(type(config), data)


def _parse_bool(text: str) -> bool:
    value = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}.get(text.lower())
    if value is None:
        raise argparse.ArgumentTypeError(f"expected 0 or 1, got {text!r}")
    return value


def _parser(tp):
    """str -> value of type ``tp`` for the command line."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        optional = type(None) in args
        rest = [a for a in args if a is not type(None)]
        scalar = next((a for a in rest if typing.get_origin(a) is not tuple), None)
        sequence = next((a for a in rest if typing.get_origin(a) is tuple), None)

        def parse(text):
            if optional and text.lower() in ("none", "null"):
                return None
            if sequence is not None and ("," in text or scalar is None):
                return _parser(sequence)(text)
            return _parser(scalar)(text)

        return parse
    if origin is tuple:
        item = _parser(typing.get_args(tp)[0])
        return lambda text: tuple(item(part) for part in text.split(","))
    if tp is bool:
        return _parse_bool
    if tp in (int, float, str):
        def parse(text):
            try:
                return tp(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"expected {tp.__name__}, got {text!r}") from None

        return parse
    raise TypeError(f"no command-line parser for fields of type {tp}")


def value_at(config, path: str):
    """The value of leaf ``path`` (``a.b.c``) of a configuration."""
    for name in path.split("."):
        config = getattr(config, name)
    return config


def add_flags(parser: argparse.ArgumentParser, base, title: str = "settings", default_label: str = "default") -> None:
    """One flag per leaf of configuration ``base`` (see the module docstring), its help
    showing ``base``'s value; values land under the leaf's path in the namespace only when
    given (read them with :func:`overrides`)."""
    all_leaves = leaves(type(base))
    counts = {}
    for leaf in all_leaves:
        counts[leaf.name] = counts.get(leaf.name, 0) + 1
    groups = {}
    for leaf in all_leaves:
        section = leaf.path.rpartition(".")[0] or title
        group = groups.setdefault(section, parser.add_argument_group(section))
        names = [f"--{leaf.path.replace('_', '-')}"]
        short = f"--{leaf.name.replace('_', '-')}"
        if counts[leaf.name] == 1 and short not in names and short not in parser._option_string_actions:
            names.insert(0, short)
        meta = leaf.field.metadata
        helptext = f"{meta.get('help', '')} ({default_label} {_show(value_at(base, leaf.path))})".strip()
        common = {"dest": leaf.path, "default": argparse.SUPPRESS, "help": helptext}
        if leaf.type is bool:
            group.add_argument(*names, nargs="?", const=True, type=_parse_bool, metavar="0|1", **common)
            negative = f"--no-{leaf.name.replace('_', '-')}"
            if counts[leaf.name] == 1 and negative not in parser._option_string_actions:
                group.add_argument(negative, dest=leaf.path, action="store_const", const=False, default=argparse.SUPPRESS,
                                   help=argparse.SUPPRESS)
        else:
            group.add_argument(*names, type=meta.get("parse") or _parser(leaf.type), choices=meta.get("choices"),
                               metavar=None if meta.get("choices") else leaf.name.upper(), **common)


def _show(value) -> str:
    if isinstance(value, tuple):
        return ",".join(map(str, value))
    return str(value)


def overrides(namespace: argparse.Namespace, cls) -> dict:
    """``{path: value}`` of the leaves of ``cls`` given on the command line."""
    given = vars(namespace)
    return {leaf.path: given[leaf.path] for leaf in leaves(cls) if leaf.path in given}
