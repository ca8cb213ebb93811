"""Vehicle models as pure functions ``transition(x, u, theta)`` and ``observe(x, u, theta)``."""

from .bank import SingleTrackBank, virtual_yaw_rate
from .bank_scale import VirtualScaleBank, virtual_yaw_reading
from .base import BaseModel, Model, VehicleModel, integrate
from .biases import with_input_offset, with_output_biases
from .domains import Interval, ParamDomains
from .dynamic import Dynamic3DOF
from .kinematic import KinematicBicycle
from .sevendof import SevenDOF
from .single_track import SingleTrack
from .tyre_lag import SingleTrackLag

__all__ = ["BaseModel", "Model", "VehicleModel", "integrate", "KinematicBicycle", "Dynamic3DOF",
           "SingleTrackBank", "SevenDOF", "SingleTrack", "SingleTrackLag", "virtual_yaw_rate",
           "VirtualScaleBank", "virtual_yaw_reading", "with_output_biases",
           "with_input_offset", "Interval", "ParamDomains"]

#: name -> class, for the CLI.
REGISTRY = {
    "KinematicBicycle": KinematicBicycle,
    "Dynamic3DOF": Dynamic3DOF,
    "SevenDOF": SevenDOF,
    "SingleTrackBank": SingleTrackBank,
    "SingleTrack": SingleTrack,
    "SingleTrackLag": SingleTrackLag,
}
