"""Watch a running graph: the scope (tap node, web server, page) and the Foxglove bridge."""
