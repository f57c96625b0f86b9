"""payload.numerics: the single-threaded numerics cover every BLAS a trial uses."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from conftest import ROOT

from payload.numerics import THREAD_VARIABLES


def test_single_threaded_numerics_limit_the_blas_scipy_loads_after_start_up() -> None:
    """A trial's process loads no SciPy at start-up, and SciPy may bring its own BLAS:
    the optimisers imported inside the limit (as the span range and the propulsion do)
    run every BLAS and OpenMP library on one thread, and after it every library loaded
    before runs as many threads as before (threadpoolctl reads the loaded libraries); the
    process starts without the thread variables, and the control (SciPy imported outside
    the limit) runs its BLAS on more than one thread."""
    code = (
        "import json, sys\n"
        "import payload.trials.campaign, payload.trials.runner\n"
        "from threadpoolctl import threadpool_info\n"
        "from payload.numerics import single_threaded_numerics\n"
        "def pools():\n"
        "    return {i['filepath']: i['num_threads'] for i in threadpool_info()}\n"
        "before, scipy_at_start = pools(), 'scipy' in sys.modules\n"
        "with single_threaded_numerics():\n"
        "    import scipy.optimize\n"
        "    inside = pools()\n"
        "print(json.dumps([scipy_at_start, before, inside, pools()]))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}  # as set here
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True,
        env=env,
    )  # fmt: skip
    scipy_at_start, before, inside, after = json.loads(done.stdout)
    assert not scipy_at_start
    assert before and set(inside) == set(after) >= set(before)
    assert set(inside.values()) == {1}
    assert {path: after[path] for path in before} == before
    # the control: SciPy imported outside the limit runs its BLAS on every core it has
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one core: the control could not tell one thread from the default")
    plain = (
        "import json, scipy.optimize\n"
        "from threadpoolctl import threadpool_info\n"
        "print(json.dumps({i['filepath']: i['num_threads'] for i in threadpool_info()}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", plain], capture_output=True, text=True, cwd=ROOT, check=True,
        env=env,
    )  # fmt: skip
    loaded_inside = set(inside) - set(before)
    assert loaded_inside and all(json.loads(done.stdout)[p] > 1 for p in loaded_inside)


def test_the_thread_variables_are_restored_after_the_last_user(monkeypatch) -> None:
    from payload.numerics import single_threaded_numerics

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    with single_threaded_numerics():
        with single_threaded_numerics():
            assert all(os.environ[name] == "1" for name in THREAD_VARIABLES)
        assert os.environ["OPENBLAS_NUM_THREADS"] == "1"  # the outer user still runs
    assert os.environ["OMP_NUM_THREADS"] == "3" and "OPENBLAS_NUM_THREADS" not in os.environ
