"""argparse options derived from :class:`TrainConfig`: every field declared with
:func:`~mixer_nerf.train.config.option` becomes the flag ``--name-with-dashes``."""

from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Any

from .train.config import TrainConfig
from .train.config_file import value_type

DEVICE_FLAGS = ("--device", "--backend")
"""Train flags that eval and render take as well."""


def train_options() -> dict[str, dict[str, Any]]:
    """``{"--flag": argparse keyword arguments}`` for each TrainConfig field with help metadata.

    Every default is None so that only what the user typed overrides TrainConfig's defaults, the
    demo settings or a config file; a bool field becomes ``--flag/--no-flag``.
    """
    hints = typing.get_type_hints(TrainConfig)
    options = {}
    for f in dataclasses.fields(TrainConfig):
        if "help" not in f.metadata:
            continue
        kwargs: dict[str, Any] = {"default": None, **f.metadata}
        kind = value_type(hints[f.name])
        if kind is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif "choices" not in kwargs:
            kwargs["type"] = kind
        options["--" + f.name.replace("_", "-")] = kwargs
    return options


def add_options(parser: argparse.ArgumentParser, flags: typing.Iterable[str]) -> None:
    """Add the named train flags (as :func:`train_options` derives them) to ``parser``."""
    options = train_options()
    for flag in flags:
        parser.add_argument(flag, **options[flag])


def typed_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The TrainConfig settings the user typed as train flags."""
    names = (flag[2:].replace("-", "_") for flag in train_options())
    return {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}
