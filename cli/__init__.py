"""The `wardmap` command line: thin entry points over the library."""
