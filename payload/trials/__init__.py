"""Cargo-transport trials: crash-safe recording, the paper's metrics, figures, campaigns
on Dask and LeRobot export.

Every name loads on first use (module ``__getattr__``): importing the package (or a
command module inside it) costs no numerical library; the recorder and the metrics bring
numpy and mcap, figures, campaigns and the LeRobot export matplotlib, Dask and pyarrow,
when first used.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "SUCCESS_CRITERION": "payload.trials.metrics",
    "MetricsError": "payload.trials.metrics",
    "TrialMetrics": "payload.trials.metrics",
    "compute_metrics": "payload.trials.metrics",
    "ctb_in_body_frame": "payload.trials.metrics",
    "first_contact_interval": "payload.trials.metrics",
    "rms_deviation": "payload.trials.metrics",
    "MODULES": "payload.trials.recorder",
    "PHASES": "payload.trials.recorder",
    "STEP_SCHEMA": "payload.trials.recorder",
    "Recording": "payload.trials.recorder",
    "RecordingError": "payload.trials.recorder",
    "StepRecord": "payload.trials.recorder",
    "TrialRecorder": "payload.trials.recorder",
    "read_recording": "payload.trials.recorder",
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
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # once loaded, an ordinary attribute
    return value


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
