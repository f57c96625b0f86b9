"""Shared fixtures: the project paths and the default design's models."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
URDF = ROOT / "urdf" / "payload.urdf"
MJCF = ROOT / "urdf" / "payload.xml"
SCENE = ROOT / "urdf" / "scene.xml"
DESIGN = ROOT / "cad" / "design.toml"

if sys.version_info < (3, 11):  # pragma: no cover
    import tomli as tomllib


def replace_once(text: str, old: str, new: str) -> str:
    """``text`` with its one occurrence of ``old`` replaced by ``new``: a test that edits a
    design or hand file this way fails if the text it means to change is not there (a
    silent no-op edit would let it pass against the unedited file)."""
    count = text.count(old)
    assert count == 1, f"expected {old!r} once in the text, found it {count} times"
    return text.replace(old, new)


def hand_file(folder: Path, urdf: str | Path, design: str | Path) -> Path:
    """The default hand description written into ``folder`` as ``hand.toml``, naming the
    URDF and the design at those paths (absolute, or relative to ``folder``)."""
    from payload.retarget.hand import DEFAULT_HAND

    toml = DEFAULT_HAND.read_text()
    toml = replace_once(toml, "{project}/urdf/payload.urdf", str(urdf))
    toml = replace_once(toml, "{project}/cad/design.toml", str(design))
    (folder / "hand.toml").write_text(toml)
    return folder / "hand.toml"


def running_environment() -> dict[str, Any]:
    """What ``payload.native.environment()`` should say of this process, worked out
    another way: the modules' own ``__version__``, the platform's names and the kernels
    OpenBLAS reports to threadpoolctl."""
    import platform

    import casadi
    import mujoco
    import numpy
    import pinocchio
    import scipy
    from threadpoolctl import threadpool_info

    blas = [i for i in threadpool_info() if i["internal_api"] == "openblas"]
    return {
        "python": platform.python_version(),
        **{m.__name__: m.__version__ for m in (numpy, scipy, mujoco, casadi, pinocchio)},
        "machine": platform.machine(),
        "openblas_core": blas[0]["architecture"] if blas else None,
    }


@pytest.fixture(scope="session")
def design_dict() -> dict[str, Any]:
    """The default design file as plain data (copy before editing)."""
    return tomllib.loads(DESIGN.read_text())


@pytest.fixture(scope="session")
def design():
    from payload.design import load_design

    return load_design(DESIGN)


@pytest.fixture(scope="session", autouse=True)
def _checkout_is_the_project():
    """This checkout is the design project of every test (``PAYLOAD_PROJECT``), wherever
    pytest runs from; tests of other projects pass ``--project`` or clear the variable."""
    old = os.environ.get("PAYLOAD_PROJECT")
    os.environ["PAYLOAD_PROJECT"] = str(ROOT)
    yield
    if old is None:
        os.environ.pop("PAYLOAD_PROJECT", None)
    else:
        os.environ["PAYLOAD_PROJECT"] = old


SERIAL_STREAMS: dict[str, str] = {
    "test_firmware_cli.py": "bus",
    "test_firmware_driver.py": "bus",
    "test_firmware_guard.py": "bus",
    "test_firmware_homing.py": "bus",
    "test_firmware_identify.py": "bus",
    "test_firmware_loop.py": "bus",
    "test_firmware_stowing.py": "web",  # an emulator's tests, with the shorter stream
    "test_review.py": "web",
    "test_review_browser.py": "web",
    "test_teleop_browser.py": "web",
    "test_teleop_server.py": "web",
}
"""Tests that run against the wall clock, by stream: ``bus``, the servo-bus emulator
integrating in real time on a pty; ``web``, headless Chromium and the live servers with
latency and watch deadlines (some of them with an emulator behind the server; the
stowing's emulator tests run in it too, to keep the two streams' times near each other:
about 6 and 5 minutes on the 2-core machine). ``make
test`` runs them after the parallel part, in two streams side by side (``-n 2 --dist
loadgroup``, scheduled by :func:`pytest_xdist_make_scheduler`: one worker a stream, each
running its tests one at a time), so no CPU-heavy test of the first part takes their
core. Nothing is shared between the streams: every server binds a free port, every
emulator its own pty, every file goes under the test's ``tmp_path``."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in SERIAL_STREAMS:
            item.add_marker(pytest.mark.serial)


