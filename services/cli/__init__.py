"""The `citytherm` command line (typer). No numerical work here: commands parse arguments, call
the pipeline or the database layer, and print with rich.

Each command group lives in its own module exposing `register(root)`. `main()` loads only the
module of the command asked for (`citytherm import` never loads the pipeline, SciPy or the ORM:
about a second of start-up on a small machine); `app` (all commands) is built on first use.
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

import typer

#: command (or command group) -> the module under `services.cli` that registers it, in help order
COMMANDS: dict[str, str] = {
    "model": "model_cmd",
    "synth": "synth_cmd",
    "run": "run_cmd",
    "compare": "compare_cmd",
    "db": "db_cmd",
    "import": "db_cmd",
    "export": "db_cmd",
    "results": "results_cmd",
    "apikey": "apikey_cmd",
    "serve": "serve_cmd",
    "worker": "worker_cmd",
}


def _root() -> None:
    """citytherm: refine TIR camera poses against a city model, extract thermal textures,
    detect heat-leak candidates, and write CityGML appearances."""


def build_app(modules: tuple[str, ...] | None = None) -> typer.Typer:
    """The typer app with the commands of `modules` (names under `services.cli`; None: all)."""
    root = typer.Typer(
        name="citytherm",
        help="Thermal-infrared image sequences onto CityGML building models.",
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_show_locals=False,
    )
    root.callback()(_root)
    for name in dict.fromkeys(COMMANDS.values()) if modules is None else modules:
        importlib.import_module(f"services.cli.{name}").register(root)
    return root


_app: typer.Typer | None = None


def __getattr__(name: str) -> Any:
    """`services.cli.app`: every command (built on first access)."""
    global _app
    if name != "app":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if _app is None:
        _app = build_app()
    return _app


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point: only the module of the command named in `argv` (default
    `sys.argv[1:]`) is loaded; help, options before the command or an unknown name load all."""
    args = sys.argv[1:] if argv is None else argv
    module = COMMANDS.get(args[0]) if args else None
    build_app((module,) if module else None)(args=args, prog_name="citytherm")
