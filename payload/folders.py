"""What the workbench's result folders hold, each file named once.

A trial's folder (``payload trial``, a campaign's ``trial-NNNN``, a live session's, a
hardware run's) holds the recording, the metrics and the two figures scored from it, and
for a live session the raw hand frames; a campaign's folder holds its summary (JSON and
Markdown) and the campaign figure beside its trials. A rescoring with another contact
definition writes its files beside the originals under tagged names (:func:`tagged`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path, PurePath

RECORDING = "log.mcap"
"""A trial's recording (MCAP: steps, hand frames, metadata, the Foxglove scene)."""

HANDS = "hands.jsonl"
"""The raw hand frames as they came (a live session's, a hardware run's; older trials')."""

METRICS = "metrics.json"
"""A trial's metrics, scored from its recording."""

CTB_FIGURE = "fig_ctb_body_frame.png"
"""A trial's figure of the CTB in Astrobee's body frame (the paper's Fig. 3)."""

ROUTE_FIGURE = "fig_route.png"
"""A trial's figure of its route through the station."""

SCORED: tuple[str, ...] = (METRICS, CTB_FIGURE, ROUTE_FIGURE)
"""What scoring a recording writes."""

TRIAL_FILES: tuple[str, ...] = (RECORDING, HANDS, *SCORED)
"""What a trial can write into its folder."""


def trial_dir(out_dir: str | PurePath, seed: int) -> Path:
    """The folder of the trial with this seed inside a campaign folder, ``trial-NNNN``."""
    return Path(out_dir) / f"trial-{int(seed):04d}"


SUMMARY = "summary.json"
"""A campaign's summary (what other tools read)."""

SUMMARY_TEXT = "summary.md"
"""A campaign's summary as a report: the definitions, the paper's column, every trial."""

CAMPAIGN_FIGURE = "fig_campaign.png"
"""A campaign's figure: each metric's spread over the trials beside the paper's."""

CAMPAIGN_FILES: tuple[str, ...] = (SUMMARY, SUMMARY_TEXT)
"""What marks a folder as a campaign's."""

SWEEP = "sweep.json"
"""A design sweep's results (what other tools read)."""

SWEEP_TEXT = "sweep.md"
"""A design sweep's table and plots as a report."""

SWEEP_FILES: tuple[str, ...] = (SWEEP, SWEEP_TEXT)
"""What marks a folder as a design sweep's."""

REPORT_FILES: tuple[str, ...] = ("envelope.json", "reach.json")
"""What marks a folder as the design reports' (``payload report envelope`` and ``reach``:
a project's ``analyses/``, or their ``--out``)."""


RESULT_FILES: dict[str, tuple[str, ...]] = {
    "trial": TRIAL_FILES,
    "campaign": CAMPAIGN_FILES,
    "sweep": SWEEP_FILES,
    "report": REPORT_FILES,
}
"""What marks a folder as each kind of command's results."""


def other_results(*own: str) -> tuple[str, ...]:
    """The files that mark the results of every kind in :data:`RESULT_FILES` but ``own``:
    what a command's ``--out`` must not hold (a trial written into a campaign's or the
    reports' folder would be mixed with them)."""
    unknown = [kind for kind in own if kind not in RESULT_FILES]
    if unknown:  # a typo would refuse the command's own kind
        raise ValueError(f"no such kind of results: {', '.join(unknown)}")
    return tuple(f for kind, files in RESULT_FILES.items() if kind not in own for f in files)


def held(folder: Path, names: Iterable[str]) -> list[str]:
    """Those of the file names ``names`` that ``folder`` holds, in their order."""
    return [name for name in names if (folder / name).exists()]


def tagged(name: str, tag: str | None) -> str:
    """The bare file name ``name`` with ``tag`` before its suffix (``metrics.json`` and
    ``contact-min1s-gap0.2s``: ``metrics.contact-min1s-gap0.2s.json``), or ``name`` itself
    without a tag."""
    if not tag:
        return name
    path = PurePath(name)
    return f"{path.stem}.{tag}{path.suffix}"


__all__ = [
    "CAMPAIGN_FIGURE",
    "CAMPAIGN_FILES",
    "CTB_FIGURE",
    "HANDS",
    "METRICS",
    "RECORDING",
    "REPORT_FILES",
    "ROUTE_FIGURE",
    "SCORED",
    "SUMMARY",
    "SUMMARY_TEXT",
    "SWEEP",
    "SWEEP_FILES",
    "SWEEP_TEXT",
    "TRIAL_FILES",
    "held",
    "tagged",
    "trial_dir",
]
