"""Every ``payload`` command the README and docs/ show parses as shown, and the front page
stays a front page."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from payload.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^```(\w*)\s*$")


def shell_commands(text: str) -> list[str]:
    """The ``payload ...`` command lines of a Markdown text's bash blocks (continuation
    lines joined, comments and a leading ``$ `` prompt dropped)."""
    out, block, joined = [], None, ""
    for line in text.splitlines():
        fence = FENCE.match(line.strip())
        if fence:
            block = None if block is not None else fence.group(1)
            continue
        if block not in ("bash", "sh", "console", ""):
            continue
        line = line.strip()
        if line.startswith("$ "):
            line = line[2:]
        joined += line
        if joined.endswith("\\"):
            joined = joined[:-1] + " "
            continue
        command, joined = joined, ""
        command = re.sub(r"\s+#.*$", "", command).strip()
        for part in re.split(r"\s*(?:&&|;)\s*", command):
            if part.startswith("payload "):
                out.append(part)
    return out


CASES = [
    pytest.param(cmd, id=f"{page.name}:{cmd[:60]}")
    for page in PAGES
    for cmd in shell_commands(page.read_text(encoding="utf-8"))
]


def test_pages_show_commands():
    assert len(CASES) >= 30  # the docs teach by example; losing them all is a bug
    front = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(shell_commands(front)) >= 4  # the four uses
    assert len(front.splitlines()) <= 220  # a front page, not a manual


@pytest.fixture(scope="module")
def parser():
    return build_parser()


@pytest.mark.parametrize("command", CASES)
def test_command_parses_as_shown(parser, command: str, capsys):
    argv = shlex.split(command)[1:]
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse's usage error
        pytest.fail(f"`{command}` does not parse (exit {exc.code})")
    assert callable(getattr(args, "func", None)), command
    assert "deprecated" not in capsys.readouterr().err, f"`{command}`: an old spelling"


def test_the_live_links_limits_table_states_the_servers_limits():
    """docs/live.md's table of limits says what the server enforces (it said bursts of 24
    after the burst became half a second of frames)."""
    from payload.teleop.messages import MAX_MESSAGE_BYTES
    from payload.teleop.server import MAX_CLIENTS, MIN_TOKEN_CHARS, RATE_BURST, RATE_LIMIT_HZ

    text = (ROOT / "docs" / "live.md").read_text(encoding="utf-8")
    rows = {
        r.split("|")[1].strip(): r.split("|")[2] for r in text.splitlines() if r.count("|") == 4
    }
    rate = re.search(r"(\d+) a second .*bursts of (\d+)", rows["messages per connection"])
    assert rate is not None
    assert (float(rate[1]), float(rate[2])) == (RATE_LIMIT_HZ, RATE_BURST)
    assert int(rows["open WebSocket connections"]) == MAX_CLIENTS
    assert re.search(r"(\d+) KiB", rows["message size"])[1] == str(MAX_MESSAGE_BYTES // 1024)
    assert re.search(r"at least (\d+) characters", rows["session token"])[1] == str(MIN_TOKEN_CHARS)


def test_the_live_pages_status_fields_are_the_servers():
    """docs/live.md's `GET /status` document names every field a hub's status has, and
    every drop counter (it once left out the driver, the operator and three counters)."""
    from payload.teleop.live import LiveHub

    text = " ".join((ROOT / "docs" / "live.md").read_text(encoding="utf-8").split())
    said = re.search(r"`GET /status` returns `(\{.*?\})`", text)
    assert said is not None, "docs/live.md no longer shows the /status document"
    status = LiveHub().status()
    named = set(re.findall(r'"(\w+)"', said[1]))
    nested = {k for v in status.values() if isinstance(v, dict) for k in v}
    assert named == set(status) | nested


def test_the_retargeting_pages_budget_summary_states_the_budgets_starts():
    """docs/retargeting.md's summary of the converged budget names its starts and its seed
    table as payload.retarget.budget has them (it once said eight starts, six from a
    512-posture table, after the code had moved to 14, 12 and 4096)."""
    from payload.retarget import RetargetConfig
    from payload.retarget.budget import SEEDS, TABLE_STARTS, budget_plan

    text = " ".join((Path(__file__).parents[1] / "docs" / "retargeting.md").read_text().split())
    said = re.search(
        r"`converged` runs (\d+) starts, each to convergence or (\d+) iterations: the warm "
        r"start, (\d+) postures of a fixed (\d+)-posture seed table",
        text,
    )
    assert said, "the Budgets summary of docs/retargeting.md is not where it was"
    config = RetargetConfig(budget="converged")
    assert tuple(int(g) for g in said.groups()) == (
        len(budget_plan(config)),
        config.max_iterations,
        TABLE_STARTS,
        SEEDS,
    )


def _sentences(page: Path) -> list[str]:
    """A page's text with its line breaks undone, cut into sentences."""
    text = " ".join(page.read_text(encoding="utf-8").split())
    return re.split(r"(?<=[.;])\s+(?=[A-Z`(])", text)


