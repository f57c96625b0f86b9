"""The Meshcat review: scene tree, placements, findings, trial replay and bad input.

Scenes are built as data (no server); placements are checked against the design's own
kinematic tree (numpy) and against Pinocchio called here directly on the generated URDF.
"""

from __future__ import annotations

import html
import json
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import tomli_w
from conftest import DESIGN, ROOT, URDF

from payload.cli import main
from payload.design import MANIPULATION_JOINTS, build_tree, load_design
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.vehicle import Vehicle
from payload.review.design_view import OFFENDING_COLOUR, REVIEW, build_design_review, link_colour
from payload.review.project import design_hash, project_files
from payload.review.scene import FAIL, PASS, frame_values
from payload.review.trial_view import (
    CONTACT_COLOUR,
    FREE_COLOUR,
    TRIAL,
    build_trial_replay,
    phase_spans,
)
from payload.trials.recorder import TrialRecorder, random_step, read_recording


def _quat_matrix(xyzw) -> np.ndarray:
    x, y, z, w = xyzw
    return pin.Quaternion(w, x, y, z).toRotationMatrix()


def _urdf_links(urdf: Path) -> dict[str, list[str]]:
    """Link name -> mesh files of its visuals, read with the standard XML parser."""
    out = {}
    for link in ET.parse(urdf).getroot().iter("link"):
        out[link.get("name")] = [m.get("filename") for m in link.findall("visual/geometry/mesh")]
    return out


@pytest.fixture(scope="module")
def review():
    return build_design_review(project_files(), reach_samples=1000)


def test_scene_tree_holds_every_link_with_its_generated_mesh(review) -> None:
    objects, transforms = review.scene.objects(), review.scene.transforms()
    links = _urdf_links(URDF)
    assert len(links) == 23
    for link, meshes in links.items():
        assert f"{REVIEW}/payload/{link}" in transforms, link
        for k, mesh in enumerate(meshes):
            obj = objects[f"{REVIEW}/payload/{link}/visual{k}"]
            data = (URDF.parent / mesh).read_bytes()
            assert obj.geometry.contents.data == data, f"{link}: not the generated mesh"
            assert obj.material.color == link_colour(link)


def test_stowed_links_sit_where_the_design_tree_puts_them(review, design) -> None:
    tree = build_tree(design)
    poses = tree.link_poses(tree.posture("stowed"))
    transforms = review.scene.transforms()
    for link, want in poses.items():
        np.testing.assert_allclose(transforms[f"{REVIEW}/payload/{link}"], want, atol=1e-9)
    np.testing.assert_allclose(transforms[REVIEW][:3, 3], -review.centre)


def test_deployment_animation_goes_from_stowed_to_home(review, design) -> None:
    tree = build_tree(design)
    anim = review.scene.animation
    for posture, index in (("stowed", 0), ("home", -1)):
        poses = tree.link_poses(tree.posture(posture))
        for link in ("stage", "A_distal", "carriage"):
            frames, pos = frame_values(anim, f"{REVIEW}/payload/{link}", "position")
            _, quat = frame_values(anim, f"{REVIEW}/payload/{link}", "quaternion")
            np.testing.assert_allclose(pos[index], poses[link][:3, 3], atol=1e-9)
            np.testing.assert_allclose(_quat_matrix(quat[index]), poses[link][:3, :3], atol=1e-9)
        _, pos = frame_values(anim, f"{REVIEW}/payload/D_tip", "position")
        tip = tree.frame_positions(tree.posture(posture))["D_tip"]
        np.testing.assert_allclose(pos[index], tip, atol=1e-9)
    assert frames == list(range(len(frames)))


def test_clearance_segments_measure_the_envelope_reports_clearances(review) -> None:
    objects, labels = review.scene.objects(), dict(review.scene.overlay.labels)
    anchors = review.scene.transforms()
    fits = {p.name: p for p in review.check.parts}
    segments = [p for p in objects if p.startswith(f"{REVIEW}/findings/clearance/")]
    assert len([p for p in segments if p.endswith("/segment")]) == 6
    named = []
    for path in segments:
        if not path.endswith("/segment"):
            continue
        a, b = objects[path].geometry.position.T.astype(float)
        label = labels[path.replace("/segment", "/label")]
        # "<part> - bay <wall> <d> mm": names the part, the wall and the distance
        part, _, rest = label.partition(" - ")
        where, mm = rest.removesuffix(" mm").rsplit(" ", 1)
        wall = next(w for w in range(6) if path.split("/")[-2] == _wall_key(w))
        assert where == _WALL_NAMES[wall]
        anchor = anchors[path.replace("/segment", "/label")][:3, 3]
        np.testing.assert_allclose(anchor, (a + b) / 2, atol=1e-6)  # points at its segment
        assert np.linalg.norm(a - b) == pytest.approx(fits[part].wall_clearance[wall], abs=2e-6)
        assert float(mm) == pytest.approx(fits[part].wall_clearance[wall] * 1e3, abs=0.051)
        named.append((fits[part].wall_clearance[wall], part))
    assert not review.offending
    # the tightest wall's label names the part the verdict calls tightest (two parts tie
    # at that wall in the default design: the first in the parts' order, as the verdict)
    tight = review.check.tightest
    assert min(named, key=lambda c: c[0]) == (tight.clearance, tight.name)


_WALL_NAMES = (
    "bay aft",
    "bay forward",
    "bay right",
    "bay left",
    "bay bottom face",
    "bay mount",
)


def test_clearance_labels_show_with_the_stowed_payload_only(review) -> None:
    anim = review.scene.animation
    frames, shown = frame_values(anim, f"{REVIEW}/findings", "visible")
    _, stage = frame_values(anim, f"{REVIEW}/payload/stage", "position")
    moved = [i for i in range(len(stage)) if not np.allclose(stage[i], stage[0])]
    assert shown[0] is True and frames[0] == 0
    assert frames[1:] == [moved[0]] and shown[1:] == [False]  # hidden as the stage leaves
    assert not review.scene.autoplay  # so the page opens on the stowed, labelled payload
    assert all(p.startswith(f"{REVIEW}/findings/") for p, _ in review.scene.overlay.labels)


def test_finger_colours_are_not_the_pass_fail_colours() -> None:
    import matplotlib.colors as mc

    from payload.envelope.drawing import FAIL_COLOUR, FINGER_COLOURS, TIGHT_COLOUR

    for f, c in FINGER_COLOURS.items():
        for signal in (FAIL_COLOUR, TIGHT_COLOUR):
            h1, h2 = mc.rgb_to_hsv(mc.to_rgb(c))[0], mc.rgb_to_hsv(mc.to_rgb(signal))[0]
            assert min(abs(h1 - h2), 1 - abs(h1 - h2)) > 0.06, (f, c, signal)


def test_title_names_the_design_and_its_hash(review) -> None:
    assert design_hash(project_files().design) in review.scene.overlay.title
    assert "cad/design.toml" in review.scene.overlay.title


