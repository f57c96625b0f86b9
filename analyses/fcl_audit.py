"""python-fcl audit of a campaign's commanded pair postures (issue 36).

Reads every trial's ``log.mcap`` under a campaign folder, takes every distinct commanded
pair posture (``q_left``, ``q_right``), and checks it with python-fcl on the URDF's
collision meshes (:class:`payload.retarget.meshcheck.PairMeshCheck`: every link pair of
the pair's two fingers but the two pads, and every link against the structure): meshes in
collision, and the least distance over those pairs. Writes a Markdown table; optionally
the first trial's every 25th posture for the test data (``tests/data``).

Usage::

    python analyses/fcl_audit.py runs/analyses-single-safe \
        --out analyses/campaign/single-safe/fcl_audit.md \
        --postures tests/data/safe_trial_seed0_postures.npz
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from payload.retarget import PairKinematics, load_hand
from payload.retarget.collision import register
from payload.retarget.meshcheck import PairMeshCheck
from payload.trials.reading import read_recording

POSTURE_STRIDE = 25
"""Every how many control steps the test data keeps a posture."""


def audit(campaign: Path) -> tuple[list[dict[str, object]], float]:
    """Per trial and pair: postures checked, meshes in collision, least non-pad distance
    [m] (up to the margin: farther is reported as the margin); and the margin [m]."""
    register()
    hand = load_hand()
    margin = float(hand.collision_margin)
    checks = {p: PairMeshCheck(PairKinematics(hand, p)) for p in ("L", "R")}
    rows: list[dict[str, object]] = []
    for log in sorted(campaign.glob("trial-*/log.mcap")):
        rec = read_recording(log)
        for pair, qs in (("L", rec.q_left), ("R", rec.q_right)):
            check = checks[pair]
            distinct = np.unique(np.asarray(qs), axis=0)
            distinct = distinct[np.all(np.isfinite(distinct), axis=1)]
            collided = sum(check.in_collision(q) for q in distinct)
            least = min((check.min_distance_near(q, margin) for q in distinct), default=margin)
            rows.append(
                {
                    "trial": log.parent.name,
                    "pair": pair,
                    "postures": len(distinct),
                    "collisions": int(collided),
                    "least_mm": least * 1e3,
                }
            )
            print(f"{log.parent.name} {pair}: {rows[-1]}", file=sys.stderr)
    return rows, margin


def markdown(rows: list[dict[str, object]], margin: float, campaign: Path) -> str:
    """The audit as a Markdown table with a one-line verdict."""
    total = sum(int(r["collisions"]) for r in rows)  # type: ignore[call-overload]
    least = min(float(r["least_mm"]) for r in rows)  # type: ignore[arg-type]
    lines = [
        f"# python-fcl audit of `{campaign.name}`'s commanded pair postures",
        "",
        f"Non-pad link pairs and links against the structure, on the URDF's meshes; margin "
        f"{margin * 1e3:.1f} mm (distances at or beyond it are shown as the margin). "
        f"Collisions: {total}; least non-pad distance {least:.2f} mm "
        f"(margin less {margin * 1e3 - least:.2f} mm).",
        "",
        "| trial | pair | distinct postures | meshes in collision | least distance [mm] |",
        "| --- | --- | --- | --- | --- |",
    ]
    lines += [
        f"| {r['trial']} | {r['pair']} | {r['postures']} | {r['collisions']} | "
        f"{float(r['least_mm']):.2f} |"  # type: ignore[arg-type]
        for r in rows
    ]
    return "\n".join(lines) + "\n"


def save_postures(campaign: Path, out: Path) -> None:
    """The first trial's every 25th commanded pair posture, with its time [s]."""
    rec = read_recording(sorted(campaign.glob("trial-*/log.mcap"))[0])
    pick = slice(0, None, POSTURE_STRIDE)
    np.savez_compressed(
        out,
        q_left=np.asarray(rec.q_left)[pick],
        q_right=np.asarray(rec.q_right)[pick],
        t=np.asarray(rec.t)[pick],
    )


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module's text)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("campaign", type=Path, help="campaign folder (trial-*/log.mcap)")
    parser.add_argument("--out", type=Path, help="Markdown file to write")
    parser.add_argument("--postures", type=Path, help="write the first trial's postures here")
    args = parser.parse_args(argv)
    if not any(args.campaign.glob("trial-*/log.mcap")):
        print(f"fcl_audit: no trial-*/log.mcap under {args.campaign}", file=sys.stderr)
        return 2
    rows, margin = audit(args.campaign)
    text = markdown(rows, margin, args.campaign)
    if args.out:
        args.out.write_text(text)
    print(text)
    if args.postures:
        save_postures(args.campaign, args.postures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
