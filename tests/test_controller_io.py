"""Controller files: save_controller / load_controller round trips (bit-identical)."""

import h5py
import numpy as np
import pytest

import aocontrol
from aocontrol.controllers import (
    ControllerBank,
    IIRBank,
    Integrator,
    load_controller,
    register_controller_format,
    save_controller,
)


def _drive(bank, n_frames=200, seed=3):
    """Command sequence of ``bank`` for a fixed random measurement sequence."""
    rng = np.random.default_rng(seed)
    m = rng.standard_normal((n_frames, bank.n_modes)) * 50.0
    bank.reset()
    out = np.array([bank.step(x) for x in m])
    bank.reset()
    return out


def test_iir_bank_round_trip_is_bit_identical(tmp_path):
    # Oracle: the saved coefficients are the bank's own; equality is exact (no tolerance:
    # HDF5 float64 datasets store the IEEE bits).
    rng = np.random.default_rng(0)
    b = rng.standard_normal((7, 5)) * 0.1
    a = np.column_stack([np.ones(7), rng.standard_normal((7, 4)) * 0.05])
    bank = IIRBank(b, a, 3000.0, command_limit=rng.uniform(100, 200, 7))
    path = save_controller(bank, tmp_path / "ctrl.h5")
    back = load_controller(path)
    assert type(back) is IIRBank
    assert back.fs == bank.fs and back.n_modes == 7
    np.testing.assert_array_equal(back.b, bank.b)
    np.testing.assert_array_equal(back.a, bank.a)
    np.testing.assert_array_equal(back.command_limit, bank.command_limit)
    # Saturating measurements exercise the stroke clipping path too.
    np.testing.assert_array_equal(_drive(back), _drive(bank))


def test_integrator_round_trip_keeps_class_gain_and_leak(tmp_path):
    bank = Integrator(np.linspace(0.1, 0.6, 4), fs=1000.0, leak=0.01)
    back = load_controller(save_controller(bank, tmp_path / "int.h5"))
    assert type(back) is Integrator
    assert back.leak == 0.01
    np.testing.assert_array_equal(back.gain, bank.gain)
    assert back.command_limit is None
    np.testing.assert_array_equal(_drive(back), _drive(bank))


def test_top_level_load_controller_and_plain_h5py_layout(tmp_path):
    path = save_controller(Integrator(0.5, fs=1250.0, n_modes=3), tmp_path / "c.h5")
    assert aocontrol.load_controller is load_controller
    with h5py.File(path, "r") as fh:
        assert fh.attrs["format"] == "aocontrol-controller"
        assert fh.attrs["class_name"] == "Integrator"
        assert fh.attrs["fs"] == 1250.0
        assert fh.attrs["software_version"] == aocontrol.__version__
        np.testing.assert_array_equal(fh["gain"][()], [0.5, 0.5, 0.5])


class _Gains(ControllerBank):
    """Test bank following the to_arrays/from_arrays protocol (proportional, optional sign)."""

    def __init__(self, gains, fs, flip=False, label=None):
        self._g = np.asarray(gains, dtype=float)
        self._fs = fs
        self.flip = flip
        self.label = label

    n_modes = property(lambda self: self._g.size)
    fs = property(lambda self: self._fs)

    def _step(self, m):
        return (-1.0 if self.flip else 1.0) * self._g * m

    def reset(self):
        pass

    def transfer_function(self, mode=0):
        raise NotImplementedError

    def to_arrays(self):
        return {"gains": self._g}, {"flip": self.flip, "label": self.label}

    @classmethod
    def from_arrays(cls, arrays, attrs):
        return cls(arrays["gains"], attrs["fs"], attrs["flip"], attrs["label"])


def test_protocol_class_round_trip_keeps_bool_and_none(tmp_path):
    bank = _Gains([1.0, 2.0], 500.0, flip=True, label=None)
    back = load_controller(save_controller(bank, tmp_path / "g.h5"))
    assert type(back) is _Gains
    assert back.flip is True and back.label is None and back.fs == 500.0
    np.testing.assert_array_equal(back.step(np.ones(2)), [-1.0, -2.0])


def test_register_controller_format_for_a_class_without_protocol(tmp_path):
    class Doubled(IIRBank):
        pass

    bank = Doubled([2.0], [1.0], 100.0, n_modes=2)
    with pytest.raises(TypeError, match="Doubled.*known: .*Integrator"):
        save_controller(bank, tmp_path / "d.h5")
    assert not (tmp_path / "d.h5").exists()
    register_controller_format(
        Doubled,
        lambda c: ({"b": c.b, "a": c.a}, {}),
        lambda arr, att: Doubled(arr["b"], arr["a"], att["fs"]),
    )
    back = load_controller(save_controller(bank, tmp_path / "d.h5"))
    assert type(back) is Doubled
    np.testing.assert_array_equal(back.b, bank.b)


def test_not_a_controller_file_is_a_clear_error(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as fh:
        fh.attrs["format"] = "something else"
    with pytest.raises(ValueError, match="not an aocontrol controller file"):
        load_controller(path)


def test_interrupted_write_leaves_no_file(tmp_path, monkeypatch):
    # Inject a failure inside the write: the second dataset raises after the first was written.
    real = h5py.Group.create_dataset
    calls = []

    def failing(self, name, *args, **kwargs):
        calls.append(name)
        if len(calls) == 2:
            raise OSError("disk full (injected)")
        return real(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing)
    bank = IIRBank([0.5], [1.0, -1.0], 1000.0, n_modes=2)
    with pytest.raises(OSError, match="injected"):
        save_controller(bank, tmp_path / "ctrl.h5")
    assert calls == ["b", "a"]  # the failure did happen mid-way
    assert list(tmp_path.iterdir()) == []
