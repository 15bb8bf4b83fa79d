"""A controller bank that redesigns itself from its own telemetry (adaptive control).

:class:`AdaptiveController` is a :class:`~aocontrol.controllers.ControllerBank` wrapping an
:class:`~aocontrol.controllers.IIRBank`. It records the measurements it receives and the
commands it returns, and every ``period`` seconds (:func:`redesign` is steps 2 to 4 as a function):

1. **Estimate.** Pseudo-open-loop PSDs and white noise levels from the last ``window``
   seconds of its telemetry, with the control layer's pipeline
   (:func:`aocontrol.synthesis.pseudo_open_loop`, then
   :func:`aocontrol.synthesis.disturbance_from_telemetry`). The pseudo open loop ``m + G u``
   is rebuilt over the window plus a lead-in of the plant's delay, which is dropped: a
   window cut from a running loop has no transient of unknown earlier commands.
2. **Select** (optional, ``select``, ``max_modes``): only the modes predicted to gain the
   most are redesigned (:func:`select_modes`), ranked by ``rank``: the residual a redesign
   is predicted to recover (:func:`recoverable_gain`, ``"bound"``) or how far the residual
   moved (:func:`residual_shift`, ``"shift"``); the others keep their controller. The gain
   of a redesign is spread over hundreds of modes, so a mode budget buys time in proportion
   to the gain it forgoes, and a coarser, shorter warm design of every mode
   (``warm_n_grid``, ``warm_max_iter`` of :func:`datadriven_designer`) is usually the better
   trade (``benchmarks/bench_adaptive.py --parts c --sweep``, ``docs/benchmarks.md``).
3. **Design.** A *designer* proposes new controllers for those modes, warm-started from the
   current ones: :func:`datadriven_designer` (``datadriven(..., initial=current)``, each
   mode's structure kept, few iterations),
   :func:`modal_gain_designer` (the optimised integrator gain of Gendron & Léna, the usual
   practice today) or :func:`lqg_designer` (LQG re-identified from the same window, run in
   its own observer form: :class:`StateSpaceRows` in :attr:`Proposal.realisation`).
4. **Certify.** Each mode of the proposal is checked before it is used: closed-loop
   stability (:func:`aocontrol.analysis.is_stable`), modulus margin at least
   ``modulus_margin`` (:func:`aocontrol.analysis.modulus_certificate`, the certificate the
   analysis layer owns: exact over the whole circle for a transfer-function plant) and every
   controller pole of modulus at most ``max_pole_radius`` (a controller that survives an
   open loop: a WFS dropout, a saturated DM). A designer that certified its modes with the
   same certificates on the same plant passes their margins on (:attr:`Proposal.margin`:
   the data-driven synthesis certifies every design so); those modes are not certified a
   second time, their margin is still compared with ``modulus_margin`` and their pole
   radius checked here. The coefficients the loop will run must also be a well-conditioned
   recursion: ``recursion_gain`` (in ``aocontrol.adaptive._redesign``), the gain from a
   mismatch of the filter's state to the command, at most ``max_recursion_gain`` (an exact
   LQG transfer function with nearly cancelling poles and zeros near ``z = 1`` has a stable
   loop and a margin, and a gain of ``1e12``); a mode the loop runs in state space is
   checked on that realisation instead (:func:`state_space_gains`: the same LQG in its
   observer form has ``4e2`` to ``1e4``). A mode that fails, or that the designer
   could not design, keeps its current controller and is reported; a proposal with no
   certified mode is not switched in at all (counted). **An uncertified controller is never used.**
5. **Switch** after the design latency (a set value, or the measured compute time rounded up
   to frames), **bumplessly**: the new bank's state is set from the recent measurements and
   the commands actually applied, so the first command of the new filter continues the loop
   instead of restarting from zero: Direct-Form I rows by :func:`bumpless_outputs`,
   state-space rows by :func:`bumpless_state`. :func:`switch_transients` measures it on a run:
   the residual in the 50 frames after each switch / the 50 before, against the same ratio
   where no switch happened. The loop runs a :class:`RealisedBank`
   (Direct-Form I rows and state-space rows, each batched over its modes).

Timing: frame ``k`` (counted from :meth:`reset`; a frame rejected for a non-finite measurement
is not stepped, hence not counted) is at ``k / fs``. Designs are requested at
the frames ``(window + j * period) * fs`` (``j >= 0``: the first once a full window is
available, so every period starts from the same first design), on the
telemetry up to the previous frame; the switch happens at the start of frame
``k_design + latency_frames``. A design requested while the previous one is still pending
(latency longer than the period) is skipped and counted. In a simulation the design runs
synchronously inside :meth:`step` (the simulated loop waits; its frames are unchanged), and
the latency is simulated by the scheduled switch.

**The multi-mode predictor.** :class:`AdaptivePredictor` runs the same schedule (and the
same timing, below) for the multi-mode predictor of
:func:`aocontrol.synthesis.eof_from_pseudo_open_loop`: step 1 is the window's pseudo-open
loop itself (the predictor is trained on the time series, not on PSDs), step 3 the regularised
least squares on it, step 4 the whole loop's certificate
(:func:`aocontrol.analysis.multimode_certificate`: stability and the multivariable modulus
margin; the weight raised until it is met, never an uncertified predictor), step 5 all modes
at once (one certified predictor or none), bumplessly from the window's last frames
(:meth:`aocontrol.controllers.MultiModeBank.set_history`). The schedule both share is
``aocontrol.adaptive._schedule.SelfDesigningBank``.

Run by :func:`aocontrol.sim.run_loop` like any bank. The runner resets the controller at the
start and the end of a run; the record of the last run (:class:`Redesign` events and
counters) survives that reset as :attr:`AdaptiveController.last_run`.

Control layer: imports nothing from :mod:`aocontrol.sim` or :mod:`aocontrol.study`.
"""