def _wall_key(w: int) -> str:
    return ("minus_x", "plus_x", "minus_y", "plus_y", "minus_z", "plus_z")[w]


def test_reach_clouds_per_finger_in_its_colour_hidden_until_ticked(review) -> None:
    from payload.envelope.report import FINGER_COLOURS

    objects, visible = review.scene.objects(), review.scene.properties("visible")
    for f, colour in FINGER_COLOURS.items():
        cloud = objects[f"{REVIEW}/reach/{f}"]
        rgb = [int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]
        np.testing.assert_allclose(cloud.geometry.color[:, 0], rgb, atol=1e-6)
        assert cloud.geometry.position.shape[1] > 100
        assert visible[f"{REVIEW}/reach/{f}"] is False


def _copy_project(tmp_path: Path, design_dict: dict, bay_size: list[float]) -> Path:
    root = tmp_path / "project"
    shutil.copytree(ROOT / "urdf", root / "urdf")
    shutil.copytree(ROOT / "cad" / "meshes", root / "cad" / "meshes")
    data = {**design_dict, "vehicle": {**design_dict["vehicle"], "bay_size": bay_size}}
    (root / "cad" / "design.toml").write_bytes(tomli_w.dumps(data).encode())
    return root / "cad" / "design.toml"


def _beyond_the_bays(design_file: Path) -> dict[str, np.ndarray]:
    """How far each part's stowed mesh (posed by the design tree) reaches beyond each of the
    bay box's six walls, -x .. +z, shape (6,) [m] (negative: short of it): independent of
    the envelope checks."""
    design = load_design(design_file)
    tree = build_tree(design)
    geom = PayloadGeometry(tree)
    poses = tree.link_poses(tree.posture("stowed"))
    sx, sy, sz = design.vehicle["bay_size"]
    lo, hi = np.array([-sx / 2, -sy / 2, -sz]), np.array([sx / 2, sy / 2, 0.0])
    out = {}
    for n in geom.links:
        v = geom.mesh_vertices[n] @ poses[n][:3, :3].T + poses[n][:3, 3]
        out[n] = np.concatenate([(lo - v).max(axis=0), (v - hi).max(axis=0)])[[0, 3, 1, 4, 2, 5]]
    return out


def test_a_design_that_does_not_fit_shows_the_offending_parts_red(tmp_path, design_dict) -> None:
    path = _copy_project(tmp_path, design_dict, [0.18, 0.10, 0.085])
    rv = build_design_review(project_files(path), reach_samples=0)
    # independent: the stowed meshes, posed by the design tree, against the bay box
    beyond = _beyond_the_bays(path)
    out = {n for n, past in beyond.items() if past.max() > 1e-6}
    assert out and "base" in out and any(n[1:2] == "_" for n in out)
    assert set(rv.offending) == out
    objects = rv.scene.objects()
    for n in beyond:
        colour = objects[f"{REVIEW}/payload/{n}/visual0"].material.color
        assert (colour == OFFENDING_COLOUR) == (n in out), n
    labels = [p for p, _ in rv.scene.overlay.labels if "/findings/protrusion/" in p]
    assert labels and {p.rsplit("/", 1)[1] for p in labels} <= out  # (one per wall: below)
    # the verdict says what failed, not only the tightest part: a protruding link named
    verdict = rv.scene.overlay.subtitle
    assert verdict.startswith("stowed fit: FAIL: ") and " protrudes " in verdict
    assert rv.scene.overlay.as_json()["outcome"] == FAIL  # the page draws it as a failure
    assert verdict.split(": ", 2)[2].split(" protrudes ")[0] in out
    # no "tightest stage -9.0 mm" after it: a negative clearance is the protrusion named
    assert "tightest" not in verdict, verdict


# -- trial replay ------------------------------------------------------------------------
N_STEPS = 40


def _record_trial(
    folder: Path,
    design_file: Path = DESIGN,
    start: tuple[float, float, float] = (1.5, 5.0, 0.25),
    meta: dict | None = None,
) -> Path:
    """A short recording with moving joints, vehicle and CTB (test fixture): the vehicle
    starts at ``start`` (world frame [m], in Kibo) and moves aft along Kibo's axis (-y);
    ``meta``: more metadata."""
    rng = np.random.default_rng(3)
    d = load_design(design_file)
    x, y, z = start
    with TrialRecorder(folder / "log.mcap") as rec:
        rec.write_meta({"seed": 3, "design_hash": design_hash(design_file), **(meta or {})})
        for k in range(N_STEPS):
            t = 0.02 * k
            q = np.zeros(17)
            q[:16] = 0.4 * np.sin(t + np.arange(16))
            q[16] = d.rail.travel * (0.5 + 0.4 * np.sin(3 * t))
            yaw = 0.3 * t
            quat = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
            rec.write(
                random_step(
                    rng,
                    t,
                    phase="acquisition" if k < N_STEPS // 2 else "translation",
                    q_meas=q,
                    deploy_meas=d.stage.travel * (0.8 + 0.2 * np.cos(t)),
                    astrobee_pos=np.array([x, y - 0.2 * t, z]),
                    astrobee_quat=quat,
                    ctb_pos=np.array([x, y - 0.2 * t, z - 0.55]),
                    ctb_quat=quat,
                    contact=bool(k % 7 < 3),
                )
            )
    return folder


@pytest.fixture(scope="module")
def trial_folder(tmp_path_factory) -> Path:
    return _record_trial(tmp_path_factory.mktemp("trial"))


@pytest.fixture(scope="module")
def replay(trial_folder):
    return build_trial_replay(trial_folder, project_files(), rate=50.0)  # every recorded step


def test_a_replay_at_10_hz_shows_the_step_at_each_tenth_of_a_second(trial_folder) -> None:
    replay = build_trial_replay(trial_folder, project_files(), rate=10.0)
    rec, anim = replay.recording, replay.scene.animation
    t = rec.t - rec.t[0]
    # independent: for each 0.1 s tick, the first recorded step at or after it; and the last
    want = {int(np.flatnonzero(t >= tick - 1e-9)[0]) for tick in np.arange(0, t[-1], 0.1)}
    want = sorted({*want, len(t) - 1})
    frames, pos = frame_values(anim, f"{TRIAL}/astrobee", "position")
    np.testing.assert_allclose(np.array(frames) / 10.0, t[want], atol=1e-12)
    np.testing.assert_allclose(pos, rec.astrobee_pos[want])
    assert replay.fps == 10.0
    # a pad shows contact at a frame when the indicator was set at any step since the last
    keys, values = frame_values(anim, f"{TRIAL}/astrobee/payload/A_tip/pad_contact", "visible")
    for i, k in enumerate(want):
        since = rec.contact[(want[i - 1] + 1 if i else 0) : k + 1]
        value = values[int(np.searchsorted(keys, t[k] * 10.0 + 1e-9, side="right")) - 1]
        assert value == since.any(), (i, k)


