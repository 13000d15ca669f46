"""Helpers shared by the command modules."""

from __future__ import annotations

import argparse
import json
import sys
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
    return json.dumps(_finite(obj), indent=indent, allow_nan=False, default=_json_default)


def _finite(value: Any) -> Any:
    import math

    import numpy as np

    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.ndarray):
        return _finite(value.tolist())
    return value


def _json_default(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
