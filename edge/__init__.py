"""The edge agent: sensor sources, tracking frontend, durable outbox, daemon."""