def test_pages_on_the_base_channel_state_the_papers_braking_rule():
    """A page that describes the base channel's neutral sphere says that braking needs both
    wrists back in neutral, as the channel does (the paper's rule: with the left wrist back
    and the right one still out, it holds its velocity). docs/simulator.md once said the
    vehicle braked as soon as the left wrist alone was back inside its sphere."""
    import numpy as np

    from payload.teleop.channels import BaseChannel, BaseConfig

    config = BaseConfig()
    out = np.array([config.sphere_radius + config.full_speed_offset, 0.0, 0.0])
    home = np.zeros(3)
    channel = BaseChannel(config, home, neutral_right=home)
    for _ in range(50):
        assert channel.step(out, right_wrist=out).mode == "drive"
    assert channel.step(home, right_wrist=out).mode == "hold"
    assert channel.step(home, right_wrist=home).mode == "brake"
    sphere = re.compile(r"virtual sphere|neutral left[- ]wrist", re.IGNORECASE)
    describing = [p for p in PAGES if any(sphere.search(s) for s in _sentences(p))]
    assert describing, "no page describes the base channel any more"
    for page in describing:
        text = " ".join(_sentences(page))
        assert "both wrists" in text, f"{page.name}: braking described without both wrists"


def test_a_page_that_bounds_the_wrench_per_axis_names_the_box_model():
    """The vehicle flies on Astrobee's 12 nozzles unless ``--propulsion box`` is given: the
    wrench is bounded by the nozzles' polytope, not per axis. A sentence that bounds or
    clips the vehicle's wrench per axis is about the ``box`` model and says so
    (docs/simulator.md once described the per-axis bound as the vehicle's, after the
    default had become the nozzles)."""
    from payload.sim.vehicle import DEFAULT_PROPULSION

    assert DEFAULT_PROPULSION == "nozzles"
    per_axis = re.compile(r"(bounded|clipped|limited) per axis", re.IGNORECASE)
    wrong = [
        f"{page.name}: {s[:100]}"
        for page in PAGES
        for s in _sentences(page)
        if per_axis.search(s) and "box" not in s
    ]
    assert not wrong, wrong


def test_the_repository_cites_only_what_it_holds():
    """Self-contained: no page, module, test, design file or build file cites a file that
    is not in the repository (the reference facts, the design card, a path on the
    machine it was written on); external numbers are cited from docs/sources.md.
    CHANGELOG.md (history) and analyses/ (generated results) are left out."""
    outside = re.compile(r"facts\.md|DESIGN\.md|/work/|/home/|/root/")
    files = [ROOT / "README.md", ROOT / "Makefile", ROOT / "pyproject.toml"]
    for folder in ("docs", "payload", "firmware_interface", "tests", "cad", "examples", ".ci"):
        files += [p for p in sorted((ROOT / folder).rglob("*")) if p.is_file()]
    found = []
    for path in files:
        if path.suffix in (".stl", ".png", ".pyc", ".so") or path == Path(__file__).resolve():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if outside.search(line):
                found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:80]}")
    assert found == []
