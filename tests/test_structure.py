"""Package structure: no import cycles between modules, function-level imports included."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("payload", "firmware_interface")


def _modules() -> dict[str, Path]:
    mods: dict[str, Path] = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = f.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = f
    return mods


def _resolve(name: str, mods: dict[str, Path]) -> str | None:
    """The longest known module that ``name`` (a module or a module's attribute) names."""
    while name:
        if name in mods:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports anywhere in its body."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            for name in names:
                target = _resolve(name, mods)
                # a package importing its own submodules is not a cycle through itself
                if target and target != mod and not target.startswith(mod + "."):
                    if not mod.startswith(target + "."):
                        graph[mod].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_cycle_finder_sees_a_cycle_hidden_in_a_function() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles() -> None:
    graph = import_graph()
    assert "payload.cli" in graph
    found = cycles(graph)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_simulation_and_trials_do_not_load_the_mesh_libraries() -> None:
    """The exporters (trimesh) load on first use: a trial's process never needs them, the
    design package still offers them."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import payload.trials.runner, payload.trials.campaign, payload.sim, payload.teleop\n"
        "assert 'trimesh' not in sys.modules, 'trimesh loaded'\n"
        "import payload.design as d, payload.design.build as b\n"
        "assert (d.write, d.generate, d.stale_files) == (b.write, b.generate, b.stale_files)\n"
        "assert {'write', 'generate', 'stale_files', 'load_design'} <= set(dir(d))\n"
        "from payload.design.solids import to_trimesh\n"
        "import manifold3d\n"
        "assert abs(to_trimesh(manifold3d.Manifold.cube([1, 2, 3])).volume - 6.0) < 1e-12\n"
        "try:\n"
        "    d.nope\n"
        "except AttributeError as exc:\n"
        "    assert 'nope' in str(exc)\n"
        "else:\n"
        "    raise AssertionError('no AttributeError')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr


def test_teleop_and_the_layers_below_never_import_the_trials_or_the_commands() -> None:
    """design < kinematics < retarget, envelope, sim < teleop < trials < cli (docs/development.md):
    nothing in those lower packages imports payload.trials, payload.sweep, payload.review
    or the dispatcher payload.cli, not even inside a function (``teleop serve`` gets its
    trial-layer live session handed down by payload.trials.live_cli)."""
    lower = ("payload.design", "payload.kinematics", "payload.retarget", "payload.envelope")
    lower += ("payload.sim", "payload.teleop")
    upper = ("payload.trials", "payload.sweep", "payload.review", "payload.cli")
    graph = import_graph()
    upward = sorted(
        f"{mod} -> {target}"
        for mod, targets in graph.items()
        if mod.startswith(lower)
        for target in targets
        if target == "payload.cli"
        or target.startswith(tuple(u + "." for u in upper[:3]))
        or target in upper[:3]
    )
    assert upward == []


def test_only_the_entry_points_import_the_dispatcher() -> None:
    """payload.cli is the top: command modules take their helpers from payload.cliutil
    and a sweep point runs the build and the reports through their functions, so nothing
    but ``python -m payload`` imports it."""
    graph = import_graph()
    importers = sorted(mod for mod, targets in graph.items() if "payload.cli" in targets)
    assert importers == ["payload.__main__"]


# Libraries a trial's worker must not load with a trial's modules: those only other
# commands use (meshes, mesh collision checks, Meshcat, the Dask client, progress bars),
# those a trial needs only once it runs (SciPy, MCAP, protobuf, figures) and MuJoCo's GLFW
# renderer, which nothing uses (the command line turns it off, its workers inherit that).
WORKER_NEVER = (
    "numba",  # the base filter's geometry is C (payload.teleop.barrier_c); Numba only without
    "llvmlite",  # a compiler, imported then
    "scipy",
    "matplotlib",
    "PIL",
    "trimesh",
    "fcl",
    "meshcat",
    "mcap",
    "mcap_protobuf",
    "google.protobuf",
    "foxglove_schemas_protobuf",
    "dask",
    "distributed",
    "rich",
    "glfw",
    "cffi",
)


def test_a_trial_worker_imports_only_what_a_trial_needs() -> None:
    """What a Dask worker imports for its first trial (the campaign, then the runner), in
    a fresh interpreter with the command line's environment, loads none of
    :data:`WORKER_NEVER` (a list of names, not a time: it cannot drift with the load)."""
    import json
    import os
    import subprocess
    import sys

    from payload.cli import COMMAND_ENV

    code = (
        "import json, sys\n"
        "import payload.trials.campaign, payload.trials.runner\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, **COMMAND_ENV},
        check=True,
    )
    loaded = set(json.loads(done.stdout))
    assert {"numpy", "mujoco", "pinocchio", "casadi", "payload.sim.world"} <= loaded
    never = tuple(f"{name}." for name in WORKER_NEVER)
    assert sorted(m for m in loaded if m in WORKER_NEVER or m.startswith(never)) == []


def test_a_whole_trial_scored_and_drawn_loads_no_scipy(tmp_path) -> None:
    """A trial with its scoring and figures (a short one, past the calibration) runs
    without SciPy: the metrics' rotations are the workbench's (SciPy's bits, tested in
    test_rotations.py), the propulsion's programmes come from the cache and the numerics'
    limit no longer loads SciPy's BLAS ahead. The cache is this process's, warmed here."""
    import json
    import os
    import subprocess
    import sys

    from payload.cli import COMMAND_ENV
    from payload.trials import runner

    runner.run_trial(0, out_dir=tmp_path / "warm", max_time=16.0)  # the caches this one uses
    code = (
        "import json, sys\n"
        "from pathlib import Path\n"
        "from payload.trials import runner\n"
        "r = runner.run_trial(0, out_dir=Path(sys.argv[1]), max_time=16.0)\n"
        "print(json.dumps([sorted(sys.modules), r['steps']]))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "trial")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, **COMMAND_ENV},
        check=True,
    )
    loaded, steps = json.loads(done.stdout.splitlines()[-1])
    assert steps > 600 and (tmp_path / "trial" / "fig_ctb_body_frame.png").is_file()
    assert "matplotlib" in loaded and "payload.trials.metrics" in loaded
    assert sorted(m for m in loaded if m == "scipy" or m.startswith("scipy.")) == []


def test_every_test_file_on_the_wall_clock_runs_in_its_serial_stream():
    """A test file that drives headless Chromium runs in ``make test``'s serial part
    (``SERIAL_STREAMS``), in the ``web`` stream; every file named exists, and the Makefile
    runs the serial part with the scheduler the streams need (``--dist loadgroup``)."""
    from conftest import SERIAL_STREAMS

    tests = ROOT / "tests"
    assert set(SERIAL_STREAMS.values()) == {"bus", "web"}
    assert all((tests / name).is_file() for name in SERIAL_STREAMS)
    for path in sorted(tests.glob("test_*.py")):
        text = path.read_text(encoding="utf-8")
        if path.name != Path(__file__).name and ("playwright" in text or "chromium_path" in text):
            assert SERIAL_STREAMS.get(path.name) == "web", path.name
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert "-n 2 --dist loadgroup -m serial" in makefile


def test_the_serial_part_runs_each_stream_on_one_worker():
    """``-n 2 --dist loadgroup -m serial`` (a few quick tests of each stream, the web
    file's first): every test of a stream on one worker, the two streams on the two.
    xdist's plain load scheduling splits these between the workers (checked: it is what
    ran before, xdist's group marks being lost under pytest 9.2)."""
    import re
    import subprocess
    import sys

    picked = "port_in_use or capsule or pad_pair or pinch_on_nothing"
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-m", "serial",
         "-v", "-p", "no:cacheprovider", "tests/test_review.py", "tests/test_firmware_guard.py",
         "-k", picked],
        capture_output=True, text=True, cwd=ROOT, check=False, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    ran = re.findall(r"\[(gw\d)\] \[[ \d]+%\] PASSED tests/(test_\w+\.py)::", done.stdout)
    assert len(ran) == 4, done.stdout[-2000:]
    workers = {name: {w for w, n in ran if n == name} for _, name in ran}
    assert all(len(w) == 1 for w in workers.values()), ran
    assert workers["test_review.py"] != workers["test_firmware_guard.py"], ran
