"""The CDR codec of the per-sample messages lives in the engine (fluxdrive.io.cdr, no ROS
import); re-exported here for the nodes."""

from fluxdrive.io.cdr import (  # noqa: F401 - re-exported: the one definition
    ENCAPSULATION,
    Codec,
    Decoder,
    Leaf,
    leaves,
    msg_dir,
    msg_text,
    read_strings,
)
