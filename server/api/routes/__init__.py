"""One module per REST resource; each defines a ``router`` that ``api/main.py`` includes."""
