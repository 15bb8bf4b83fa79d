"""Structure of :mod:`aocontrol.sim.wfs`: the sensors' shared interface (the package's import
circles are checked with the whole package's in ``tests/test_layers.py``).

Shared interface: both optical sensors derive from ``WavefrontSensor``, which alone defines
what they share (a subclass with its own copy is caught), and they check their inputs with the
same messages.
"""

from __future__ import annotations

import numpy as np
import pytest


def test_former_name_warns_with_the_release_that_removes_it():
    import aocontrol.sim.wfs as wfs

    match = r"LinearModalWFS is deprecated: use aocontrol\.sim\..*removed in 0\.2\.0"
    with pytest.warns(DeprecationWarning, match=match):
        assert wfs.LinearModalWFS is wfs.LinearModalSensor
    with pytest.raises(AttributeError, match="has no attribute 'LinearModalWFZ'"):
        _ = wfs.LinearModalWFZ


#: What the sensors share, defined once in the base class (module docstring of
#: aocontrol/sim/wfs/_sensor.py): no sensor defines its own.
SHARED = (
    "valid_subapertures",
    "n_valid_subapertures",
    "n_signals",
    "_check_opd",
    "detector_image",
    "reference_frame",
    "reference_signals",
    "signals_from_frame",
    "measure",
    "pixel_jacobian_product",
    "__getstate__",
    "__setstate__",
)


def _redefined(cls: type, base: type) -> set[str]:
    """The members of :data:`SHARED` that ``cls`` or a class between it and ``base`` defines."""
    between = cls.__mro__[: cls.__mro__.index(base)]
    return {name for name in SHARED for klass in between if name in vars(klass)}


def test_both_sensors_share_one_interface():
    from aocontrol.sim.wfs import PyramidWFS, ShackHartmannWFS, WavefrontSensor

    for cls in (PyramidWFS, ShackHartmannWFS):
        assert issubclass(cls, WavefrontSensor)
        assert _redefined(cls, WavefrontSensor) == set(), cls.__name__
    assert all(name in vars(WavefrontSensor) for name in SHARED)

    # The twin that must fail: a sensor with its own copy of measure.
    class Copied(PyramidWFS):
        def measure(self, opd, photons, read_noise, rng):  # pragma: no cover - not called
            return super().measure(opd, photons, read_noise, rng)

    assert _redefined(Copied, WavefrontSensor) == {"measure"}


def test_shared_checks_speak_the_same_way_for_both_sensors():
    # The base owns the OPD check and the matrix check of the pixel Jacobian: one message.
    from aocontrol.sim.pupil import vlt_pupil
    from aocontrol.sim.wfs import PyramidWFS, ShackHartmannWFS

    pupil = vlt_pupil(16)
    sensors = [
        PyramidWFS(pupil, 1.1e-6, n_subapertures=8, modulation=1.0),
        ShackHartmannWFS(pupil, 0.7e-6, n_subapertures=4, model="diffractive"),
    ]
    for wfs in sensors:
        with pytest.raises(ValueError, match=r"opd must end with shape \(16, 16\), got \(3, 3\)"):
            wfs.signals(np.zeros((3, 3)))
        with pytest.raises(ValueError, match=f"matrix must have n_signals={wfs.n_signals} "):
            wfs.pixel_jacobian_product(wfs.reference_frame, np.ones((2, wfs.n_signals + 1)))
        # Oracle: the signals are normalised by the flux, so a frame in any flux unit gives
        # the signals of its OPD; a flat wavefront gives zero.
        opd = np.random.default_rng(4).standard_normal((2, 16, 16)) * 30.0
        frames = wfs.detector_image(opd)
        assert frames.shape == (2, *wfs.frame_shape)
        np.testing.assert_allclose(
            wfs.signals_from_frame(frames * 250.0), wfs.signals(opd), rtol=1e-9, atol=1e-12
        )
        assert np.array_equal(wfs.signals(np.zeros((16, 16))), np.zeros(wfs.n_signals))


def test_geometric_shack_hartmann_has_no_detector():
    from aocontrol.sim.pupil import vlt_pupil
    from aocontrol.sim.wfs import ShackHartmannWFS

    wfs = ShackHartmannWFS(vlt_pupil(16), 0.7e-6, n_subapertures=4)
    rng = np.random.default_rng(0)
    for what, call in [
        ("detector_image", lambda: wfs.detector_image(np.zeros((16, 16)))),
        ("reference_frame", lambda: wfs.reference_frame),
        ("detector_image", lambda: wfs.measure(np.zeros((16, 16)), 1e3, 0.1, rng)),
    ]:
        with pytest.raises(ValueError, match=f"{what} needs model='diffractive'"):
            call()
    assert wfs.signals(np.zeros((16, 16))).shape == (wfs.n_signals,)  # its signals do work
