"""Meshcat design review in the browser: the payload on Astrobee, envelope, reach, trials.

``payload review`` (:mod:`payload.review.cli`) builds a :class:`~payload.review.scene.Scene`
(meshcat commands as data) from the design project with
:func:`~payload.review.design_view.build_design_review` and, for a recorded trial,
:func:`~payload.review.trial_view.build_trial_replay`, then serves it on the review's own
page (:mod:`payload.review.live`; with ``--watch`` the page follows the design file),
draws it into a running meshcat server (``--zmq-url``) or writes it as one standalone HTML
page (:mod:`payload.review.page`).

Names load on first use, so the command line starts without the geometry stack.
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "DesignReview": "payload.review.design_view",
    "build_design_review": "payload.review.design_view",
    "TrialReplay": "payload.review.trial_view",
    "build_trial_replay": "payload.review.trial_view",
    "read_trial": "payload.review.trial_view",
    "PayloadModel": "payload.review.model",
    "ProjectFiles": "payload.review.project",
    "design_hash": "payload.review.project",
    "project_files": "payload.review.project",
    "ReviewError": "payload.review.errors",
    "Scene": "payload.review.scene",
    "static_html": "payload.review.page",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'payload.review' has no attribute {name!r}")
