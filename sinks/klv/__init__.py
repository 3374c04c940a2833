"""STANAG 4609 KLV: MISB ST 0601 video metadata (docs/klv.md).

One integration, one package.

BER and IMAPB encodings (``ber``, ``imapb``), the ST 0601 local set (``st0601``), an event as
its packet (``uas``), MPEG-TS muxing (``mpegts``), video muxing with ffmpeg (``video``) and the
sink (``sink``).
"""

from __future__ import annotations

from sinks.klv.sink import KlvSink, KlvSinkConfig

__all__ = ["KlvSink", "KlvSinkConfig"]
