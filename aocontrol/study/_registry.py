"""The controllers of the case comparison: the control layer's registry, seen from study.

The registry itself (name -> design on PSDs) lives in the control layer,
:mod:`aocontrol.synthesis` (:data:`~aocontrol.synthesis.CONTROLLERS`,
:class:`~aocontrol.synthesis.ControllerSpec`, :class:`~aocontrol.synthesis.DesignInputs`,
:func:`~aocontrol.synthesis.register_controller`), so that a user with telemetry and no
simulator designs through the same names (:func:`aocontrol.synthesis.design_from_telemetry`).
The comparison (:func:`aocontrol.study.compare.compare_case`, the CLI, sweeps) fills
:class:`DesignInputs` from a calibration run of the simulator; a ``needs_telemetry=False``
spec (the reference integrator) is run with the scanned gain and no calibration run. This
module re-exports the registry for the comparison; a controller registered here is
registered for every entry point (one dictionary). ``integrator`` is an alias of
``reference`` (:data:`CONTROLLER_ALIASES`: one controller, one spec, one name in the results).
"""

from __future__ import annotations

from aocontrol.synthesis import (
    CONTROLLER_ALIASES,
    CONTROLLERS,
    MODULUS_MARGIN,
    MPC_HORIZON,
    ControllerSpec,
    DesignInputs,
    controller_names,
    get_controller,
    register_controller,
)

__all__ = [
    "CONTROLLERS",
    "CONTROLLER_ALIASES",
    "controller_names",
    "get_controller",
    "MODULUS_MARGIN",
    "MPC_HORIZON",
    "ControllerSpec",
    "DesignInputs",
    "register_controller",
]
