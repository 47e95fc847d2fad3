"""``afmtool config init``: write the packaged defaults as a commented TOML file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

__all__ = ["app"]

app = typer.Typer(help="Parameter files.", no_args_is_help=True)


@app.command("init")
def init(
    path: Annotated[Path, typer.Argument(help="Where to write the TOML file.")] = Path("afmtool.toml"),
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing file.")] = False,
) -> None:
    """Write every command's defaults, with help and units, to edit and pass as --config."""
    from afmtool.config.defaults import default_toml
    from afmtool.errors import ConfigError
    from afmtool.runtime.atomic import write_text_atomic

    if path.exists() and not force:
        raise ConfigError(f"{path} exists; use --force to overwrite")
    write_text_atomic(path, default_toml())
    typer.echo(f"wrote {path}")
