"""The native-code cache: a kernel's full self-check, once passed, is remembered beside its
library for later processes, and forgotten when anything it depends on changes."""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

import pytest

from payload import native


@pytest.fixture
def library(monkeypatch, tmp_path) -> ctypes.CDLL:
    """A small library built into a cache of its own, no check passed in this process."""
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(native, "_CHECKED", set())
    monkeypatch.setattr(native, "_FULL_CHECKS", [])  # this library's checks stay here
    compiler = native.find_compiler()
    assert compiler is not None  # the suite runs where kernels compile
    path = native.build_library("probe", {"probe.c": "int probe(void) { return 7; }\n"}, compiler)
    return ctypes.CDLL(str(path))


def test_a_passed_full_check_lets_later_processes_run_the_short_one(library, monkeypatch):
    assert native.probes(library, (3, 4), 100, 10) == 100
    native.passed(library, (3, 4))
    stamp = native.check_stamp(library, (3, 4))
    assert stamp.is_file() and stamp.parent == Path(library._name).parent
    assert native.probes(library, (3, 4), 100, 10) == 10  # this process
    monkeypatch.setattr(native, "_CHECKED", set())  # the next process
    assert native.probes(library, (3, 4), 100, 10) == 10
    assert native.probes(library, (3, 5), 100, 10) == 100  # another shape
    # anything the answer depends on besides the C changed: checked in full again
    monkeypatch.setattr(native, "_CHECKED", set())
    monkeypatch.setattr(native, "_checked_with", lambda: "other numpy")
    assert native.probes(library, (3, 4), 100, 10) == 100


def test_a_full_check_is_named_where_the_bench_reads_it(library, monkeypatch):
    """``full_checks`` names a kernel each time it runs its full self-check in this process
    (no stamp yet), not when it runs the short one: what ``payload bench trial`` reports
    as time the next run will not spend."""
    seen: list[int] = []
    assert native.self_checked(library, "k", 40, lambda n: seen.append(n) or True)
    assert native.self_checked(library, "k", 40, lambda n: seen.append(n) or True)
    assert seen == [40, 4] and native.full_checks() == ("probe",)  # the hash left off
    monkeypatch.setattr(native, "_CHECKED", set())  # the next process, the stamp made
    assert native.self_checked(library, "k", 40, lambda n: seen.append(n) or True)
    assert native.full_checks() == ("probe",) and seen[-1] == 4
    assert not native.self_checked(library, "other", 40, lambda n: False)  # failed: named
    assert native.full_checks() == ("probe", "probe")


def test_a_rebuilt_library_or_another_environment_asks_for_a_full_check(library, monkeypatch):
    """A stamp names the library file as built (size and time): the same name rebuilt (a
    new compiler, say) is checked in full; a stamp of another environment is replaced by
    the new one, not kept beside it; another key's stamp stays."""
    native.passed(library, "k")
    native.passed(library, "other key")
    first = native.check_stamp(library, "k")
    path = Path(library._name)
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # rebuilt
    monkeypatch.setattr(native, "_CHECKED", set())
    assert native.probes(library, "k", 50, 5) == 50
    native.passed(library, "k")
    second = native.check_stamp(library, "k")
    assert second != first and second.is_file() and not first.exists()
    assert len(list(path.parent.glob(f"{path.stem}.*{native.CHECK_SUFFIX}"))) == 2


def test_the_stamp_follows_the_workbenchs_code(tmp_path):
    """Any change to a module's text (the numpy code the kernels are checked against), or
    a module more, changes the sources' digest the stamps are named by."""
    from payload.cache import sources_digest

    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "native.py").write_text("x = 1\n")
    (package / "sub" / "mod.py").write_text("def f():\n    return 1.0\n")
    digests = [sources_digest(package)]
    (package / "sub" / "mod.py").write_text("def f():\n    return 1.0 + 0.0\n")
    sources_digest.cache_clear()
    digests.append(sources_digest(package))
    (package / "extra.py").write_text("")
    sources_digest.cache_clear()
    digests.append(sources_digest(package))
    # the packaged default design fills what a project's design leaves out: it counts too
    (package / "data").mkdir()
    (package / "data" / "design.toml").write_text("[servo]\nlength = 0.034\n")
    sources_digest.cache_clear()
    digests.append(sources_digest(package))
    (package / "data" / "design.toml").write_text("[servo]\nlength = 0.035\n")
    sources_digest.cache_clear()
    digests.append(sources_digest(package))
    sources_digest.cache_clear()
    assert len(set(digests)) == 5


