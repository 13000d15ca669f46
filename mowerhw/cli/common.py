"""Helpers shared by the command modules."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mowerhw.config import EX_CONFIG, Config, ConfigError, default_config, load_config


def add_config_argument(parser: argparse.ArgumentParser, required: bool = False) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        required=required,
        metavar="FILE",
        help="runtime config YAML (default: built-in defaults with the shipped calibration)",
    )


def add_plot_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """``--plot [PNG]``: a figure, at the given path or (bare flag) next to the input."""
    parser.add_argument(
        "--plot", nargs="?", type=Path, const=True, default=None, metavar="PNG", help=help
    )


def load_config_or_exit(path: Path | None) -> Config:
    """The validated config, or print every problem and exit 78 (EX_CONFIG)."""
    try:
        return load_config(path) if path is not None else default_config()
    except ConfigError as exc:
        report_config_error(exc)
        raise SystemExit(EX_CONFIG) from None


def report_config_error(exc: ConfigError) -> None:
    print(f"mowerhw: invalid configuration\n{exc}", file=sys.stderr)


def print_json(obj: Any, indent: int | None = 2) -> None:
    """Print ``obj`` as strict JSON (RFC 8259): NaN and infinities become null."""
    print(strict_json(obj, indent))


def strict_json(obj: Any, indent: int | None = None) -> str:
    """``obj`` as strict JSON text: numpy values converted, non-finite numbers as null."""
    from mowerhw.common.strictjson import finite

    return json.dumps(finite(obj), indent=indent, allow_nan=False, default=_json_default)


def _json_default(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def number(
    kind: type = float,
    *,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
) -> Callable[[str], Any]:
    """An argparse ``type``: a finite number of ``kind`` within the bounds, or an error
    naming them."""
    noun = "whole number" if kind is int else "number"

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"{text!r} is not a {noun}") from None
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite {noun}")
        for bound, ok, words in (
            (gt, lambda v, b: v > b, "greater than"),
            (ge, lambda v, b: v >= b, "at least"),
            (le, lambda v, b: v <= b, "at most"),
        ):
            if bound is not None and not ok(value, bound):
                raise argparse.ArgumentTypeError(
                    f"{text} is out of range: must be {words} {bound:g}"
                )
        return value

    parse.__name__ = noun
    return parse


#: a random seed (numpy takes 0 … 2**32 - 1)
seed_number = number(int, ge=0, le=2**32 - 1)


def _writable_ancestor(path: Path) -> Path:
    """The nearest existing folder at or above ``path``'s parent, if the user may write
    there (the output can be made); ArgumentTypeError otherwise."""
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write {path}: {folder} is not a writable folder")
    return folder


def output_file(text: str) -> Path:
    """An argparse ``type``: a file that can be written (checked before any work)."""
    path = Path(text)
    if not text or path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is a folder; give a file name")
    if path.exists() and not os.access(path, os.W_OK):
        raise argparse.ArgumentTypeError(f"cannot write {path}: not writable")
    _writable_ancestor(path)
    return path


def output_dir(text: str) -> Path:
    """An argparse ``type``: a folder that exists or can be made, and can be written."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a folder")
    if path.exists():
        if not os.access(path, os.W_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"cannot write into {path}")
    else:
        _writable_ancestor(path)
    return path
