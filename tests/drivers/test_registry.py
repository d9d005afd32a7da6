"""Issue 4 drivers: the shared lazy backend registry and the per-kind open_* functions."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap

import pytest

from oralnav.drivers import arm, effector, io
from oralnav.drivers import camera as camera_pkg
from oralnav.drivers.arm import Arm, open_arm
from oralnav.drivers.arm.sim import SimArm
from oralnav.drivers.camera import Camera, open_camera
from oralnav.drivers.camera.sim import SimCamera
from oralnav.drivers.effector import EndEffector, open_effector
from oralnav.drivers.effector.sim import SimEffector
from oralnav.drivers.errors import DriverInitError
from oralnav.drivers.io import SafetyInputs, open_inputs
from oralnav.drivers.io.sim import SimInputs
from oralnav.drivers.registry import backend_class


class _Base:
    pass


class _Impl(_Base):
    pass


_NOT_A_CLASS = 3


def test_backend_class_resolves_and_checks_the_base():
    """issue 4 drivers: a 'module:Class' entry resolves to the class when it subclasses the
    kind's base."""
    table = {"impl": f"{__name__}:_Impl"}
    assert backend_class("widget", table, "impl", _Base) is _Impl


def test_unknown_backend_names_kind_name_and_known_ones():
    """issue 4 drivers: an unknown backend raises DriverInitError naming the kind, the name
    and the known names."""
    with pytest.raises(DriverInitError, match=r"unknown widget backend 'nope' \(known: a, b\)"):
        backend_class("widget", {"b": "x:Y", "a": "x:Y"}, "nope", _Base)
    with pytest.raises(DriverInitError, match=r"unknown widget backend \[\] \(known: none\)"):
        backend_class("widget", {}, [], _Base)  # type: ignore[arg-type]


def test_import_failures_and_wrong_classes_are_init_errors(tmp_path, monkeypatch):
    """issue 4 drivers: an unimportable module (any import error, chained), a malformed entry,
    a missing attribute or a class of the wrong kind raise DriverInitError naming them."""
    with pytest.raises(DriverInitError, match="'ghost' is not available: cannot import no_such"):
        backend_class("widget", {"ghost": "no_such_mod_xyz:G"}, "ghost", _Base)
    # A vendor SDK can fail to load with something other than ImportError.
    (tmp_path / "broken_sdk_mod.py").write_text("raise OSError('libfoo.so: cannot open')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(DriverInitError, match="OSError: libfoo.so") as info:
        backend_class("widget", {"b": "broken_sdk_mod:X"}, "b", _Base)
    assert isinstance(info.value.__cause__, OSError)
    with pytest.raises(DriverInitError, match="not of the form 'module:Class'"):
        backend_class("widget", {"m": "just_a_module"}, "m", _Base)
    with pytest.raises(DriverInitError, match="is not a _Base subclass"):
        backend_class("widget", {"x": f"{__name__}:_Missing"}, "x", _Base)
    with pytest.raises(DriverInitError, match="is not a _Base subclass"):
        backend_class("widget", {"x": f"{__name__}:_NOT_A_CLASS"}, "x", _Base)


def test_every_kind_registers_sim_and_opens_it_unstarted(tmp_path):
    """issue 4 drivers: open_arm/open_effector/open_inputs/open_camera('sim', ...) build
    unstarted sim backends; only backends that exist are registered (issue 8: every entry
    of every table imports and implements its kind)."""
    for pkg, lookup in ((arm, arm.arm_class), (effector, effector.effector_class),
                        (io, io.inputs_class), (camera_pkg, camera_pkg.camera_class)):
        assert "sim" in pkg.BACKENDS
        for name in pkg.BACKENDS:
            if name == "aravis" and importlib.util.find_spec("gi") is None:
                continue  # PyGObject is an optional extra (dev.sh installs it where it can)
            lookup(name)  # DriverInitError if the module or class is missing
    assert {"replay", "sim"} <= set(camera_pkg.BACKENDS)
    a = open_arm("sim", name="ur")
    assert isinstance(a, SimArm) and isinstance(a, Arm) and not a.state().connected
    e = open_effector("sim")
    assert isinstance(e, SimEffector) and isinstance(e, EndEffector)
    i = open_inputs("sim")
    assert isinstance(i, SimInputs) and isinstance(i, SafetyInputs)

    class Source:
        def capture(self, cameras):
            raise AssertionError("the constructor must not capture")

    c = open_camera("sim", name="left", source=Source())
    assert isinstance(c, SimCamera) and isinstance(c, Camera)


@pytest.mark.parametrize(
    ("opener", "kind"),
    [(open_arm, "arm"), (open_effector, "end-effector"), (open_inputs, "inputs"),
     (open_camera, "camera")],
)
def test_each_kind_names_itself_in_registry_errors(opener, kind):
    """issue 4 drivers: an unknown backend error names the kind of device asked for."""
    with pytest.raises(DriverInitError, match=rf"unknown {kind} backend 'ur_rtde_x'"):
        opener("ur_rtde_x")


def test_backends_are_imported_lazily_and_drivers_import_no_upper_layer():
    """issue 4 drivers: importing the driver packages imports no backend module; no driver
    module imports oralnav.control, safety, daemon or sim."""
    code = textwrap.dedent(
        """
        import sys
        import oralnav.drivers.arm, oralnav.drivers.effector, oralnav.drivers.io
        import oralnav.drivers.camera
        eager = [m for m in sys.modules if m.endswith(".sim") and "drivers" in m]
        assert not eager, eager
        import oralnav.drivers.arm.sim, oralnav.drivers.effector.sim, oralnav.drivers.io.sim
        import oralnav.drivers.camera.sim, oralnav.drivers.clock, oralnav.drivers.registry
        upper = [m for m in sys.modules
                 if m.split(".")[:2] in (["oralnav", "control"], ["oralnav", "safety"],
                                         ["oralnav", "daemon"], ["oralnav", "sim"])]
        assert not upper, upper
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
