"""The `citytherm` command line (typer). No numerical work here: commands parse arguments, call
the pipeline or the database layer, and print with rich.

Each command group lives in its own module exposing `register(root)`.
"""

from __future__ import annotations

import typer

from services.cli import (
    apikey_cmd,
    compare_cmd,
    db_cmd,
    model_cmd,
    results_cmd,
    run_cmd,
    serve_cmd,
    synth_cmd,
    worker_cmd,
)

app = typer.Typer(
    name="citytherm",
    help="Thermal-infrared image sequences onto CityGML building models.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)

for _module in (
    model_cmd,
    synth_cmd,
    run_cmd,
    compare_cmd,
    db_cmd,
    results_cmd,
    apikey_cmd,
    serve_cmd,
    worker_cmd,
):
    _module.register(app)


@app.callback()
def _root() -> None:
    """citytherm: refine TIR camera poses against a city model, extract thermal textures,
    detect heat-leak candidates, and write CityGML appearances."""


def main() -> None:
    """Console-script entry point."""
    app()
