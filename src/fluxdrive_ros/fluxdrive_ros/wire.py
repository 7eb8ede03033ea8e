"""Engine rows <-> per-sample messages as CDR bytes: the one mapping lives in the engine
(fluxdrive.io.messages, no ROS import); re-exported here for the nodes."""

from fluxdrive.io.messages import (  # noqa: F401 - re-exported: the one definition
    STATUS_SENSOR_CLIP,
    STATUS_SIMULATED,
    STATUS_STALE_COMMAND,
    ControlWire,
    EstimateWire,
    FrameWire,
    RowCodec,
    Stamp,
    TruthWire,
    duty_commander,
    fault_name,
)
