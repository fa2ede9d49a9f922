"""The command line loads only the module of the command it runs (`services.cli.main`)."""

from __future__ import annotations

import json
import subprocess
import sys

import typer.main

from services import cli


def _names(app: typer.Typer) -> set[str]:
    group = typer.main.get_command(app)
    return set(group.commands)  # type: ignore[attr-defined]


def test_every_command_is_mapped_to_the_module_that_registers_it() -> None:
    assert _names(cli.app) == set(cli.COMMANDS)
    for command, module in cli.COMMANDS.items():
        assert command in _names(cli.build_app((module,))), (command, module)


def test_import_does_not_load_the_pipeline_or_the_orm() -> None:
    code = (
        "import sys, json\n"
        "from services.cli import main\n"
        "try:\n"
        "    main(['import', '--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = ('scipy', 'sqlalchemy.orm', 'workers.job', 'open3d')\n"
        "print(json.dumps(sorted(m for m in heavy if m in sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "citytherm import" in out
    assert json.loads(out.strip().splitlines()[-1]) == []


def test_help_lists_every_command() -> None:
    code = "from services.cli import main; main(['--help'])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout
    for command in cli.COMMANDS:
        assert command in out
