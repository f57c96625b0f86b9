"""Cargo-transport trials: crash-safe recording, the paper's metrics, figures, campaigns
on Dask and LeRobot export.

The recorder and the metrics are imported eagerly (numpy, scipy, mcap); figures,
campaigns and the LeRobot export load matplotlib, Dask and pyarrow on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

from payload.trials.metrics import (
    SUCCESS_CRITERION,
    MetricsError,
    TrialMetrics,
    compute_metrics,
    ctb_in_body_frame,
    first_contact_interval,
    rms_deviation,
)
from payload.trials.recorder import (
    MODULES,
    PHASES,
    STEP_SCHEMA,
    Recording,
    RecordingError,
    StepRecord,
    TrialRecorder,
    read_recording,
)

_LAZY = {
    "CampaignError": "payload.trials.campaign",
    "PAPER_RESULTS": "payload.trials.campaign",
    "finish_trial": "payload.trials.campaign",
    "load_trial_results": "payload.trials.campaign",
    "run_campaign": "payload.trials.campaign",
    "runner_trial_fn": "payload.trials.campaign",
    "summarize": "payload.trials.campaign",
    "summary_markdown": "payload.trials.campaign",
    "trial_dir": "payload.trials.campaign",
    "write_summary": "payload.trials.campaign",
    "FigureError": "payload.trials.figures",
    "ModuleRect": "payload.trials.figures",
    "plot_ctb_body_frame": "payload.trials.figures",
    "plot_route": "payload.trials.figures",
    "LeRobotExportError": "payload.trials.lerobot",
    "export_lerobot": "payload.trials.lerobot",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'payload.trials' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


__all__ = [
    "MODULES",
    "PAPER_RESULTS",
    "PHASES",
    "STEP_SCHEMA",
    "SUCCESS_CRITERION",
    "CampaignError",
    "FigureError",
    "LeRobotExportError",
    "MetricsError",
    "ModuleRect",
    "Recording",
    "RecordingError",
    "StepRecord",
    "TrialMetrics",
    "TrialRecorder",
    "compute_metrics",
    "ctb_in_body_frame",
    "export_lerobot",
    "finish_trial",
    "first_contact_interval",
    "load_trial_results",
    "plot_ctb_body_frame",
    "plot_route",
    "read_recording",
    "rms_deviation",
    "run_campaign",
    "runner_trial_fn",
    "summarize",
    "summary_markdown",
    "trial_dir",
    "write_summary",
]
