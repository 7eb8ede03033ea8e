"""Record a graph: the recorder node (the bag writer it feeds is fluxdrive.io.bagwriter)."""
