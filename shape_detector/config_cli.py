"""Command-line flags for the detector's settings, from their one declaration.

``add_detector_flags(parser, "accurate")`` adds ``--preset`` and one ``--name`` flag per
setting of :class:`~shape_detector.detector_config.DetectorConfig` (``--max-objects 10``;
booleans as ``--free-space`` / ``--no-free-space``); argparse refuses invalid values with
the reason. ``config_from_args(args)`` turns the parsed flags into a config: the preset,
with the flags given on top.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from typing import Any

from .detector_config import PRESETS, DetectorConfig, detector_specs, preset
from .settings import Spec, check, valid_values

#: dest of the preset flag; flags of settings use their setting names as dest
_PRESET_DEST = "preset"


def _parser_for(spec: Spec) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        value: Any = text
        if spec.kind is int:
            try:
                value = int(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{spec.name} must be an integer, got {text!r}") from None
        elif spec.kind is float:
            try:
                value = float(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{spec.name} must be a number, got {text!r}") from None
        problem = check(spec, value)
        if problem is not None:
            raise argparse.ArgumentTypeError(problem)
        return value

    parse.__name__ = spec.kind.__name__
    return parse


def add_detector_flags(parser: argparse.ArgumentParser, default_preset: str = "realtime",
                       only: Iterable[str] | None = None, title: str = "detector settings") -> None:
    """``--preset`` and a flag per detector setting (those in ``only``, default all) in a
    group of ``parser``; defaults shown are the preset's, a flag not given keeps the preset's value."""
    group = parser.add_argument_group(title, "defaults are the preset's (docs/parameters.md lists them)")
    group.add_argument("--preset", dest=_PRESET_DEST, default=default_preset, choices=tuple(PRESETS),
                       help=f"settings preset (default {default_preset})")
    shown = preset(default_preset)
    wanted = set(only) if only is not None else None
    for name, spec in detector_specs().items():
        if wanted is not None and name not in wanted:
            continue
        flag = "--" + name.replace("_", "-")
        default = getattr(shown, name)
        if spec.kind is bool:
            group.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None,
                               help=f"{spec.doc} (preset: {'on' if default else 'off'})")
        else:
            group.add_argument(flag, dest=name, type=_parser_for(spec), default=None, metavar=name.upper(),
                               help=f"{spec.doc}; {valid_values(spec)} (preset: {default!r})")


def add_setting_flags(group: Any, all_specs: dict[str, Spec], names: Iterable[str]) -> None:
    """A ``--name`` flag (dest ``name``, default the setting's) for each of ``names`` of
    ``all_specs`` (e.g. :func:`~shape_detector.settings.specs` of the node's config) on
    ``group`` (a parser or an argument group); invalid values are refused with the reason."""
    for name in names:
        spec = all_specs[name]
        group.add_argument("--" + name.replace("_", "-"), dest=name, type=_parser_for(spec), default=spec.default,
                           metavar=name.upper(), help=f"{spec.doc}; {valid_values(spec)} (default {spec.default!r})")


def config_from_args(args: argparse.Namespace, **changes: Any) -> DetectorConfig:
    """The preset ``--preset`` names with every given flag, then ``changes``, applied."""
    given = {k: v for k, v in vars(args).items() if k in detector_specs() and v is not None}
    return preset(getattr(args, _PRESET_DEST, "realtime"), **{**given, **changes})
