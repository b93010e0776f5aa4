"""Offline tools beside the runtime: segmentation training data, training and logit adjustment,
and the demo's process orchestration. They may import server, edge, sim and shared; the server
and the edge never import them (import-linter contracts in pyproject.toml)."""
