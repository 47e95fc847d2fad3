"""Where the commands' headline items used to be declared; :class:`Item` is re-exported from here.

Every command's results are a typed record now, and each record declares its headline
(``HEADLINE``) and its state rules (``STATES``) itself (:mod:`afmtool.records`), read by
:mod:`afmtool.report.headline`.  The command table (:mod:`afmtool.config.commands`) and the
headline module still import :class:`Item` from here.
"""

from __future__ import annotations

from afmtool.records.base import Item

__all__ = ["Item"]
