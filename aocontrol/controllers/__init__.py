"""Controllers: one interface (:class:`ControllerBank`) for every controller of the project.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from aocontrol.controllers._base import ControllerBank, IIRBank
from aocontrol.controllers._integrator import Integrator
from aocontrol.controllers._io import load_controller, register_controller_format, save_controller
from aocontrol.controllers._lqg import FilterpyLQG, LQGBank, LQGStateSpace
from aocontrol.controllers._mpc import MPCBank
from aocontrol.controllers._multimode import MultiModeBank

__all__ = [
    "ControllerBank",
    "IIRBank",
    "Integrator",
    "FilterpyLQG",
    "LQGBank",
    "LQGStateSpace",
    "MPCBank",
    "MultiModeBank",
    "save_controller",
    "load_controller",
    "register_controller_format",
]
