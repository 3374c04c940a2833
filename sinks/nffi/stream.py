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

from gateway.transports.xmlstream import RootSplitter

__all__ = ["MessageSplitter"]

_NAME = rb"(?:[A-Za-z_][A-Za-z0-9_.\-]*:)?NFFIMessage"
#: A document's end: its closing tag, or a self-closing root (an empty message).
_END = re.compile(rb"</" + _NAME + rb"\s*>|<" + _NAME + rb"(?:\s[^<>]*)?/>")
_START = re.compile(rb"<" + _NAME + rb"[\s>/]")


class MessageSplitter(RootSplitter):
    """Cuts an IP1 byte stream into NFFI documents, skipping (and counting) what is not one."""

    def __init__(self, max_message_bytes: int) -> None:
        super().__init__(_START, _END, max_message_bytes)
