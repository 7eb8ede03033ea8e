"""Look into a running graph: topics, nodes, parameters, fault reset; parameter docs."""