_TITLE = re.compile(
    r"(?P<what>design review|trial replay) — (?P<subject>\S+) \(design (?P<hash>\w+)\)"
)
_SUBTITLE = re.compile(
    r"(?P<aspect>stowed fit|recording): (?P<verdict>pass|FAIL|finished|not finished)\b.*"
)


def test_the_design_review_and_a_trial_replay_are_titled_alike(review, replay, trial_folder):
    """Both pages: "<what> — <subject> (design <hash>)" over "<aspect>: <verdict>...", and
    the page's <title> (the browser tab) is that title too."""
    from payload.review.page import static_html

    want_hash = design_hash(project_files().design)
    subjects = {}
    for what, scene in (("design review", review.scene), ("trial replay", replay.scene)):
        head = _TITLE.fullmatch(scene.overlay.title)
        assert head is not None, scene.overlay.title
        assert (head["what"], head["hash"]) == (what, want_hash)
        subjects[what] = head["subject"]
        assert _SUBTITLE.fullmatch(scene.overlay.subtitle), scene.overlay.subtitle
        page = static_html(scene)
        tab = page[page.index("<title>") + 7 : page.index("</title>")]
        assert html.unescape(tab) == scene.overlay.title + " - payload review", tab
        assert scene.overlay.as_json()["tab"] == html.unescape(tab)  # the live page's too
    assert subjects["design review"].endswith("/cad/design.toml")
    folder = Path(trial_folder)
    assert subjects["trial replay"] == f"{folder.parent.name}/{folder.name}"
    assert replay.scene.overlay.subtitle.startswith("recording: finished; ")
    # the design review's line is a verdict (drawn by its outcome), the replay's a status
    assert (review.scene.overlay.outcome, replay.scene.overlay.outcome) == (PASS, None)


def test_the_replay_draws_the_keep_in_boxes_around_the_route(replay) -> None:
    """The station's keep-in boxes (issue 33) are drawn, and together they cover the
    simulated route's waypoints (where the vehicle is meant to fly) and none of the
    station's solid geoms' centres (MuJoCo's world, read independently)."""
    import mujoco

    from payload.sim.world import build_world

    objects, transforms = replay.scene.objects(), replay.scene.transforms()
    paths = sorted(p for p in objects if "/keep_in/" in p)
    assert len(paths) == 3  # Kibo, the vestibule, Node 2
    boxes = []
    for path in paths:
        size = np.asarray(objects[path].geometry.lengths, dtype=float)
        centre = transforms[path][:3, 3]
        boxes.append((centre - size / 2, centre + size / 2))

    def inside(p: np.ndarray) -> bool:
        return any(np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9) for lo, hi in boxes)

    world = build_world()
    for waypoint in world.layout.route():
        assert inside(np.asarray(waypoint, dtype=float)), waypoint
    m, d = world.model, mujoco.MjData(world.model)
    mujoco.mj_forward(m, d)
    station = list(world.iss_geoms)
    assert station  # the walls, racks and handrails
    assert not any(inside(d.geom_xpos[g]) for g in station)


def test_the_replay_draws_the_zones_its_trial_ran(tmp_path) -> None:
    """A trial run with `--zones` records them (as data); its replay drew the station's
    keep-in boxes whatever it had run. It draws the recorded ones now, a keep-out box
    among them (in the legend too), where the JSON put it."""
    from payload.sim.world import build_world
    from payload.sim.zones import station_zones

    keepout = ([1.5, 5.6, -0.3], [2.1, 5.9, 0.3])  # across Kibo [m], world frame
    zones = station_zones(build_world().layout, keepout=[keepout])
    folder = _record_trial(tmp_path / "zoned", meta={"zones": zones.as_json()})
    replay = build_trial_replay(folder, project_files(), rate=10.0)
    objects, transforms = replay.scene.objects(), replay.scene.transforms()
    (path,) = [p for p in objects if "/keep_out/" in p]
    size = np.asarray(objects[path].geometry.lengths, dtype=float)
    centre = transforms[path][:3, 3]
    np.testing.assert_allclose(centre - size / 2, keepout[0], atol=1e-12)
    np.testing.assert_allclose(centre + size / 2, keepout[1], atol=1e-12)
    assert len([p for p in objects if "/keep_in/" in p]) == len(zones.keepin)
    assert any("keep-out" in label for _, label in replay.scene.overlay.legend)


def test_the_replays_keep_out_boxes_are_the_failure_red() -> None:
    """One red: the keep-out boxes (a trial's ``--zones``) are drawn, and listed in the
    legend, in the colour of a part that fails (they were a second red, #ff0000 beside
    #e00000, the same to the eye)."""
    from payload.envelope.drawing import FAIL_COLOUR
    from payload.review.scene import Scene
    from payload.review.trial_view import draw_keep_in, trial_legend
    from payload.sim.world import build_world

    scene = Scene()
    draw_keep_in(scene, [(np.zeros(3), np.ones(3))], TRIAL, "keep_out")
    (box,) = scene.objects().values()
    assert f"#{box.material.color:06x}" == FAIL_COLOUR.lower()
    legend = {n: c for c, n in trial_legend(build_world(), keep_in=False, keep_out=True)}
    assert legend["keep-out boxes (the trial's zones)"] == FAIL_COLOUR.lower()


def test_one_animation_frame_per_recorded_step_at_the_recorded_rate(replay) -> None:
    rec, anim = replay.recording, replay.scene.animation
    assert replay.fps == pytest.approx(50.0)
    for path in (f"{TRIAL}/astrobee", f"{TRIAL}/ctb", f"{TRIAL}/astrobee/payload/B_distal"):
        frames, pos = frame_values(anim, path, "position")
        assert len(frames) == len(pos) == len(rec) == N_STEPS
        np.testing.assert_allclose(np.array(frames) / replay.fps, rec.t - rec.t[0], atol=1e-12)
    _, pos = frame_values(anim, f"{TRIAL}/astrobee", "position")
    np.testing.assert_allclose(pos, rec.astrobee_pos)
    for link in _urdf_links(URDF):
        frames, _ = frame_values(anim, f"{TRIAL}/astrobee/payload/{link}", "quaternion")
        assert len(frames) == N_STEPS


def test_a_links_pose_in_a_frame_is_pinocchio_fk_of_the_recorded_joints(replay, design) -> None:
    model = pin.buildModelFromUrdf(str(URDF))
    data = model.createData()
    tree = build_tree(design)
    rec, anim = replay.recording, replay.scene.animation
    for k in (0, 17, N_STEPS - 1):
        q = pin.neutral(model)
        values = dict(zip(MANIPULATION_JOINTS, rec.q_meas[k]))
        values["stage"] = rec.deploy_meas[k]
        for name, v in values.items():
            q[model.joints[model.getJointId(name)].idx_q] = v
        pin.framesForwardKinematics(model, data, q)
        tree_poses = tree.link_poses(values)
        for link in ("A_distal", "B_middle", "carriage", "stage", "D_knuckle"):
            want = data.oMf[model.getFrameId(link, pin.FrameType.BODY)]
            _, pos = frame_values(anim, f"{TRIAL}/astrobee/payload/{link}", "position")
            _, quat = frame_values(anim, f"{TRIAL}/astrobee/payload/{link}", "quaternion")
            np.testing.assert_allclose(pos[k], want.translation, atol=1e-12)
            np.testing.assert_allclose(_quat_matrix(quat[k]), want.rotation, atol=1e-9)
            np.testing.assert_allclose(pos[k], tree_poses[link][:3, 3], atol=1e-9)


