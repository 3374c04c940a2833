"""Ground truth against tracks: GOSPA and the track-picture metrics of ``fischer-gateway score``.

``files`` reads a truth file (``simulate --truth``) and a JSONL archive, ``score`` computes
the metrics (definitions in its docstring and docs/tracking.md), ``gospa`` the metric itself,
``replay`` runs a scenario offline through a tracker, ``report`` prints a score.
"""