def test_a_cache_key_follows_each_of_its_inputs(monkeypatch):
    """``code_key`` (the stowed-fit answers' and the models' fingerprints' names) moves
    with its kind, with each part and where one part ends, with the sources and with a
    library's version; the same inputs give the same name."""
    from payload import cache

    base = ("fit-1", ("numpy",), b"cad/design.toml", b"[finger]")
    keys = [cache.code_key(*base[:2], *base[2:]), cache.code_key(*base[:2], *base[2:])]
    assert keys[0] == keys[1] and len(keys[0]) == 32
    keys = [keys[0], cache.code_key("fit-2", ("numpy",), *base[2:])]
    keys.append(cache.code_key("fit-1", ("numpy",), b"cad/design.tom", b"l[finger]"))
    keys.append(cache.code_key("fit-1", ("numpy",), b"cad/design.toml", b"[finger] "))
    keys.append(cache.code_key("fit-1", ("numpy", "trimesh"), *base[2:]))
    monkeypatch.setattr(cache, "dist_version", lambda name: "0.0-other")
    keys.append(cache.code_key(*base[:2], *base[2:]))
    monkeypatch.setattr(cache, "sources_digest", lambda: "another tree")
    keys.append(cache.code_key(*base[:2], *base[2:]))
    assert len(set(keys)) == len(keys), keys


def test_a_stamp_passed_under_other_sources_asks_for_a_full_check(library, monkeypatch):
    """The stamp is named by the sources' digest taken at import: a full check passed
    under other sources (the workbench edited since) is not this process's stamp, and
    the same sources find it again."""
    native.passed(library, (5,))
    mine = native.check_stamp(library, (5,))
    assert mine.is_file()
    with monkeypatch.context() as m:
        m.setattr(native, "_SOURCES", "another digest")
        m.setattr(native, "_CHECKED", set())
        native._checked_with.cache_clear()
        try:
            other = native.check_stamp(library, (5,))
            assert other != mine and not other.exists()
            assert native.probes(library, (5,), 100) == 100
        finally:
            native._checked_with.cache_clear()
    assert native.check_stamp(library, (5,)) == mine


def test_pruning_a_library_deletes_its_stamps(library):
    native.passed(library, 1)
    stamp = native.check_stamp(library, 1)
    assert stamp.is_file()
    native.prune(Path(library._name).parent, "probe", keep=0)
    assert not Path(library._name).exists() and not stamp.exists()


def test_the_compilers_flags_are_asked_once_per_cache(monkeypatch, tmp_path):
    """The optional flags a compiler accepts are probed once (a compile per flag) and read
    back from the cache by later processes."""
    import subprocess

    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    compiler = native.find_compiler()
    runs: list[list[str]] = []
    real_run = subprocess.run

    def run(args, **kwargs):
        runs.append(list(args))
        return real_run(args, **kwargs)

    monkeypatch.setattr(subprocess, "run", run)
    native.flags.cache_clear()
    try:
        first = native.flags(compiler)
        assert len(runs) == len(native.OPTIONAL_CFLAGS)
        assert first[: len(native.CFLAGS)] == native.CFLAGS
        native.flags.cache_clear()  # the next process
        assert native.flags(compiler) == first and len(runs) == len(native.OPTIONAL_CFLAGS)
    finally:
        native.flags.cache_clear()


def test_a_distributions_version_is_the_installed_one():
    """What cached answers are named by: the installed distribution's version (numpy's
    own ``__version__`` here), ``?`` for one not installed."""
    import numpy as np

    from payload.cache import dist_version

    assert dist_version("numpy") == np.__version__
    assert dist_version("no-such-distribution-anywhere") == "?"


def test_the_environment_names_the_versions_and_blas_kernels_a_result_ran_on():
    """``native.environment()``: the packages' versions as the modules say them, and the
    kernels OpenBLAS picked as threadpoolctl reads them (and forced ones in a process
    started with ``OPENBLAS_CORETYPE``)."""
    import platform
    import subprocess
    import sys

    from conftest import running_environment

    from payload.native import environment

    assert environment() == running_environment()
    if platform.machine() != "x86_64":  # the forced kernels below are x86-64's
        return
    code = "from payload.native import environment; print(environment()['openblas_core'])"
    forced = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, "OPENBLAS_CORETYPE": "Nehalem"},  # SSE4.2: any x86-64 since 2008
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert forced.stdout.strip() == "Nehalem"


def test_the_result_packages_are_pinned_and_run_as_pinned():
    """``constraints.txt`` (what ``make`` installs with) pins every package a trial's
    provenance names, and the suite runs on those versions: the committed results it
    checks were made with them."""
    from importlib.metadata import version

    from conftest import ROOT
    from packaging.requirements import Requirement

    pins, here = {}, {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.split("#")[0].strip():
            req = Requirement(line)
            (pinned,) = req.specifier  # one exact version each
            assert pinned.operator == "==", line
            pins[req.name.lower()] = pinned.version
            if req.marker is None or req.marker.evaluate():
                here[req.name.lower()] = pinned.version
    assert {dist for _, dist in native.RESULT_PACKAGES} <= set(pins)
    installed = {dist: version(dist) for dist in here}
    assert installed == here, "not the versions constraints.txt pins: install with make"
