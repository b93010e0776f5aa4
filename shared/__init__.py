"""Conventions and pure code shared by the edge agent, the server and the simulator.

Nothing here opens sessions, sockets or models; files are read only when asked.
"""
