"""SLAM back-end: place recognition, geometric verification, the pose graph and the stage that runs them."""
