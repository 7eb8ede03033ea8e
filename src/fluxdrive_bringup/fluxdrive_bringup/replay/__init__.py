"""Replay a bag onto the graph: the live replay publisher."""
