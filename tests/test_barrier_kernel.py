"""The base safety filter's compiled geometry (payload.teleop.barrier_c) gives the bits of
the Python functions it is written from and of Numba's compilation of them, is refused
when it does not, and spares a start with the filter Numba's import."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from payload.teleop import barrier_c
from payload.teleop import filter_kernel as ref


def test_the_c_answers_as_the_python_and_numba_on_other_scenes():
    """Scenes past the self-check's (120 to 419), every array written compared to the bit
    with the plain Python functions and with Numba's compilation of them (a second
    compiler of the same code); some scenes have no rows, some fill many."""
    kernel = barrier_c.compiled_barrier()
    assert kernel is not None  # a C compiler is here
    numba_rows, numba_box = ref.numba_kernels()
    counts = []
    for k in range(barrier_c.CHECK_PROBES, barrier_c.CHECK_PROBES + 300):
        scene = barrier_c.probe_scene(k)
        got = barrier_c.run_rows(kernel.barrier_rows, scene)
        assert got == barrier_c.run_rows(ref.barrier_rows, scene), k
        assert got == barrier_c.run_rows(numba_rows, scene), k
        box = barrier_c.run_box(kernel.enclosing_box, scene)
        assert (
            box
            == barrier_c.run_box(ref.enclosing_box, scene)
            == barrier_c.run_box(numba_box, scene)
        )
        counts.append(int(np.frombuffer(got[0], np.int64)[0]))
    assert min(counts) == 0 and max(counts) >= 20


@pytest.mark.parametrize(("gain", "bound"), [(2.0, 0.02), (0.1, 0.006)])
def test_the_rows_of_a_point_inside_a_box_against_a_closed_form(gain, bound):
    """One shape of one sample point 1 cm inside a 1 m box's +x face and 20 cm to the
    vehicle's left, with a 5 cm margin, the vehicle unrotated and asked for nothing: one
    pair, whose two rows are the face's normal (+x), without and with its yaw lever
    (n . (e_z x r) = -0.2 m), bound by the recovery speed out of the margin: 2 cm/s when
    the gain asks for more (2/s x 6 cm = 12 cm/s), 0.1/s x 6 cm = 6 mm/s when less; the
    distance is -1 cm and the slack at rest -bound."""
    kernel = barrier_c.compiled_barrier()
    assert kernel is not None
    xmat, xpos = np.eye(3).reshape(1, 9).copy(), np.zeros((1, 3))
    obs = np.array([[[-1.0, -0.5, -0.5]], [[0.0, 0.5, 0.5]]])  # the face at x = 0
    local = np.array([[-0.01, 0.2, 0.0]])
    params = np.array([0.05, 1.0, 0.1, gain, 0.02, 0.1, 0.1, 0.1])
    rows, out, lower, pts = np.zeros((2, 4)), np.zeros((2, 2)), np.zeros((1, 1)), np.zeros((1, 3))
    boxes = np.array([local, np.zeros_like(local)])  # the point's box, of no extent
    count, least = kernel.barrier_rows(
        xmat, xpos, 0, np.zeros(1, np.int64), boxes, local, np.array([0, 1]), obs,
        np.zeros(4), params, 1, rows, out, lower, pts,
    )  # fmt: skip
    assert count == 2  # with and without the yaw term
    # the face's normal n = (1, 0, 0); the yaw term n . (e_z x r) of the point's lever r
    yaw = np.dot([1.0, 0.0, 0.0], np.cross([0.0, 0.0, 1.0], local[0]))
    np.testing.assert_array_equal(rows, [[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, yaw]])
    np.testing.assert_allclose(out[0], [bound, bound], rtol=1e-12)
    np.testing.assert_allclose(lower, [[-0.01]], rtol=1e-12)
    assert least == out[1, 0] == -out[0, 0]


def test_a_kernel_with_other_bits_is_refused(refused_kernel):
    """The stopping speed's product distributed (the same in exact arithmetic) is
    refused, and the filter takes Numba's functions."""
    with refused_kernel(
        barrier_c,
        "double u = accel * (sqrt(b * b + 2.0 * d / accel) - b);",
        "double u = accel * sqrt(b * b + 2.0 * d / accel) - accel * b;",
        says="differs",
    ):
        assert barrier_c.compiled_barrier() is None
        rows, _ = barrier_c.geometry_kernels()
        assert type(rows).__module__.startswith("numba")


def test_without_the_c_the_filter_runs_numbas(monkeypatch):
    """``PAYLOAD_NATIVE=0``: Numba's compilation of the Python (whose rows the first test
    compares with the C's)."""
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    rows, box = barrier_c.geometry_kernels()
    assert (rows, box) == ref.numba_kernels()
    assert type(rows).__module__.startswith("numba")


def test_a_filter_is_made_without_importing_numba():
    """A base safety filter made and stepped in a fresh process: its geometry is the C,
    and making it imports neither Numba nor llvmlite nor the SciPy Numba loads."""
    code = (
        "import sys\n"
        "import numpy as np\n"
        "from payload.schema import VehicleTwist\n"
        "from payload.sim.driver import SimDriver\n"
        "from payload.sim.world import build_world\n"
        "from payload.teleop.channels import BaseConfig\n"
        "from payload.trials.preparation import base_filter_for\n"
        "sim = SimDriver(build_world())\n"
        "before = set(sys.modules)\n"
        "f = base_filter_for(sim, BaseConfig())\n"
        "f(VehicleTwist(np.array([0.1, 0.0, 0.0]), np.zeros(3), 0.0), sim.data)\n"
        "print(f._barrier_rows.__qualname__)\n"
        "new = set(sys.modules) - before\n"
        "print(sorted(m for m in new if m.split('.')[0] in ('numba', 'scipy', 'llvmlite')))\n"
        "print('numba' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    kind, loaded, numba = done.stdout.split("\n")[:3]
    assert kind == "CompiledBarrier.barrier_rows" and loaded == "[]" and numba == "False"


def test_an_index_out_of_range_raises_as_the_python_does():
    """A body index past the bodies, a sample point past the points, a geom past the geoms,
    or fewer rows than the pass fills: the Python raises IndexError, and the C raises it
    too instead of reading or writing past an array."""
    kernel = barrier_c.compiled_barrier()
    assert kernel is not None
    scene = barrier_c.probe_scene(4)
    bad_body = dict(scene, bodies=scene["bodies"] + scene["xmat"].shape[0])
    bad_point = dict(scene, first_point=scene["first_point"] + 1)
    full = int(np.frombuffer(barrier_c.run_rows(kernel.barrier_rows, scene)[0], np.int64)[0])
    assert full >= 4
    short = dict(scene, most=full - 2)
    for bad in (bad_body, bad_point, short):
        for fn in (ref.barrier_rows, kernel.barrier_rows):
            with pytest.raises(IndexError):
                barrier_c.run_rows(fn, bad)
    geoms = np.array([0, scene["xmat"].shape[0]], dtype=np.int64)
    corners = np.zeros((2, 3))
    for fn in (ref.enclosing_box, kernel.enclosing_box):
        with pytest.raises(IndexError):
            fn(scene["xpos"], scene["xmat"], geoms, corners, np.zeros(3), np.eye(3))
