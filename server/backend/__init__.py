"""SLAM back-end: place recognition, geometric verification and the pose graph (issue 37)."""