def stream_of(nodeid: str) -> str:
    """The serial stream of a test (``SERIAL_STREAMS``), or its own id outside them."""
    return SERIAL_STREAMS.get(nodeid.split("::", 1)[0].rpartition("/")[2], nodeid)


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup``: each stream of ``SERIAL_STREAMS`` is one unit of work, so one
    worker runs all of it, one test at a time. (xdist's own ``xdist_group`` marks do not
    reach its scheduler under pytest 9.2: the group suffix it puts on a test's id is no
    longer read, and the tests were handed out one by one.) Other ``--dist`` modes keep
    xdist's schedulers."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class StreamScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return stream_of(nodeid)

    return StreamScheduling(config, log)


@pytest.fixture(scope="session", autouse=True)
def _isolated_payload_cache(tmp_path_factory):
    """Compiled solvers go to a temporary ``PAYLOAD_CACHE_DIR``, not the user's cache; the
    workers of one parallel run share it (the cache writes each library atomically).
    ``make test`` names one empty folder for both of its runs (``PAYLOAD_TEST_CACHE_DIR``),
    so the serial part loads what the parallel part compiled instead of compiling it
    again; the first compile of each library is still a test's."""
    old = os.environ.get("PAYLOAD_CACHE_DIR")
    given = os.environ.get("PAYLOAD_TEST_CACHE_DIR")
    if given:
        os.environ["PAYLOAD_CACHE_DIR"] = given
    elif os.environ.get("PYTEST_XDIST_WORKER"):
        shared = tmp_path_factory.getbasetemp().parent / "payload-cache"
        shared.mkdir(exist_ok=True)
        os.environ["PAYLOAD_CACHE_DIR"] = str(shared)
    else:
        os.environ["PAYLOAD_CACHE_DIR"] = str(tmp_path_factory.mktemp("payload-cache"))
    yield
    if old is None:
        os.environ.pop("PAYLOAD_CACHE_DIR", None)
    else:
        os.environ["PAYLOAD_CACHE_DIR"] = old


@pytest.fixture
def fresh_checks(monkeypatch, tmp_path) -> Path:
    """No kernel self-check has passed yet, in this process or an earlier one: the
    kernels' check stamps go to a folder of their own (returned), empty to start with."""
    from payload import native

    stamps = tmp_path / "check-stamps"
    stamps.mkdir()
    real = native.check_stamp
    monkeypatch.setattr(native, "_CHECKED", set())
    monkeypatch.setattr(native, "check_stamp", lambda lib, key: stamps / real(lib, key).name)
    return stamps


@pytest.fixture
def failing_compiler(monkeypatch, tmp_path) -> Path:
    """A C compiler that prints several lines on stderr and exits 1, made the one the
    retargeting solvers use, with a fresh solver cache in ``tmp_path``."""
    import payload.retarget.compiled as compiled

    cc = tmp_path / "bad-cc"
    cc.write_text("#!/bin/sh\necho 'x.c:1: error: one' >&2\necho 'x.c:2: error: two' >&2\nexit 1\n")
    cc.chmod(0o755)
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(compiled, "_compiler", lambda: str(cc))
    return cc


