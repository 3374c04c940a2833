"""Platform maths: geodesy/MGRS, terrain AGL, targeting CEP, energy, radio, hop plans, symbols.

Every figure the platform relies on is computed here and checked against the claims ledger
(``claims.yaml``) by ``fischer-gateway selftest``.
"""

__all__: list[str] = []
