"""The options an estimator takes (``-e NAME:OPTION=VALUE``, and the flags that set the same),
read off the fields of its config dataclass, so that there is no second table to keep in step.

A field declared with :func:`option` is one; the others are internal knobs no user sets.  Its
annotation says what it takes: ``int``, ``float``, ``str`` or ``Path``, or a ``Literal`` of the
values it is one of (``None`` among them is written ``none``).  Its default is what it is when
not given.  :func:`check_choices` is the config's own check of those values.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mosaic_cli.errors import BadInput

# The key of a field's metadata that makes it an option; its value: the estimators of the config
# that take it (None: all of them).
_OPTION = "mosaic_option"
# The key that marks an option as an ablation's: accepted, but not listed in ``--help``
# (docs/developer/estimator-options.md lists them for developers).
_ABLATION = "mosaic_ablation"

# How the value of an option of each kind is written in the help.
_PLACEHOLDERS: dict[type, str] = {int: "N", float: "X", str: "TEXT", Path: "FILE"}


def option(default: Any, *, only: tuple[str, ...] | None = None, ablation: bool = False) -> Any:
    """A config field that is an option (``default``: its value when not given); ``only``: the
    estimators of the config that take it, when not all do (``reset-every``: the LSTM's);
    ``ablation``: a setting for experiments (the paper's table, the model card's runs), which a
    user has no reason to change: accepted, not listed in the help."""
    return dataclasses.field(default=default, metadata={_OPTION: only, _ABLATION: ablation})


@dataclass(frozen=True)
class Option:
    """One option: its name as written (``reset-every``), what its value is read as (``kind``),
    the values it is one of (None: any of its kind) and its default."""

    key: str
    kind: type
    choices: tuple | None = None
    default: Any = None
    ablation: bool = False  # an experiment's setting: not listed in the help

    def read(self, estimator: str, value: Any) -> Any:
        """The value of ``NAME:KEY=VALUE`` (text) or of a flag (already typed); ``BadInput`` for
        a value not of its kind.  Whether it is one of the choices is the config's check."""
        if self.kind is int:
            try:
                return int(value)
            except (TypeError, ValueError):
                raise BadInput(f"estimator {estimator!r}: {self.key} must be a whole number, got {value!r}") from None
        if self.kind is float:
            try:
                return float(value)
            except (TypeError, ValueError):
                raise BadInput(f"estimator {estimator!r}: {self.key} must be a number, got {value!r}") from None
        if self.kind is Path:
            return str(value)  # a file name keeps its case
        text = str(value).lower()
        return None if text == "none" and self.choices is not None and None in self.choices else text

    def listed(self) -> str:
        """The choices as a sentence: ``lk, ecc or none``, ``1, 5, 9``."""
        named = [str(c) for c in self.choices or () if c is not None]
        return ", ".join(named) + (" or none" if self.choices is not None and None in self.choices else "")

    def usage(self) -> str:
        """``patches=1|5|9 (1)``, ``chunk=N (16)``, ``weights=FILE``: how it is written, and its default."""
        if self.choices is not None:
            values = "|".join("none" if c is None else str(c) for c in self.choices)
        else:
            values = _PLACEHOLDERS[self.kind]
        default = "" if self.default is None else f" ({self.default})"
        return f"{self.key}={values}{default}"


def options_of(config: type, estimator: str | None = None) -> dict[str, Option]:
    """The options of the dataclass ``config`` by field name, in field order; with ``estimator``,
    only those it takes."""
    hints = typing.get_type_hints(config)
    found = {}
    for f in dataclasses.fields(config):
        if _OPTION not in f.metadata:
            continue
        only = f.metadata[_OPTION]
        if estimator is not None and only is not None and estimator not in only:
            continue
        kind, choices = _kind_and_choices(hints[f.name])
        found[f.name] = Option(f.name.replace("_", "-"), kind, choices, f.default, bool(f.metadata.get(_ABLATION, False)))
    return found


def check_choices(config: Any) -> None:
    """``BadInput`` for the first option of the dataclass instance ``config`` whose value is none
    of its choices, named as written: ``refine must be one of lk, ecc or none, got 'sift'``."""
    for name, opt in options_of(type(config)).items():
        value = getattr(config, name)
        if opt.choices is not None and value not in opt.choices:
            raise BadInput(f"{opt.key} must be one of {opt.listed()}, got {value!r}")


def _kind_and_choices(annotation: Any) -> tuple[type, tuple | None]:
    """``int | None`` -> (int, None); ``Literal["lk", "ecc"] | None`` -> (str, ("lk", "ecc", None))."""
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    members = typing.get_args(annotation) if union else (annotation,)
    nullable = type(None) in members
    (inner,) = [m for m in members if m is not type(None)]
    if typing.get_origin(inner) is typing.Literal:
        values = typing.get_args(inner)
        return type(values[0]), values + ((None,) if nullable else ())
    return inner, None
