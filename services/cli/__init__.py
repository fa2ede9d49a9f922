"""The `citytherm` command line (typer). No numerical work here: commands parse arguments, call
the pipeline or the database layer, and print with rich.

Each command group lives in its own module exposing `register(root)`. `main()` loads only the
module of the command asked for (`citytherm import` never loads the pipeline, SciPy or the ORM:
about a second of start-up on a small machine); `app` (all commands) is built on first use.
"""

from __future__ import annotations

import sys
from types import ModuleType
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


def _module(name: str) -> ModuleType:
    """The command module `services.cli.<name>`, imported now (explicit imports: the layer test
    sees them)."""
    if name == "model_cmd":
        from services.cli import model_cmd as module
    elif name == "synth_cmd":
        from services.cli import synth_cmd as module
    elif name == "run_cmd":
        from services.cli import run_cmd as module
    elif name == "compare_cmd":
        from services.cli import compare_cmd as module
    elif name == "db_cmd":
        from services.cli import db_cmd as module
    elif name == "results_cmd":
        from services.cli import results_cmd as module
    elif name == "apikey_cmd":
        from services.cli import apikey_cmd as module
    elif name == "serve_cmd":
        from services.cli import serve_cmd as module
    elif name == "worker_cmd":
        from services.cli import worker_cmd as module
    else:
        raise KeyError(f"no command module {name!r}")
    return module


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
        _module(name).register(root)
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
