"""Vehicle orientation: `orient`, the rover's motion between two overlapping looks by visual
odometry (toolbox/odometry), its heading held by the sun sensor; navigate and route-follow use it between
their moves."""
from .commands import module
from .look import Look, take_look
from .odometer import Odometer, OrientFailed, Outcome, odometer_of, orient_here
from .settings import OrientSettings

__all__ = ["Look", "Odometer", "OrientFailed", "OrientSettings", "Outcome", "module", "odometer_of", "orient_here",
           "take_look"]