@pytest.fixture
def refused_kernel(monkeypatch, caplog, tmp_path) -> Callable[..., Any]:
    """``with refused_kernel(module, old, new):`` builds, inside the block, the kernel of
    ``module`` whose C has ``old`` replaced by ``new`` (the replacement must change it;
    ``attr`` names the source, ``SOURCE`` by default) in a cache of its own; on leaving,
    the module's logger must have warned ``says`` (its self-check refused the kernel).
    ``forget``: a cached factory to clear before and after."""
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))

    @contextmanager
    def refused(
        module: Any,
        old: str,
        new: str,
        *,
        attr: str = "SOURCE",
        says: str = "differ",
        forget: Any = None,
    ) -> Iterator[None]:
        source = getattr(module, attr)
        other = source.replace(old, new)
        assert other != source, f"{module.__name__}.{attr} has no {old!r}"
        monkeypatch.setattr(module, attr, other)
        if forget is not None:  # a factory that keeps its kernel for the process
            forget.cache_clear()
        try:
            with caplog.at_level("WARNING", logger=module.__name__):
                yield
            assert says in caplog.text
        finally:
            if forget is not None:
                forget.cache_clear()

    return refused


def reg(table: bytes, name: str) -> int:
    """The register ``name``'s value in a servo's control table (the emulator's bytes),
    decoded from the table layout: what a row the driver read must show."""
    from firmware_interface.control_table import BY_NAME, decode

    r = BY_NAME[name]
    return decode(r, table[r.address : r.address + r.size])


def spy_on_the_wire(monkeypatch: pytest.MonkeyPatch) -> dict[int, set[tuple[int, int | None]]]:
    """Every packet the host sends on a Dynamixel bus from now on (``SdkPort.writePort``
    spied), by the servo ID it reaches: a set of (instruction, register address), one
    pair per address it reads or writes (a sync or bulk packet counted under each servo it
    names; a PING, a REBOOT or any other packet without a register under its ID, address
    None; a READ or WRITE to the broadcast ID under ``BROADCAST_ID``)."""
    from firmware_interface import protocol as P
    from firmware_interface.port import SdkPort

    seen: dict[int, set[tuple[int, int | None]]] = {}
    write = SdkPort.writePort

    def note(dxl_id: int, inst: int, addr: int | None, n: int = 1) -> None:
        spots = [None] if addr is None else range(addr, addr + n)
        seen.setdefault(dxl_id, set()).update((inst, a) for a in spots)

    def spy(port: Any, packet: list[int]) -> int:
        pkt = P.parse(bytes(packet))
        inst, par = pkt.instruction, pkt.params

        def word(k: int) -> int:
            return int.from_bytes(par[k : k + 2], "little")

        if inst in (P.READ, P.SYNC_READ, P.FAST_SYNC_READ):
            ids = [pkt.id] if inst == P.READ else list(par[4:])
            for i in ids:
                note(i, inst, word(0), word(2))
        elif inst in (P.WRITE, P.REG_WRITE):
            note(pkt.id, inst, word(0), len(par) - 2)
        elif inst == P.SYNC_WRITE:
            for k in range(4, len(par), 1 + word(2)):
                note(par[k], inst, word(0), word(2))
        elif inst == P.BULK_READ:
            for k in range(0, len(par), 5):
                note(par[k], inst, word(k + 1), word(k + 3))
        elif inst == P.BULK_WRITE:
            k = 0
            while k < len(par):
                note(par[k], inst, word(k + 1), word(k + 3))
                k += 5 + word(k + 3)
        else:
            note(pkt.id, inst, None)
        return write(port, packet)

    monkeypatch.setattr(SdkPort, "writePort", spy)
    return seen


def band_ticks(joint: str, design: Any = None) -> float:
    """A servo's static friction dead band plus one tick of rounding [ticks], from the
    design's constants by hand (default: the packaged design's): at rest, friction holds
    the shaft while the proportional current's torque kt (P / 128) e mA is below the
    Coulomb friction (no I gain)."""
    from payload.design.params import load_design

    s = (design if design is not None else load_design()).servo
    kind = joint if joint in ("rail", "stage") else "abduction" if "abd" in joint else "finger"
    return s.coulomb / (s.kt * getattr(s.gains, kind)[0] / 128 * 1e-3) + 1.0
