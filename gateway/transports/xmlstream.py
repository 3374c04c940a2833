"""XML documents back to back on a byte stream, cut into single documents by their root tag.

CoT over TCP (``<event>`` ... ``</event>``) and NFFI over IP1 (``<NFFIMessage>`` ...) have no
framing but the root element itself. ``RootSplitter`` takes the stream in chunks and returns
each document whole, from its ``<?xml`` declaration (when one directly precedes it) or its
root's start tag to the end the caller's pattern matches. What stands before a document and
is not part of it (a stray closing tag, half a document after a reconnect) is skipped and
counted in ``fragments``. More than ``max_bytes`` held without an end is a stream nobody can
follow: ``is_overflowing`` tells the reader to hang up. Each byte is searched for an end once
(a chunk a byte at a time costs no re-scan of what is held), so a slow sender costs linear time.
"""

from __future__ import annotations

import re

__all__ = ["RootSplitter"]

_DECLARATION = re.compile(rb"<\?xml[^>]*\?>\s*\Z")


class RootSplitter:
    """Cuts a byte stream into documents whose root starts at ``start`` and ends at ``end``.

    ``end`` must match a single tag (it starts with ``<`` and holds no other ``<``), which is
    what lets the search resume where it left off.
    """

    def __init__(self, start: re.Pattern[bytes], end: re.Pattern[bytes], max_bytes: int) -> None:
        self.max_bytes = max_bytes
        #: Pieces of the stream before a document that were not part of it.
        self.fragments = 0
        self._start = start
        self._end = end
        self._buffer = bytearray()
        self._searched = 0  # bytes already searched for an end without finding one

    @property
    def buffered(self) -> int:
        """Bytes held that are not yet a whole document."""
        return len(self._buffer)

    @property
    def is_overflowing(self) -> bool:
        """More than ``max_bytes`` held without a document end."""
        return len(self._buffer) > self.max_bytes

    def feed(self, chunk: bytes) -> list[bytes]:
        """Take ``chunk``; return the documents it completed, each from its ``<?xml``/root."""
        self._buffer += chunk
        documents: list[bytes] = []
        while True:
            # Only a tag opened by the last "<" already searched can end in the new bytes
            # (a match holds no other "<"), so the search resumes there, not from the start.
            last_open = self._buffer.rfind(b"<", 0, self._searched)
            start_at = last_open if last_open >= 0 else self._searched
            found = self._end.search(self._buffer, start_at)
            if found is None:
                self._searched = len(self._buffer)
                return documents
            piece = bytes(self._buffer[: found.end()])
            del self._buffer[: found.end()]
            self._searched = 0
            starts = [m.start() for m in self._start.finditer(piece)]
            if not starts:
                self.fragments += 1  # an end with no document before it
                continue
            start = starts[-1]
            declaration = piece.rfind(b"<?xml", 0, start)
            if declaration >= 0 and _DECLARATION.match(piece, declaration, start):
                start = declaration
            if piece[:start].strip():
                self.fragments += 1
            documents.append(piece[start:])
