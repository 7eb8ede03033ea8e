"""Measure the graph: benchmarks, the soak test and the software-in-the-loop bench."""
