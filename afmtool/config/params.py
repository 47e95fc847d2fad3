"""Typed parameter models, one frozen dataclass per command.

Each command resolves its parameters with :func:`afmtool.config.resolve_from`
and saves the effective values next to its outputs.
"""

from __future__ import annotations

__all__ = ["SECTIONS"]

#: Config-file section -> parameter model; commands register here.
SECTIONS: dict[str, type] = {}
