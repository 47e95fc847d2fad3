"""Text that comes from a file (names, units, labels), decoded and cleaned once, where it is read.

Instrument files hold their strings as C buffers (NUL-padded, sometimes with a NUL inside),
as UTF-16 (LabVIEW, Windows tools), as Latin-1 (``µm`` in a JPK or Chiaro header) or as
UTF-8.  A NUL that reaches a writer breaks it (HDF5 variable-length strings refuse embedded
NULs; a CSV ``# units.x:`` line would be cut), and a newline would split a CSV header.  So
every channel name and unit is passed through :func:`clean_label` when its
:class:`~afmtool.io.capture.ChannelSpec` is made, and readers decode raw bytes with
:func:`decode_file_text`; writers never see either raw.
"""

from __future__ import annotations

__all__ = ["MAX_LABEL_CHARS", "decode_file_text", "clean_label"]

#: Longest channel name or unit kept, characters (longer is cut; no instrument writes more).
MAX_LABEL_CHARS = 256


def _looks_utf16(raw: bytes) -> str | None:
    """``"utf-16-le"``/``"utf-16-be"`` for BOM-less UTF-16 of ASCII text (every other byte NUL), else None."""
    if len(raw) < 2 or len(raw) % 2:
        return None
    if not any(raw[1::2]) and all(raw[0::2]):
        return "utf-16-le"
    if not any(raw[0::2]) and all(raw[1::2]):
        return "utf-16-be"
    return None


def decode_file_text(raw: bytes | str) -> str:
    """Bytes from a file as text: UTF-16 (with a byte-order mark, or ASCII in 16-bit units), UTF-8, else Latin-1.

    Latin-1 is the fallback because every byte is a Latin-1 character (so the
    decoding never fails) and it is what older instrument software writes.  A
    ``str`` whose characters are UTF-16 bytes read one by one (``"V\\x00o\\x00"``,
    as some libraries hand them over) is decoded again.
    """
    if isinstance(raw, str):
        if "\x00" not in raw or any(ord(c) > 255 for c in raw):
            return raw
        raw = raw.encode("latin-1")  # a NUL inside: perhaps UTF-16 bytes handed over one per character
    raw = bytes(raw)
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
        return raw.decode("utf-16", errors="replace")
    stripped = raw.rstrip(b"\x00")
    stripped += b"\x00" * (len(stripped) % 2)  # a UTF-16-LE string loses its last NUL to rstrip
    encoding = _looks_utf16(stripped)
    if encoding is not None:
        return stripped.decode(encoding, errors="replace")
    if raw[:3] == b"\xef\xbb\xbf":
        raw = raw[3:]
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def clean_label(text: bytes | str) -> str:
    """A channel name or unit as one printable line: decoded, NULs and control characters removed, trimmed.

    Idempotent, so a record copied (``dataclasses.replace``) is cleaned again at no harm.
    """
    text = decode_file_text(text)
    if not text.isprintable():
        text = "".join(c if c.isprintable() else (" " if c in "\t\r\n" else "") for c in text)
    return text.strip()[:MAX_LABEL_CHARS]
