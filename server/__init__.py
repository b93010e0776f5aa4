"""The map server: ingest, perception, association, mapping, storage, API."""
