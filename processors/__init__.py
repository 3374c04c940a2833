"""Processors shipped with fischer-gateway: fusion, and the counter-UAS cue.

Each is found through the entry-point group ``fischer_gateway.processors`` and configured
under ``processors:``; the algorithms they run live in ``gateway.flow`` and ``gateway.domain``.
"""
