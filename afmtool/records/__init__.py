"""What each command found, as typed, frozen records (issue 29, item 2): :mod:`afmtool.records.base`.

One module per command (``records/invols.py`` ...) declares its root record, the
``results`` of its ``report.json``, with the headline on it.  Standard library only.
"""

from afmtool.records.base import Item, Record, State, StateRule, inline, json_key, lookup, optional, record, resolve

__all__ = ["Item", "Record", "State", "StateRule", "inline", "json_key", "lookup", "optional", "record", "resolve"]
