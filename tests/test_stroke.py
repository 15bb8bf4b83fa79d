"""The stroke: one owner (the DM), one name per meaning, the old names deprecated.

Model (:mod:`aocontrol.sim.dm`): the DM owns the physical limit (``actuator_stroke`` [nm]) and
a per-mode limit (``modal_stroke`` [nm RMS]); a stage keeps no copy; a controller's own clip
is ``command_limit``; the MPC's bound in the case comparison is the DM's ``command_bound``,
derived from ``m2c`` by :func:`aocontrol.sim.dm.modal_stroke` only; ``datadriven``'s
``hinf_weight`` is a weight, not a stroke. Every old keyword keeps working with a
``DeprecationWarning`` and gives the same object, bit for bit.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from aocontrol import loop_plant
from aocontrol.controllers import IIRBank, Integrator, LQGBank, MPCBank
from aocontrol.sim import LinearModalSensor, ModalDM, ModalTimeSeries, Stage, run_loop
from aocontrol.sim.dm import DeformableMirror, modal_stroke
from aocontrol.sim.pupil import vlt_pupil
from aocontrol.synthesis import (
    DesignInputs,
    DisturbanceModel,
    datadriven,
    get_controller,
    lqg_state_space,
    mpc,
)

FS = 1000.0
DEPRECATED = r"'stroke' is deprecated, use 'command_limit'"


def _ss():
    d = DisturbanceModel(
        [[1.98, -0.9801], [1.9, -0.95]], [1.0, 1.0], np.zeros((2, 0)), np.zeros((2, 0)),
        np.zeros((2, 0)), fs=FS,
    )  # fmt: skip
    return lqg_state_space(d, latency_frames=0.3, noise_variance=0.01)


def _commands(bank, m):
    bank.reset()
    return np.array([bank.step(row) for row in m])


# ----------------------------------------------------------------------------- the DM owns it
def test_stage_keeps_no_copy_of_the_stroke():
    # The stage's only stroke is its DM's: no field holds another, the DM given is the DM used.
    dm = ModalDM(2, modal_stroke=[1.0, 2.0])
    stage = Stage(Integrator(0.5, fs=FS, n_modes=2), dm=dm)
    names = {f.name for f in dataclasses.fields(Stage)}
    assert not names & {"stroke", "dm_stroke", "m2c", "actuator_stroke", "modal_stroke"}
    assert stage.dm is dm
    assert dataclasses.replace(stage, name="other").dm is dm
    assert Stage(Integrator(0.5, fs=FS, n_modes=2)).dm.limited is False  # default: unlimited
    with pytest.raises(ValueError, match=r"dm has 2 modes, the controller of 'stage' has 3"):
        Stage(Integrator(0.5, fs=FS, n_modes=3), dm=dm)
    with pytest.raises(TypeError, match="dm must be an aocontrol.sim.dm.ModalDM, got float"):
        Stage(Integrator(0.5, fs=FS, n_modes=2), dm=3200.0)
    with pytest.raises(TypeError, match=r"give dm only \(\['stroke'\] are the deprecated"):
        Stage(Integrator(0.5, fs=FS, n_modes=2), dm=dm, stroke=1.0)


def test_deprecated_stage_keywords_build_the_same_dm_and_run_bit_identically():
    # Two paths: Stage(stroke=, dm_stroke=, m2c=) (deprecated) and Stage(dm=ModalDM(...)) run
    # the same loop, every telemetry array and saturation count equal bit for bit, with both
    # limits active; reading the old attributes returns the DM's.
    rng = np.random.default_rng(1)
    n_frames, n_modes = 300, 3
    d = 3.0 * rng.standard_normal((n_frames, n_modes)).cumsum(axis=0) / 20.0
    m2c = rng.standard_normal((7, n_modes))
    sensor = LinearModalSensor(1.0, 0.2)

    def run(stage):
        return run_loop(stage, ModalTimeSeries(d, fs=FS), n_frames, rng=3, record=("dm",))

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = Stage(
            Integrator(0.5, fs=FS, n_modes=n_modes), sensor, 0.5, stroke=2.0, dm_stroke=2.5,
            m2c=m2c,
        )  # fmt: skip
    assert [str(w.message).split(" is ")[0] for w in caught] == [
        f"Stage: '{k}'" for k in ("stroke", "dm_stroke", "m2c")
    ]
    assert all(w.category is DeprecationWarning and "use 'dm'" in str(w.message) for w in caught)
    dm = ModalDM(n_modes, modal_stroke=2.0, actuator_stroke=2.5, m2c=m2c)
    new = Stage(Integrator(0.5, fs=FS, n_modes=n_modes), sensor, 0.5, dm=dm)
    a, b = run(old), run(new)
    assert a.saturation.sum() > 0 and a.actuator_saturation.sum() > 0  # both limits bind
    np.testing.assert_array_equal(a.telemetry["dm"], b.telemetry["dm"])
    np.testing.assert_array_equal(a.saturation, b.saturation)
    np.testing.assert_array_equal(a.actuator_saturation, b.actuator_saturation)
    with pytest.warns(DeprecationWarning, match="'stroke' is deprecated, use 'dm.modal_stroke'"):
        np.testing.assert_array_equal(old.stroke, dm.modal_stroke)
    with pytest.warns(DeprecationWarning, match="use 'dm.actuator_stroke'"):
        assert old.dm_stroke == 2.5
    with pytest.warns(DeprecationWarning, match="use 'dm.m2c'"):
        np.testing.assert_array_equal(old.m2c, m2c)


def test_dm_deprecated_stroke_names_warn_and_give_the_same_dm():
    with pytest.warns(DeprecationWarning, match="'stroke' is deprecated, use 'actuator_stroke'"):
        old = DeformableMirror(vlt_pupil(32), n_actuators=15, stroke=100.0)
    assert old == DeformableMirror(vlt_pupil(32), n_actuators=15, actuator_stroke=100.0)
    with pytest.warns(DeprecationWarning, match="use 'actuator_stroke'"):
        assert old.stroke == 100.0
    with pytest.warns(DeprecationWarning, match="'stroke' is deprecated, use 'modal_stroke'"):
        mdm = ModalDM(2, stroke=[1.0, 2.0])
    np.testing.assert_array_equal(mdm.modal_stroke, [1.0, 2.0])
    with pytest.warns(DeprecationWarning, match="use 'modal_stroke'"):
        np.testing.assert_array_equal(mdm.stroke, [1.0, 2.0])
    with pytest.raises(TypeError, match="give 'modal_stroke' only"):
        ModalDM(2, stroke=1.0, modal_stroke=1.0)


def test_command_bound_is_modal_stroke_and_the_smaller_limit():
    # Oracle: the bound of an actuator stroke alone is modal_stroke(m2c, stroke) (the one
    # derivation); with a modal limit too, the smaller of the two per mode; None unlimited.
    m2c = np.array([[1.0, 0.5, 0.0], [-2.0, 0.25, 0.0]])
    dm = ModalDM(3, actuator_stroke=100.0, m2c=m2c)
    np.testing.assert_array_equal(dm.command_bound, modal_stroke(m2c, 100.0))
    np.testing.assert_array_equal(dm.command_bound, [50.0, 200.0, np.inf])
    both = ModalDM(3, modal_stroke=[80.0, 80.0, 80.0], actuator_stroke=100.0, m2c=m2c)
    np.testing.assert_array_equal(both.command_bound, [50.0, 80.0, 80.0])
    assert ModalDM(3, m2c=m2c).command_bound is None


# ----------------------------------------------------------------- the controller's own limit
def _pairs():
    """(name, build(**kw)) for every controller constructor that took ``stroke``."""
    ss = _ss()
    plant = loop_plant(FS, 0.3)
    f = np.linspace(0.0, FS / 2, 65)
    psd = np.vstack([1.0, 2.0])[:, :1] / (1.0 + (f / 50.0) ** 2)
    return [
        ("IIRBank", lambda **kw: IIRBank([0.4], [1.0, -1.0], FS, n_modes=2, **kw)),
        ("Integrator", lambda **kw: Integrator([0.4, 0.5], FS, **kw)),
        (
            "from_transfer_functions",
            lambda **kw: IIRBank.from_transfer_functions(
                [Integrator(0.4, FS).transfer_function()] * 2, **kw
            ),
        ),
        ("LQGBank", lambda **kw: LQGBank(ss, **kw)),
        ("MPCBank", lambda **kw: MPCBank(ss, horizon=3, **kw)),
        ("mpc", lambda **kw: mpc(plant, f, psd, noise_psd=1e-3, horizon=3, **kw)),
    ]


_NAMES = ["IIRBank", "Integrator", "from_transfer_functions", "LQGBank", "MPCBank", "mpc"]


@pytest.mark.parametrize("index", range(len(_NAMES)), ids=_NAMES)
def test_deprecated_controller_stroke_warns_and_gives_the_same_commands(index):
    # Two paths: stroke= (deprecated) and command_limit= give banks with the same limit and
    # the same clipped commands, bit for bit (the limit binds); .stroke reads command_limit.
    name, build = _pairs()[index]
    assert name == _NAMES[index]
    limit = np.array([0.3, 0.6])
    with pytest.warns(DeprecationWarning, match=DEPRECATED):
        old = build(stroke=limit)
    new = build(command_limit=limit)
    np.testing.assert_array_equal(old.command_limit, limit)
    m = 2.0 * np.random.default_rng(0).standard_normal((50, 2))
    u_old, u_new = _commands(old, m), _commands(new, m)
    assert np.any(np.abs(u_new) >= limit * (1 - 1e-12))  # the limit binds
    np.testing.assert_array_equal(u_old, u_new)
    with pytest.warns(DeprecationWarning, match=DEPRECATED):
        np.testing.assert_array_equal(old.stroke, limit)
    with pytest.raises(TypeError, match="give 'command_limit' only"):
        build(stroke=limit, command_limit=limit)


@pytest.mark.parametrize("cls", [LQGBank, MPCBank])
def test_controller_files_written_with_stroke_still_load(cls):
    # Files written before the rename store the limit as "stroke": they load with it.
    bank = cls(_ss(), command_limit=[0.3, 0.6])
    arrays, attrs = bank.to_arrays()
    assert "command_limit" in arrays and "stroke" not in arrays
    arrays["stroke"] = arrays.pop("command_limit")
    back = cls.from_arrays(arrays, {**attrs, "fs": FS, "n_modes": 2})
    np.testing.assert_array_equal(back.command_limit, [0.3, 0.6])


def test_design_inputs_stroke_is_command_limit_and_the_mpc_takes_it():
    # The registry's MPC is limited by DesignInputs.command_limit, which the simulator sets
    # to its DM's command_bound; the old field name warns and gives the same inputs.
    plant = loop_plant(FS, 0.3)
    f = np.linspace(0.0, FS / 2, 65)
    psd = np.vstack([1.0, 2.0])[:, :1] / (1.0 + (f / 50.0) ** 2)
    common = dict(plant=plant, freqs=f, psd=psd, noise_psd=np.full(2, 1e-3), fs=FS, n_modes=2)
    bound = ModalDM(2, actuator_stroke=1.0, m2c=[[2.0, 0.5], [1.0, -4.0]]).command_bound
    inp = DesignInputs(**common, reference_gain=0.5, command_limit=bound)
    with pytest.warns(DeprecationWarning, match=DEPRECATED):
        old = DesignInputs(**common, reference_gain=0.5, stroke=bound)
    assert old.command_limit is bound
    assert dataclasses.replace(inp, reference_gain=0.3).command_limit is bound
    bank, _ = get_controller("mpc").build(inp)
    np.testing.assert_array_equal(bank.command_limit, [0.5, 0.25])


@pytest.mark.slow
def test_case_mpc_bound_is_the_dms_modal_stroke():
    # The case comparison's MPC bound comes from the stage's DM only: modal_stroke of the
    # basis' m2c and the case's actuator stroke (3.2 um, converted once to 3200 nm).
    from aocontrol.study.compare import design_inputs
    from aocontrol.study.scene import build_scene

    scene = build_scene("bright1-best", quick=True)
    st = scene.stage2
    dm = st.modal_dm()
    assert dm.actuator_stroke == st.spec.dm_stroke_nm == pytest.approx(3200.0)
    expected = modal_stroke(st.basis.m2c, 3200.0)
    np.testing.assert_array_equal(dm.command_bound, expected)
    inp = design_inputs(scene, "single", 0.5, seconds=0.05, seed=0, estimator="welch")
    np.testing.assert_array_equal(inp.command_limit, expected)


# --------------------------------------------------------------------- a weight, not a stroke
def test_datadriven_stroke_weight_is_the_deprecated_hinf_weight():
    # Two paths: stroke_weight= (deprecated) and hinf_weight= give the same design bit for
    # bit; a bad weight is refused under its new name.
    plant = loop_plant(FS, 0.5)
    f = np.linspace(0.0, FS / 2, 33)
    psd = 1.0 / (1.0 + (f / 10.0) ** 2)
    kw = dict(order=2, n_grid=16, max_iter=2, progress=False)
    new = datadriven(plant, f, psd, hinf_weight=0.05, **kw)
    with pytest.warns(DeprecationWarning, match="'stroke_weight' is deprecated, use 'hinf_weight'"):
        old = datadriven(plant, f, psd, stroke_weight=0.05, **kw)
    np.testing.assert_array_equal(old.controller.b, new.controller.b)
    np.testing.assert_array_equal(old.controller.a, new.controller.a)
    with pytest.raises(ValueError, match="hinf_weight must be"):
        datadriven(plant, f, psd, hinf_weight=-1.0, **kw)