def test_pads_show_the_opposing_contact_indicator_and_labels_the_phases(replay) -> None:
    rec, anim, objects = replay.recording, replay.scene.animation, replay.scene.objects()
    for f in "ABCD":
        for state, colour, want in (
            ("contact", CONTACT_COLOUR, rec.contact),
            ("free", FREE_COLOUR, ~rec.contact),
        ):
            path = f"{TRIAL}/astrobee/payload/{f}_tip/pad_{state}"
            assert objects[path].material.color == colour
            frames, values = frame_values(anim, path, "visible")
            at = np.searchsorted(frames, np.arange(N_STEPS), side="right") - 1
            np.testing.assert_array_equal(np.array(values)[at], want)
    assert [s[0] for s in phase_spans(rec)] == ["acquisition", "translation"]
    # the phase is the page's text at the animation time: spans from the trial's start
    t = rec.t - rec.t[0]
    half = N_STEPS // 2
    assert replay.scene.overlay.phases == [
        ("acquisition", pytest.approx(0.0), pytest.approx(t[half - 1])),
        ("translation", pytest.approx(t[half]), pytest.approx(t[-1])),
    ]


# -- command line and bad input ------------------------------------------------------------
def _err(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def test_trial_folder_without_a_readable_recording_exits_2(tmp_path, capsys) -> None:
    assert main(["review", "--trial", str(tmp_path / "none")]) == 2
    assert "not a folder" in _err(capsys)
    assert main(["review", "--trial", str(tmp_path)]) == 2
    assert f"--trial {tmp_path}: not a trial folder (no log.mcap in it)" in _err(capsys)
    (tmp_path / "log.mcap").write_bytes(b"not an mcap file")
    assert main(["review", "--trial", str(tmp_path)]) == 2
    assert f": --trial {tmp_path}: no readable recording" in _err(capsys)
    # named alone (``payload review TRIAL``), the line names the folder, not an option
    # the user did not type
    assert main(["review", str(tmp_path)]) == 2
    err = _err(capsys)
    assert f": {tmp_path}: no readable recording" in err and "--trial" not in err, err


def test_a_trial_folder_named_alone_is_replayed_as_with_trial(tmp_path, capsys) -> None:
    """``payload review TRIAL`` replays the trial as ``--trial TRIAL`` does (the same notes,
    the same page's title and size); a project, a campaign's folder, a folder without a
    recording and a trial given twice are each one line and exit 2."""
    folder = _record_trial(tmp_path / "campaign" / "trial-0003")
    by_option, alone = tmp_path / "a.html", tmp_path / "b.html"
    assert main(["review", "--trial", str(folder), "--static", str(by_option),
                 "--reach-samples", "0"]) == 0  # fmt: skip
    said = capsys.readouterr().out.splitlines()
    assert main(["review", str(folder), "--static", str(alone), "--reach-samples", "0"]) == 0
    assert capsys.readouterr().out.splitlines()[:-1] == said[:-1]  # but "wrote <file>"
    assert any("trial-0003" in line for line in said)
    pages = [page.read_text() for page in (by_option, alone)]
    assert [len(page) for page in pages] == [len(pages[0])] * 2
    titles = [re.search(r"<title>(.*?)</title>", page).group(1) for page in pages]
    assert titles[0] == titles[1] and "trial-0003" in titles[0]
    assert main(["review", str(ROOT), "--reach-samples", "0"]) == 2
    assert f"is a design project, not a trial; review it with --project {ROOT}" in _err(capsys)
    assert main(["review", str(tmp_path / "campaign"), "--reach-samples", "0"]) == 2
    err = _err(capsys)
    assert "holds 1 recorded run(s), each in its own folder; name one, e.g. " in err
    assert err.endswith(str(folder))
    # a folder of campaigns (a project's runs/): one of the trials in them is named
    assert main(["review", str(tmp_path), "--reach-samples", "0"]) == 2
    assert _err(capsys).endswith(f"holds 1 recorded run(s), each in its own folder; name one, "
                                 f"e.g. {folder}")  # fmt: skip
    (tmp_path / "empty").mkdir()
    assert main(["review", str(tmp_path / "empty"), "--reach-samples", "0"]) == 2
    assert "not a trial folder (no log.mcap in it)" in _err(capsys)
    # the recording itself names its trial
    assert main(["review", str(folder / "log.mcap"), "--static", str(alone), "--reach-samples",
                 "0"]) == 0  # fmt: skip
    assert capsys.readouterr().out.splitlines()[:-1] == said[:-1]
    assert main(["review", str(tmp_path / "none")]) == 2
    assert "not a folder" in _err(capsys)
    assert main(["review", str(folder), "--trial", str(folder)]) == 2
    assert "give the trial once" in _err(capsys)
    # --trial DIR is checked as TRIAL is, its lines beginning with the option: a
    # campaign's folder names a trial in it, and the recording names its trial
    camp = tmp_path / "campaign"
    assert main(["review", "--trial", str(camp), "--reach-samples", "0"]) == 2
    assert _err(capsys).endswith(f"--trial {camp}: holds 1 recorded run(s), each in its own "
                                 f"folder; name one, e.g. {folder}")  # fmt: skip
    assert main(["review", "--trial", str(folder / "log.mcap"), "--static", str(alone),
                 "--reach-samples", "0"]) == 0  # fmt: skip
    assert capsys.readouterr().out.splitlines()[:-1] == said[:-1]


def test_recording_of_another_design_exits_2(tmp_path, design_dict, capsys) -> None:
    other = _copy_project(tmp_path, design_dict, [0.21, 0.10, 0.10])
    folder = _record_trial(tmp_path / "trial", other)
    assert main(["review", "--trial", str(folder)]) == 2
    err = _err(capsys)
    assert "another design" in err and design_hash(other) in err and design_hash(DESIGN) in err


def test_a_trial_cut_short_is_replayed_and_said_to_be(tmp_path, capsys) -> None:
    """A recording whose writer was killed (never closed) replays the steps it holds, and
    the review says it is not a finished run instead of showing it as one."""
    folder = _record_trial(tmp_path / "trial")
    log = folder / "log.mcap"
    log.write_bytes(log.read_bytes()[: log.stat().st_size * 2 // 3])  # the file never closed
    rec = read_recording(log)
    assert not rec.complete and 0 < len(rec) < N_STEPS
    out = tmp_path / "r.html"
    assert main(["review", "--trial", str(folder), "--static", str(out), "--reach-samples",
                 "0"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert f"({len(rec)} steps" in printed and "not a finished run: cut short" in printed
    assert "recording: not finished: cut short" in out.read_text()  # the page's subtitle


def test_bad_reach_samples_and_static_folder_exit_2(tmp_path, capsys) -> None:
    assert main(["review", "--reach-samples", "-1"]) == 2
    assert "--reach-samples" in _err(capsys)
    assert main(["review", "--static", str(tmp_path)]) == 2
    assert "is a folder" in _err(capsys)
    typo = tmp_path / "no-such-dir" / "review.html"
    assert main(["review", "--static", str(typo), "--reach-samples", "0"]) == 2
    assert f"no folder {typo.parent}" in _err(capsys) and not typo.parent.exists()
    # a page named as a picture (a new user's review.png) is refused, nothing written
    picture = tmp_path / "review.png"
    assert main(["review", "--static", str(picture), "--reach-samples", "0"]) == 2
    assert "the name ends in .html" in _err(capsys) and not picture.exists()
    assert main(["review", "--zmq-url", "tcp://127.0.0.1:1", "--reach-samples", "0"]) == 2
    assert "no meshcat server" in _err(capsys)
    assert main(["review", "--rate", "0"]) == 2
    assert "--rate must be > 0 Hz" in _err(capsys)
    assert main(["review", "--port", "70000"]) == 2
    assert "--port" in _err(capsys)
    # each where it does nothing: a rate without a replay, a port of no served page
    page = tmp_path / "r.html"
    for argv, words in (
        (["--rate", "10"], "--rate is a trial replay's frame rate"),
        (["--watch", "--rate", "10"], "--watch serves the design review, no replay"),
        (["--static", str(page), "--port", "7071"], "--static writes a file"),
        (["--zmq-url", "tcp://127.0.0.1:1", "--port", "7071"], "--zmq-url uses that"),
    ):
        assert main(["review", *argv, "--reach-samples", "0"]) == 2
        err = _err(capsys)
        assert words in err and len(err.strip().splitlines()) == 1, err
    assert not page.exists()
    assert main(["review", "--watch", "--trial", str(tmp_path)]) == 2
    err = _err(capsys)
    assert "--watch" in err and "--trial" in err
    assert main(["review", "--watch", str(tmp_path)]) == 2  # the combination, not the folder
    err = _err(capsys)
    assert f"it does not take a trial (TRIAL {tmp_path})" in err, err
    assert main(["review", "--watch", "--zmq-url", "tcp://127.0.0.1:1"]) == 2
    err = _err(capsys)  # the combination refused, not a server looked for
    assert "--watch" in err and "--zmq-url" in err


def test_a_port_in_use_exits_2_in_one_line(capsys) -> None:
    """Another program (an earlier review) holds the port: one line, not a traceback."""
    import socket

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = str(held.getsockname()[1])
        for watch in ([], ["--watch"]):
            assert main(["review", *watch, "--port", port, "--reach-samples", "0"]) == 2
            err = _err(capsys)
            assert f"--port {port}" in err and "in use" in err and "--port 0" in err


def test_a_design_outside_a_projects_cad_folder_is_refused_and_nothing_written(tmp_path):
    """``--design F`` where F is not a project's ``cad/design.toml``: the review has no
    models of F, and ``--watch`` used to write F's models into F's grandparent folder."""
    import os
    import subprocess
    import sys

    alt = tmp_path / "drafts" / "alt.toml"
    alt.parent.mkdir()
    shutil.copyfile(DESIGN, alt)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for extra in (["--watch", "--port", "0"], ["--static", str(tmp_path / "r.html")]):
        argv = ["review", "--design", str(alt), "--reach-samples", "0", *extra]
        try:
            run = subprocess.run(
                [sys.executable, "-m", "payload", *argv],
                capture_output=True,
                text=True,
                timeout=60,
                env=env,
            )
        except subprocess.TimeoutExpired:
            pytest.fail(f"{argv} kept serving a design that is in no project")
        assert run.returncode == 2, run.stderr
        err = run.stderr.strip()
        assert len(err.splitlines()) == 1 and "not a design project's cad/design.toml" in err
    assert [p.name for p in tmp_path.iterdir()] == ["drafts"]
    assert [p.name for p in alt.parent.iterdir()] == ["alt.toml"]


def test_a_static_page_that_cannot_be_written_is_one_line(tmp_path, capsys) -> None:
    blocker = tmp_path / "notes.txt"
    blocker.write_text("mine")
    out = blocker / "review.html"  # below a regular file: no folder can be made there
    assert main(["review", "--static", str(out), "--reach-samples", "0"]) == 2
    err = _err(capsys)
    assert f"--static {out}" in err and "cannot" in err
    assert blocker.read_text() == "mine" and sorted(tmp_path.iterdir()) == [blocker]


def _scene_paths(html: str) -> set[str]:
    """Paths of the set_object commands embedded in a meshcat static page."""
    import base64
    import re

    import umsgpack

    out = set()
    for blob in re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html):
        cmd = umsgpack.unpackb(base64.b64decode(blob))
        if cmd.get("type") == "set_object":
            out.add(cmd["path"])
    return out


def test_review_draws_into_a_running_meshcat_server(capsys) -> None:
    from meshcat.servers.zmqserver import start_zmq_server_as_subprocess

    from payload.review.serve import close_viewer, open_viewer

    proc, zmq_url, web_url = start_zmq_server_as_subprocess()
    try:
        assert main(["review", "--zmq-url", zmq_url, "--reach-samples", "0"]) == 0
        assert f"meshcat: {web_url}" in capsys.readouterr().out
        vis = open_viewer(zmq_url)  # clears the review, so read the scene first
        paths = _scene_paths(vis.window.get_scene())
        assert paths == set()  # an attached review starts from an empty scene
        assert main(["review", "--zmq-url", zmq_url, "--reach-samples", "0"]) == 0
        paths = _scene_paths(vis.window.get_scene())
        close_viewer(vis)  # attached: leaves the server running
        assert proc.poll() is None
    finally:
        proc.kill()
        proc.wait()
    for link, meshes in _urdf_links(URDF).items():
        for k in range(len(meshes)):
            assert f"{REVIEW}/payload/{link}/visual{k}" in paths
    assert f"{REVIEW}/vehicle/bays" in paths


def test_stale_generated_models_are_rebuilt_before_the_review(tmp_path, design_dict, capsys):
    """The one rule for stale models (docs/design-loop.md): the command rebuilds them,
    saying so; the library's scene builder still refuses models that do not match."""
    from payload.design import stale_files
    from payload.review.errors import ReviewError

    path = _copy_project(tmp_path, design_dict, [0.20, 0.10, 0.10])
    data = {**design_dict, "rail": {**design_dict["rail"], "travel": 0.045}}
    path.write_bytes(tomli_w.dumps(data).encode())
    with pytest.raises(ReviewError, match="do not match"):
        build_design_review(project_files(path), reach_samples=0)
    html = tmp_path / "r.html"
    argv = ["review", "--design", str(path), "--reach-samples", "0", "--static", str(html)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "models: rebuilt " in out and "urdf/payload.urdf" in out and html.stat().st_size
    assert stale_files(load_design(path), path.parent.parent) == []


def test_watch_serves_the_page_and_stops_cleanly_on_ctrl_c(tmp_path, design_dict) -> None:
    import os
    import signal
    import subprocess
    import sys
    import time
    import urllib.request

    path = _copy_project(tmp_path, design_dict, design_dict["vehicle"]["bay_size"])
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "payload.cli", "review", "--watch", "--design", str(path)]
    proc = subprocess.Popen(
        [*cmd, "--port", "0", "--reach-samples", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        url = None
        deadline = time.monotonic() + 120
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if line.startswith("review: "):
                url = line.split()[1]
        assert url is not None, "no address printed"
        page = urllib.request.urlopen(url, timeout=10).read().decode()
        assert "MeshCat.Viewer" in page and "payload-overlay" in page
        update = json.loads(urllib.request.urlopen(url + "update?have=-1", timeout=10).read())
        assert update["version"] == 0 and update["commands"] and update["error"] is None
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0
        err = proc.stderr.read()
        assert "stopped" in err and "Traceback" not in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_watch_says_the_new_verdict_after_each_rebuild(tmp_path, design_dict) -> None:
    """``review --watch`` prints the stowed-fit verdict of every rebuild, not only that it
    rebuilt: a save that shrinks the bay below the stowed payload (the bay test above)
    turns pass into FAIL in the terminal."""
    import threading
    import time

    from payload.review.cli import live_review

    path = _copy_project(tmp_path, design_dict, design_dict["vehicle"]["bay_size"])
    live = live_review(str(path), 0)
    assert live.rebuild() is None
    assert any(n.startswith("stowed fit: pass") for n in live.notes())
    said: list[str] = []
    stop = threading.Event()
    watcher = threading.Thread(target=live.watch, args=(stop, said.append), daemon=True)
    watcher.start()
    try:
        data = {
            **design_dict,
            "vehicle": {**design_dict["vehicle"], "bay_size": [0.18, 0.10, 0.085]},
        }
        time.sleep(0.05)
        path.write_bytes(tomli_w.dumps(data).encode())
        deadline = time.monotonic() + 60
        while not any(s.startswith("stowed fit: FAIL") for s in said):
            assert time.monotonic() < deadline, said
            time.sleep(0.05)
    finally:
        stop.set()
        watcher.join(5)
    at = next(i for i, s in enumerate(said) if s.startswith("rebuilt in "))
    assert said[at + 1].startswith("stowed fit: FAIL"), said
    assert not any(s.startswith("design: ") for s in said)
    # a save that is not TOML: its line names the file once (it said "F: F: not valid")
    path.write_text(path.read_text() + "[[[broken\n")
    error = live.rebuild()
    assert error is not None and error.count(str(path)) == 1, error
    assert error.startswith(f"{path}: ") and "not valid TOML" in error, error
    # a parameter's error is named after the file, once too
    fingers = {**design_dict["finger"], "lengths": {**design_dict["finger"]["lengths"]}}
    fingers["lengths"]["distal"] = -0.01
    path.write_bytes(tomli_w.dumps({**design_dict, "finger": fingers}).encode())
    error = live.rebuild()
    assert error.startswith(f"{path}: finger.lengths.distal: ") and error.count(str(path)) == 1


def test_the_models_visuals_are_those_yourdfpy_reads(tmp_path):
    """The review reads the URDF's mesh visuals itself (no trimesh): against yourdfpy, on
    the committed model and on one whose visuals have an origin and a scale."""
    import yourdfpy

    from payload.review.model import PayloadModel

    text = URDF.read_text()
    first = text.index("<mesh ")
    edited = (
        text[:first].replace(
            "<visual>", '<visual>\n      <origin xyz="0.01 -0.02 0.03" rpy="0.3 -0.2 1.1"/>', 1
        )
        + text[first:].replace("<mesh ", '<mesh scale="0.5 2 1" ', 1)
    ).replace('filename="../', f'filename="{URDF.parent.parent}/')
    other = tmp_path / "other.urdf"
    other.write_text(edited)
    for urdf in (URDF, other):
        model = PayloadModel(urdf)
        robot = yourdfpy.URDF.load(str(urdf), build_scene_graph=False, load_meshes=False)
        assert model.links == tuple(link.name for link in robot.robot.links)
        for link in robot.robot.links:
            theirs = [v for v in link.visuals if v.geometry and v.geometry.mesh]
            mine = model.visuals[link.name]
            assert len(mine) == len(theirs)
            for v, w in zip(mine, theirs):
                assert v.mesh == (urdf.parent / w.geometry.mesh.filename).resolve()
                origin = np.eye(4) if w.origin is None else np.asarray(w.origin, float)
                assert np.allclose(v.origin, origin, atol=1e-15)
                scale = 1.0 if w.geometry.mesh.scale is None else w.geometry.mesh.scale
                assert np.array_equal(v.scale, np.broadcast_to(np.asarray(scale, float), (3,)))
    assert not np.allclose(PayloadModel(other).visuals[model.links[0]][0].origin, np.eye(4))


def test_the_replays_legend_names_each_colour_once() -> None:
    """One row per colour and no name twice: the CTB's bag and handle, the station's walls
    and handrails are told apart (the colours the world draws them in, read from the
    model here)."""
    from payload.review.trial_view import trial_legend
    from payload.sim.world import build_world

    world = build_world()
    rows = trial_legend(world, keep_in=True)
    names = [n for _, n in rows]
    assert len(set(names)) == len(names), names
    assert len({c for c, _ in rows}) == len(rows)
    m = world.model
    colour = {}
    for n in ("ctb_bag", "ctb_handle", "kibo_wall_x0_0", "kibo_handrail_0"):
        r, g, b = (round(float(v) * 255) for v in m.geom_rgba[m.geom(n).id][:3])
        colour[n] = f"#{r:02x}{g:02x}{b:02x}"
    legend = {n: c for c, n in rows}
    assert legend["CTB bag"] == colour["ctb_bag"] and legend["CTB handle"] == colour["ctb_handle"]
    assert legend["ISS walls"] == colour["kibo_wall_x0_0"]
    assert legend["ISS handrails"] == colour["kibo_handrail_0"]
    # the contact indicator stands out from every other colour of the replay (CIE76 colour
    # difference, from sRGB through XYZ to CIELAB, D65): the pads in contact were a green
    # beside finger C's green
    contact = legend["pads in opposing contact"]
    apart = min(_cie76(contact, c) for c, n in rows if n != "pads in opposing contact")
    assert apart >= 40.0, (contact, apart)


def _cie76(a: str, b: str) -> float:
    """The CIE76 colour difference of two ``#rrggbb`` sRGB colours."""

    def lab(text: str) -> np.ndarray:
        c = np.array([int(text[i : i + 2], 16) / 255 for i in (1, 3, 5)])
        c = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
        to_xyz = np.array(
            [[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]
        )
        t = to_xyz @ c / np.array([0.95047, 1.0, 1.08883])
        f = np.where(t > (6 / 29) ** 3, np.cbrt(t), t / (3 * (6 / 29) ** 2) + 4 / 29)
        return np.array([116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])])

    return float(np.linalg.norm(lab(a) - lab(b)))


def test_links_that_collide_are_drawn_in_the_collision_colour(
    tmp_path, design_dict, capsys
) -> None:
    """With 60 mm distal links the curled distal links run into the stage and the carriage:
    every failing part was the same red, so a reviewer could not tell a collision from a
    protrusion. The links that collide, as the envelope report's JSON lists them
    (``self_collisions``, and those colliding as the fingers unfold), are drawn in the
    collision colour (the envelope figure's magenta edge); none is outside the bays, so the
    only red ones are those the report finds reaching into the vehicle body as the fingers
    unfold; every other link keeps its finger's colour or grey; the legend explains the
    colour."""
    from payload.design.build import write

    root = _copy_project(tmp_path, design_dict, design_dict["vehicle"]["bay_size"]).parents[1]
    lengths = {**design_dict["finger"]["lengths"], "distal": 0.060}
    data = {**design_dict, "finger": {**design_dict["finger"], "lengths": lengths}}
    (root / "cad" / "design.toml").write_bytes(tomli_w.dumps(data).encode())
    write(load_design(root / "cad" / "design.toml"), root)
    capsys.readouterr()
    assert main(["--project", str(root), "report", "envelope", "--no-search", "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    colliding = {n for c in report["self_collisions"] for n in c["links"]}
    assert all(p["inside"] for p in report["parts"]) and report["deploy_path"]["vehicle_clear"]
    assert "stage" in colliding and any(n.endswith("_distal") for n in colliding)
    rv = build_design_review(project_files(root / "cad" / "design.toml"), reach_samples=0)
    objects = rv.scene.objects()
    links = [n for n, meshes in _urdf_links(root / "urdf" / "payload.urdf").items() if meshes]
    drawn = {n: objects[f"{REVIEW}/payload/{n}/visual0"].material.color for n in links}
    # red: only the links that reach into the vehicle body as the fingers unfold (the
    # report's deploy_path.unfolding.vehicle_hits), never one only colliding
    unfolding = report["deploy_path"]["unfolding"]
    hit = {h["link"] for h in unfolding["vehicle_hits"]}
    colliding |= {n for c in unfolding["collisions"] for n in c["links"]}
    red = {n for n, c in drawn.items() if c == OFFENDING_COLOUR}
    assert red == hit, f"drawn red: {sorted(red)}"
    from payload.envelope.drawing import COLLISION_COLOUR

    collision = int(COLLISION_COLOUR[1:], 16)
    assert {n for n, c in drawn.items() if c == collision} == colliding - hit
    for n, c in drawn.items():
        if n not in colliding | hit:
            assert c == link_colour(n), n
    rows = {text: colour for colour, text in rv.scene.overlay.legend}
    meaning = next(t for t, c in rows.items() if c.lower() == COLLISION_COLOUR.lower())
    assert "collides with another link" in meaning and "(none here)" not in meaning


def _deployment_rows(tree, per_second: int) -> np.ndarray:
    """The deployment the review plays, sampled ``per_second`` times a second: the stage
    down in 2 s with the fingers stowed, then the fingers and the rail straight from stowed
    to home in 1.5 s; shape (n, 18), ``ALL_JOINTS`` order."""
    from payload.design.tree import ALL_JOINTS

    stowed, home = tree.posture("stowed"), tree.posture("home")
    rows = []
    for s in np.linspace(0.0, 1.0, 2 * per_second + 1):
        rows.append({**stowed, "stage": (1 - s) * stowed["stage"] + s * home["stage"]})
    for s in np.linspace(0.0, 1.0, round(1.5 * per_second) + 1):
        rows.append(
            {j: (1 - s) * stowed[j] + s * home[j] for j in ALL_JOINTS} | {"stage": home["stage"]}
        )
    return np.array([[q[j] for j in ALL_JOINTS] for q in rows])


def test_links_that_collide_while_deploying_are_drawn_in_the_collision_colour(
    tmp_path, design_dict
) -> None:
    """With the home posture's fingers abducted -0.3 rad, B_distal and C_distal pass through
    each other as the fingers and the rail go from stowed to home: the envelope check
    passes (its sweep lowers the stage with the fingers held stowed), and the review drew
    them in their fingers' colours under a green verdict. The links that collide with
    another link in the deployment the page plays, as MuJoCo's model of the convex pieces
    finds them here (four times the page's frame rate), are drawn in the collision colour;
    every other link keeps its colour; the verdict says it, in the fail colour, and the
    legend's magenta says deploying."""
    from payload.design.build import write
    from payload.envelope.collisions import CollisionModel
    from payload.envelope.drawing import COLLISION_COLOUR
    from payload.envelope.vehicle import vehicle_from_dict

    path = _copy_project(tmp_path, design_dict, design_dict["vehicle"]["bay_size"])
    data = {**design_dict, "home": {**design_dict["home"], "finger": [0.0, -0.3, 0.0, 0.0]}}
    path.write_bytes(tomli_w.dumps(data).encode())
    write(load_design(path), path.parents[1])  # the MJCF keeps the home posture
    rv = build_design_review(project_files(path), reach_samples=0)
    assert rv.check.sweep.clear and not rv.check.self_collision  # stowed, the stage down
    design = load_design(path)
    tree = build_tree(design)
    model = CollisionModel(PayloadGeometry(tree), vehicle_from_dict(design.vehicle))
    pairs = model.check(_deployment_rows(tree, 120)).pair_counts()
    colliding = {n for pair in pairs if "vehicle" not in pair for n in pair}
    assert colliding == {"B_distal", "C_distal"}, pairs
    objects = rv.scene.objects()
    links = [n for n, meshes in _urdf_links(URDF).items() if meshes]
    drawn = {n: objects[f"{REVIEW}/payload/{n}/visual0"].material.color for n in links}
    assert {n for n, c in drawn.items() if c == int(COLLISION_COLOUR[1:], 16)} == colliding
    for n, c in drawn.items():
        if n not in colliding:
            assert c == link_colour(n), n
    verdict = rv.scene.overlay.subtitle  # the envelope report's
    assert verdict.startswith("stowed fit: FAIL: deployment: ")
    assert rv.scene.overlay.outcome == FAIL
    said = verdict.partition("stowed fit: FAIL: deployment: ")[2]
    assert said.startswith(("B_distal and C_distal collide", "C_distal and B_distal collide"))
    assert "as the fingers unfold" in said
    rows = {colour.lower(): text for colour, text in rv.scene.overlay.legend}
    assert "deploying" in rows[COLLISION_COLOUR.lower()]
    assert not rows[COLLISION_COLOUR.lower()].endswith("(none here)")


def test_the_collision_colour_stands_apart_from_every_other_colour_drawn(review) -> None:
    """Magenta sits between finger B's purple and finger D's pink in hue, but far from
    both in colour (CIE76, as the replay's contact indicator): every other colour of the
    design review's legend is at least 40 away (finger D's pink, the nearest, about 62)."""
    from payload.envelope.drawing import COLLISION_COLOUR

    others = [c for c, _ in review.scene.overlay.legend if c.lower() != COLLISION_COLOUR]
    assert len(others) == len(review.scene.overlay.legend) - 1
    apart = min(_cie76(COLLISION_COLOUR, c) for c in others)
    assert apart >= 40.0, apart


def test_a_failing_design_has_one_label_per_wall_naming_the_farthest_part(
    tmp_path, design_dict
) -> None:
    """With the bays 180 x 100 x 85 mm, 13 parts stick out of the bottom face: a label per
    part crowded over Astrobee's body. Each wall now has one label: a crossed wall's names
    the part sticking out farthest beyond it and how many more cross it, as found here from
    the stowed meshes (posed by the design tree) against the bay box, wall by wall (a part
    crossing two walls crosses both, not only the one it crosses most); the other walls
    keep their clearance, and no wall a part crosses is labelled with one (the base and the
    stage cross the forward wall less than the bottom face: a "0.00 mm" there read safe)."""
    path = _copy_project(tmp_path, design_dict, [0.18, 0.10, 0.085])
    rv = build_design_review(project_files(path), reach_samples=0)
    beyond = _beyond_the_bays(path)  # part -> how far beyond each wall [m]
    crossing = {w: [n for n, past in beyond.items() if past[w] > 1e-6] for w in range(6)}
    assert max(len(c) for c in crossing.values()) > 6  # the crowd at issue
    most = {n: int(np.argmax(past)) for n, past in beyond.items() if past.max() > 1e-6}
    assert any(most[n] != w for w, c in crossing.items() for n in c)  # a second wall crossed
    labels = rv.scene.overlay.labels
    assert len(labels) == 6  # one per wall
    said = {}
    for path_, text in labels:
        if "/findings/protrusion/" not in path_:
            m = re.fullmatch(r"\w+ - (.+) -?[\d.]+ mm", text)
            assert m, text
            wall = _WALL_NAMES.index(m[1])
            assert not crossing[wall], f"a clearance on {m[1]}, which {crossing[wall]} cross"
            continue
        m = re.fullmatch(r"(\w+) - ([\d.]+) mm beyond (.+?)(?: \(and (\d+) more\))?", text)
        assert m, text
        part, mm, wall, more = m[1], float(m[2]), _WALL_NAMES.index(m[3]), int(m[4] or 0)
        assert path_.rsplit("/", 1)[1] == part
        assert wall not in said, f"two labels on {m[3]}"
        said[wall] = part
        farthest = max(beyond[n][wall] for n in crossing[wall])
        assert beyond[part][wall] == pytest.approx(farthest, abs=1e-6), (text, beyond[part])
        assert mm == pytest.approx(farthest * 1e3, abs=0.051), text
        assert more == len(crossing[wall]) - 1, text
    assert set(said) == {w for w, c in crossing.items() if c}


def test_a_session_the_cap_stopped_is_said_to_have_stopped_early(tmp_path) -> None:
    """A closed recording of a session the --max-time cap stopped is a finished recording
    of a session that did not reach its task's end: the page's subtitle says both."""
    folder = _record_trial(tmp_path / "trial", meta={"ended_by": "max_time"})
    out = tmp_path / "r.html"
    assert main(["review", "--trial", str(folder), "--static", str(out), "--reach-samples",
                 "0"]) == 0  # fmt: skip
    page = out.read_text()
    assert "recording: finished, the session stopped early: stopped by the --max-time cap" in page


def test_clearance_labels_take_every_part_as_the_envelope_report_does(
    tmp_path, design_dict, capsys
):
    """With the sides 90 mm apart some parts stick out sideways: a wall's clearance label
    is still the least clearance to it over every part, inside the bays or not, as the
    envelope report's JSON gives per part (``report envelope --json``, python-fcl per wall);
    a wall a part crosses has its protrusion labelled instead."""
    root = tmp_path / "project"
    shutil.copytree(ROOT / "urdf", root / "urdf")
    shutil.copytree(ROOT / "cad" / "meshes", root / "cad" / "meshes")
    data = {**design_dict, "array": {**design_dict["array"], "side_gap": 0.090}}
    (root / "cad" / "design.toml").write_bytes(tomli_w.dumps(data).encode())
    capsys.readouterr()  # (the report rebuilds the models first)
    assert main(["--project", str(root), "report", "envelope", "--no-search", "--json"]) == 1
    parts = json.loads(capsys.readouterr().out)["parts"]
    rv = build_design_review(project_files(root / "cad" / "design.toml"), reach_samples=0)
    crossed = {p["wall"] for p in parts if not p["inside"]}
    assert crossed and len(crossed) < 6
    labels = dict(rv.scene.overlay.labels)
    walls = Vehicle().walls  # the design keeps the default bays
    drawn = set()
    for w in range(6):
        label = labels.get(f"{REVIEW}/findings/clearance/{_wall_key(w)}/label")
        if label is None:
            continue
        drawn.add(walls[w])
        part, _, rest = label.partition(" - ")
        mm = float(rest.removesuffix(" mm").rsplit(" ", 1)[1])
        least = min(
            p["wall_clearance_mm"][w] for p in parts if p["wall_clearance_mm"][w] is not None
        )
        assert mm == pytest.approx(least, abs=0.051), label
        named = next(p for p in parts if p["name"] == part)
        assert named["wall_clearance_mm"][w] == pytest.approx(least, abs=0.01), label
    assert drawn == set(walls) - crossed
    assert labels[f"{REVIEW}/findings/clearance/plus_z/label"] == "stage - bay mount 6.0 mm"


def test_a_review_of_a_design_file_that_is_not_there_says_so(tmp_path, capsys) -> None:
    """``review --design F`` with no file F said F was "not a design project's
    cad/design.toml"; a file that is not there, or a folder, is said to be that."""
    for given, said in ((tmp_path / "none.toml", "no such file"), (tmp_path, "a folder")):
        assert main(["review", "--design", str(given), "--reach-samples", "0"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"payload: error: --design {given}: {said}"], err


def test_open_without_a_browser_says_so(monkeypatch, capsys) -> None:
    """``review --open`` where no browser can be started (a server, a container) opened
    nothing without a word; it says so, naming the page to open."""
    import webbrowser

    from payload.review import cli

    opened: list[str] = []
    monkeypatch.setattr(webbrowser, "open", lambda url, new=0: opened.append(url) or False)
    cli._open_in_browser("http://127.0.0.1:7000/")
    assert opened == ["http://127.0.0.1:7000/"]
    err = capsys.readouterr().err.splitlines()
    assert err == ["payload: warning: --open: no browser to open here; open "
                   "http://127.0.0.1:7000/ in one"]  # fmt: skip
    monkeypatch.setattr(webbrowser, "open", lambda url, new=0: True)
    cli._open_in_browser("http://127.0.0.1:7000/")
    assert capsys.readouterr().err == ""
