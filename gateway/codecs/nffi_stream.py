"""IP1 framing: NFFI documents back to back on a TCP stream, cut into single documents.

What we accept (docs/nffi.md, "Framing"): each document is one ``NFFIMessage`` element, with
or without a namespace prefix, optionally preceded by an XML declaration and whitespace; a
document ends at its closing ``</NFFIMessage>`` tag, or is one self-closing
``<NFFIMessage .../>`` (an empty message, a heartbeat). Nothing else frames it: no length
prefix, no delimiter. Bytes before a document that are not part of it (a stray ``</track>``,
half a document after a reconnect) are skipped and counted as ``fragments``; the document
after them still parses. A buffer that grows past ``max_message_bytes`` without a document
end is a stream we cannot follow: ``is_overflowing`` tells the reader to hang up.
"""

from __future__ import annotations

import re

__all__ = ["MessageSplitter"]

_NAME = rb"(?:[A-Za-z_][A-Za-z0-9_.\-]*:)?NFFIMessage"
#: A document's end: its closing tag, or a self-closing root (an empty message).
_END = re.compile(rb"</" + _NAME + rb"\s*>|<" + _NAME + rb"(?:\s[^<>]*)?/>")
_START = re.compile(rb"<" + _NAME + rb"[\s>/]")
_DECLARATION = re.compile(rb"<\?xml[^>]*\?>\s*\Z")


class MessageSplitter:
    """Cuts an IP1 byte stream into NFFI documents, skipping (and counting) what is not one."""

    def __init__(self, max_message_bytes: int) -> None:
        self.max_message_bytes = max_message_bytes
        #: Pieces of the stream before a document that were not part of it.
        self.fragments = 0
        self._buffer = bytearray()
        self._searched = 0  # bytes already searched for an end without finding one

    @property
    def buffered(self) -> int:
        """Bytes held that are not yet a whole document."""
        return len(self._buffer)

    @property
    def is_overflowing(self) -> bool:
        """More than ``max_message_bytes`` held without a document end."""
        return len(self._buffer) > self.max_message_bytes

    def feed(self, chunk: bytes) -> list[bytes]:
        """Take ``chunk``; return the documents it completed, each from its ``<?xml``/root."""
        self._buffer += chunk
        messages: list[bytes] = []
        while True:
            # Only a tag opened by the last "<" already searched can end in the new bytes
            # (a match holds no other "<"), so the search resumes there, not from the start.
            last_open = self._buffer.rfind(b"<", 0, self._searched)
            start_at = last_open if last_open >= 0 else self._searched
            found = _END.search(self._buffer, start_at)
            if found is None:
                self._searched = len(self._buffer)
                return messages
            piece = bytes(self._buffer[: found.end()])
            del self._buffer[: found.end()]
            self._searched = 0
            starts = [m.start() for m in _START.finditer(piece)]
            if not starts:
                self.fragments += 1  # an end with no document before it
                continue
            start = starts[-1]
            declaration = piece.rfind(b"<?xml", 0, start)
            if declaration >= 0 and _DECLARATION.match(piece, declaration, start):
                start = declaration
            if piece[:start].strip():
                self.fragments += 1
            messages.append(piece[start:])
