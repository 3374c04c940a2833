"""KLV metadata (SMPTE 336, MISB ST 0601 / ST 1201) and its MPEG-TS carriage (STANAG 4609).

``ber`` frames packets, ``imapb`` maps floats, ``st0601`` is the UAS Datalink Local Set;
``mpegts`` writes the asynchronous KLV elementary stream in a transport stream.
"""
