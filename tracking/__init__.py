"""The multi-target tracker: detections in, one track per real object out.

``Tracker`` (``tracking.tracker``) groups detections into sensor frames, assigns each frame's
detections to tracks jointly (global nearest neighbour on Mahalanobis costs), filters each
track with a constant-velocity Kalman filter (``tracking.kalman``) and runs its life:
tentative, confirmed, coasting, deleted. The fusion processor (``processors.fusion``) is its
only user in the daemon.
"""

from tracking.settings import DEFAULT_CLASSES, OTHER, TrackerCounts, TrackerSettings
from tracking.tracker import Tracker

__all__ = ["DEFAULT_CLASSES", "OTHER", "Tracker", "TrackerCounts", "TrackerSettings"]