from __future__ import annotations

from aocontrol.adaptive._controller import (
    BUMPLESS_FRAMES,
    MIN_WINDOW_FRAMES,
    AdaptiveController,
    AdaptiveRun,
    Redesign,
)
from aocontrol.adaptive._designers import (
    datadriven_designer,
    lqg_designer,
    modal_gain_designer,
)
from aocontrol.adaptive._predictor import AdaptivePredictor
from aocontrol.adaptive._realisation import (
    BUMPLESS_LAST_WEIGHT,
    BUMPLESS_MEMORY,
    RealisedBank,
    StateSpaceRows,
    bumpless_outputs,
    bumpless_state,
    state_space_gain,
    state_space_gains,
)
from aocontrol.adaptive._redesign import (
    BOUND_N_FFT,
    RANKINGS,
    Designer,
    Proposal,
    Update,
    certify,
    recoverable_gain,
    redesign,
    residual_shift,
    select_modes,
)
from aocontrol.adaptive._transients import TRANSIENT_FRAMES, SwitchTransients, switch_transients

__all__ = [
    "BOUND_N_FFT",
    "BUMPLESS_FRAMES",
    "BUMPLESS_LAST_WEIGHT",
    "BUMPLESS_MEMORY",
    "MIN_WINDOW_FRAMES",
    "RANKINGS",
    "TRANSIENT_FRAMES",
    "AdaptiveController",
    "AdaptivePredictor",
    "AdaptiveRun",
    "Designer",
    "Proposal",
    "RealisedBank",
    "Redesign",
    "StateSpaceRows",
    "SwitchTransients",
    "Update",
    "bumpless_outputs",
    "bumpless_state",
    "certify",
    "datadriven_designer",
    "lqg_designer",
    "modal_gain_designer",
    "recoverable_gain",
    "redesign",
    "residual_shift",
    "select_modes",
    "state_space_gain",
    "state_space_gains",
    "switch_transients",
]
