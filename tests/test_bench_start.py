"""``payload bench start``: each start measured in fresh processes, reported with every
run; bad input is one line and exit 2. (A benchmark: no time is asserted here.)"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from payload.trials.startbench import NAMES, START_AIM_S, measures

ROOT = Path(__file__).resolve().parents[1]


def _documented() -> tuple[str, ...]:
    """The JSON fields docs/speed.md promises for ``bench start``, in its order (the
    names other tools read: an independent source, not the code's list)."""
    text = " ".join((ROOT / "docs" / "speed.md").read_text().split())
    listed = text.split("whose fields are the names in the table's order: ", 1)[1]
    listed = listed.split(", each a median", 1)[0]
    return tuple(name.strip("` ") for name in listed.split(","))


MEASURES = _documented()


def test_the_bench_reports_the_measures_asked_for_with_their_runs():
    """Three of the measures (the others compile the retargeting solvers in the test's own
    cache, half a minute): each named with its runs, the median of two, the aims of
    those measured; an unknown name is one line and exit 2, naming the ones there are."""
    asked = ("version_s", "help_s", "safety_filter_s")
    done = subprocess.run(
        [sys.executable, "-m", "payload", "bench", "start", "--repeat", "2", "--json",
         "--only", ",".join(asked)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert tuple(result["runs"]) == asked
    for name in asked:
        runs = result["runs"][name]
        assert len(runs) == 2 and all(v > 0 for v in runs)
        assert result[name] == sum(runs) / 2  # the median of two
    assert result["aims"] == {"version_s": START_AIM_S, "help_s": START_AIM_S}
    assert len(result["load"]) == 2 and all(len(x) == 3 for x in result["load"])
    bad = subprocess.run(
        [sys.executable, "-m", "payload", "bench", "start", "--only", "help_s,boot_s"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert bad.returncode == 2 and bad.stdout == ""
    (line,) = bad.stderr.strip().splitlines()
    assert line.startswith("payload: error: --only: no measure boot_s (there are: version_s")
    assert all(name in line for name in MEASURES)


def test_every_measure_is_named_in_the_help():
    """The measures the bench takes are the ones its --only help lists."""
    assert tuple(measures(ROOT)) == NAMES == MEASURES
    done = subprocess.run(
        [sys.executable, "-m", "payload", "bench", "start", "--help"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert all(name in done.stdout for name in MEASURES)


def test_a_measured_command_that_fails_is_named(tmp_path):
    """A measure whose process fails (a project with no design) raises naming it, with
    the process's own last line."""
    from payload.trials.startbench import StartBenchError

    (tmp_path / "cad").mkdir()
    take = measures(tmp_path)["retargeters_s"]
    with pytest.raises(StartBenchError, match=r"the retargeters failed .*: .+"):
        take()


def test_a_repeat_below_one_is_one_line_and_exit_2():
    done = subprocess.run(
        [sys.executable, "-m", "payload", "bench", "start", "--repeat", "0"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == ["payload: error: --repeat must be >= 1, got 0"]
    assert done.stdout == ""
