"""The teleoperation pipeline's compiled kernels (hand features, the One Euro filter's
step) give numpy's bits, and fall back when they cannot."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from payload import native
from payload.retarget.errors import RetargetError
from payload.teleop import filter_c, hand_c
from payload.teleop.filters import OneEuroConfig, OneEuroFilter, _step_numpy
from payload.teleop.hands import INDEX_TIP, THUMB_TIP, Hand
from payload.teleop.pipeline import human_feature_vector, human_features


@pytest.fixture
def fresh_kernel(monkeypatch, tmp_path):
    """Build the kernel anew (own cache), and forget it afterwards."""
    monkeypatch.setenv("PAYLOAD_CACHE_DIR", str(tmp_path))
    hand_c.compiled_hand_features.cache_clear()
    filter_c.compiled_one_euro.cache_clear()
    yield
    hand_c.compiled_hand_features.cache_clear()
    filter_c.compiled_one_euro.cache_clear()


def test_the_compiled_features_are_numpys():
    kernel = hand_c.compiled_hand_features(human_features)
    assert kernel is not None  # a compiler and numpy's OpenBLAS are here
    degenerate = 0
    with np.errstate(all="ignore"):
        for joints in hand_c.random_hands(3000, seed=99):
            got = kernel(joints)
            try:
                want = human_features(Hand(joints, True)).as_vector()
            except RetargetError:
                want = None
            if want is None:
                degenerate += 1
                assert got is None
            else:
                assert got.tobytes() == want.tobytes()
                assert human_feature_vector(Hand(joints, True)).tobytes() == want.tobytes()
    assert 0 < degenerate < 300  # coincident tips and NaN joints among the probes


@pytest.mark.parametrize("fault", ["coincident", "nan"])
def test_a_bad_hand_raises_numpys_error(fault):
    """The kernel declines a degenerate or non-finite hand, and the pipeline's features
    raise the numpy code's error for it."""
    joints = hand_c.random_hands(1, seed=3)[0].copy()
    if fault == "coincident":
        joints[INDEX_TIP] = joints[THUMB_TIP]
    else:
        joints[THUMB_TIP, 0] = np.nan
    with pytest.raises(RetargetError) as numpy_error:
        human_features(Hand(joints, True))
    with pytest.raises(RetargetError) as error:
        human_feature_vector(Hand(joints, True))
    assert str(error.value) == str(numpy_error.value)


def test_a_kernel_with_other_bits_is_refused(fresh_kernel, refused_kernel):
    """The wrist frame's x axis as along * (1 / |along|) (the same in exact arithmetic)
    is refused."""
    with refused_kernel(hand_c, "x[i] = along[i] / n;", "x[i] = along[i] * (1.0 / n);"):
        assert hand_c.compiled_hand_features(human_features) is None
    joints = hand_c.random_hands(1, seed=4)[0]
    want = human_features(Hand(joints, True)).as_vector()
    assert human_feature_vector(Hand(joints, True)).tobytes() == want.tobytes()


def test_native_off_runs_numpy(fresh_kernel, monkeypatch):
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    assert hand_c.compiled_hand_features(human_features) is None


def _run_filter(samples, stamps, config) -> list:
    """A filter's outputs (or the error's text) over the samples, with a reset now and then."""
    f = OneEuroFilter(config)
    out = []
    compiled = False
    for i, (x, t) in enumerate(zip(samples, stamps)):
        if i % 250 == 249:
            f.reset()
        try:
            out.append(f(x, t).tobytes())
        except ValueError as exc:
            out.append(str(exc))
        compiled |= f._bound is not None and f._bound[2] is not None
    out.append(compiled)
    return out


@pytest.mark.parametrize("config", [OneEuroConfig(), OneEuroConfig(1.0, 0.2, 2.5)])
def test_the_compiled_filter_step_is_numpys(config, monkeypatch):
    """1,000 samples of 25 joints (and of one point) with irregular, repeated and older
    stamps, resets and a non-finite sample: the same outputs and errors with the compiled
    step and with numpy's."""
    assert filter_c.compiled_one_euro(_step_numpy) is not None
    rng = np.random.default_rng(17)
    for rows in (25, 1):
        samples = np.cumsum(rng.normal(scale=0.004, size=(1000, rows, 3)), axis=0)
        samples[500, 0, 1] = np.inf
        steps = rng.choice([0.02, 0.021, 0.0, -0.01], size=1000, p=[0.85, 0.1, 0.03, 0.02])
        stamps = np.cumsum(steps)
        compiled = _run_filter(samples, stamps, config)
        monkeypatch.setattr(filter_c, "compiled_one_euro", lambda reference: None)
        plain = _run_filter(samples, stamps, config)
        monkeypatch.undo()
        assert compiled[-1] is True and plain[-1] is False  # the compiled step ran, or not
        assert compiled[:-1] == plain[:-1]
        assert "One Euro filter: non-finite sample" in compiled


def test_a_filter_kernel_with_other_bits_is_refused(fresh_kernel, refused_kernel):
    """The new estimate as x_prev + a (x - x_prev) (the same in exact arithmetic) is
    refused, and numpy's step runs."""
    with refused_kernel(
        filter_c,
        "xs[3 * r + i] = a * x[3 * r + i] + (1 - a) * xs[3 * r + i];",
        "xs[3 * r + i] = xs[3 * r + i] + a * (x[3 * r + i] - xs[3 * r + i]);",
        says="differs",
    ):
        assert filter_c.compiled_one_euro(_step_numpy) is None


@pytest.mark.parametrize("cap", [None, 0.19])
def test_the_compiled_limiter_step_is_numpys(cap):
    """3,000 steps toward requests that hold, move, rest and overshoot the cap, with the
    state replaced from outside now and then (as the base filter does): the compiled
    step and numpy's give the same values and rates in every bit."""
    from payload.teleop.channels import JerkLimiter
    from payload.teleop.limiter_c import compiled_limiter

    assert compiled_limiter(JerkLimiter) is not None
    mine, theirs = JerkLimiter(3, 0.0175, 0.02, cap), JerkLimiter(3, 0.0175, 0.02, cap)
    rng = np.random.default_rng(31)
    target = np.zeros(3)
    for k in range(3000):
        if k % 75 == 0:
            target = rng.normal(scale=(0.0, 0.02, 0.4, 1e-4, 0.1)[(k // 75) % 5], size=3)
        if k % 500 == 499:  # the state set from outside: new arrays
            v, r = rng.normal(scale=0.05, size=3), rng.normal(scale=0.005, size=3)
            mine.value, mine.rate = v.copy(), r.copy()
            theirs.value, theirs.rate = v.copy(), r.copy()
        got = mine.step(target, 0.02)
        want = theirs._step_vector(target, 0.02)
        assert got.tobytes() == want.tobytes(), k
        assert mine.rate.tobytes() == theirs.rate.tobytes(), k
    assert mine._bound is not None and mine._bound[2] is not None  # the compiled step ran


@pytest.mark.parametrize(
    ("module", "old", "new", "factory", "made_of"),
    [
        # the braking lead as rate * (|rate| / 2j): the same in exact arithmetic
        ("limiter_c", "w[i] = e[i] - rate[i] * nr / (2 * max_jerk);",
         "w[i] = e[i] - rate[i] * (nr / (2 * max_jerk));", "compiled_limiter", "JerkLimiter"),
        # C's fmod for Python's %: they differ on negative headings
        ("base_c", "pymod(desired - heading + M_PI", "fmod(desired - heading + M_PI",
         "compiled_base", "_base_channel"),
    ],
    ids=["limiter", "base channel"],
)  # fmt: skip
def test_a_channel_kernel_with_other_bits_is_refused(
    fresh_kernel, refused_kernel, module, old, new, factory, made_of
):
    """A jerk limiter or base channel kernel whose C differs from numpy's operations in a
    way exact arithmetic would not see is refused by its self-check, and numpy's step
    runs."""
    import importlib

    from payload.teleop import channels

    kernels = importlib.import_module(f"payload.teleop.{module}")
    make = getattr(kernels, factory)
    with refused_kernel(kernels, old, new, says="differs", forget=make):
        assert make(getattr(channels, made_of)) is None


# -- the tracking supervisor's hand check -----------------------------------------------------
def _supervisors():
    from payload.teleop.safety import SafetyConfig, TrackingSupervisor

    neutral = {"left": np.array([0.3, 0.2, 1.0]), "right": np.array([0.3, -0.2, 1.0])}
    compiled = TrackingSupervisor(SafetyConfig(), {s: v.copy() for s, v in neutral.items()})
    python = TrackingSupervisor(SafetyConfig(), {s: v.copy() for s, v in neutral.items()})
    for side in ("left", "right"):  # the numpy check for this one, for good
        python._kernels[side] = ((python.config, python.neutral[side]), None)
    return compiled, python, neutral


def test_the_compiled_hand_check_judges_as_numpy():
    """3,000 frames of two hands wandering about their neutral poses, with dropouts,
    non-finite joints, stretched hands, far wrists and jumps: the supervisor with the
    compiled check and with numpy's gives the same hands, weights and events."""
    from payload.teleop.hands import WRIST, HandFrame

    compiled, python, neutral = _supervisors()
    assert compiled._check_kernel("left") is not None
    rng = np.random.default_rng(31)
    pose = {s: neutral[s] + rng.normal(scale=0.03, size=(25, 3)) for s in neutral}
    kinds = set()
    for k in range(3000):
        hands = {}
        for side in ("left", "right"):
            pose[side] = pose[side] + rng.normal(scale=0.004, size=3)  # the hand drifts
            joints = pose[side] + rng.normal(scale=1e-3, size=(25, 3))
            glitch = rng.integers(40)
            if glitch == 0:
                joints[rng.integers(25), rng.integers(3)] = np.nan
            elif glitch == 1:
                joints[rng.integers(25)] = joints[WRIST] + rng.normal(size=3)  # stretched
            elif glitch == 2:
                joints = joints + rng.normal(scale=0.5, size=3)  # a jump
            elif glitch == 3:
                joints = joints + np.array([1.5, 0.0, 0.0])  # far from neutral
            hands[side] = Hand(joints, tracked=bool(glitch != 4))
        frame = HandFrame(0.02 * k - 0.05 * (k % 700 == 5), hands["left"], hands["right"])
        a, b = compiled.step(frame), python.step(frame)
        assert (a.blend_left, a.blend_right) == (b.blend_left, b.blend_right)
        for x, y in ((a.left, b.left), (a.right, b.right)):
            assert (x is None) == (y is None)
            assert x is None or np.array_equal(x.joints, y.joints, equal_nan=True)
        assert [(e.kind, e.detail) for e in a.events] == [(e.kind, e.detail) for e in b.events]
        kinds.update(e.detail.split(" ")[0] for e in a.events)
    assert {"non-finite", "joint", "wrist", "not"} <= kinds, kinds


def test_the_compiled_hand_check_on_the_limits():
    """Joints a hair inside, on and outside the reach and the workspace limits: the
    kernel's verdicts are numpy's (the same arithmetic, not just the same idea)."""
    compiled, python, neutral = _supervisors()
    kernel = compiled._check_kernel("left")
    c = compiled.config
    rng = np.random.default_rng(32)
    agreed = {True: 0, False: 0}
    for _ in range(300):
        wrist = neutral["left"] + rng.normal(scale=0.05, size=3)
        u = rng.normal(size=3)
        joints = wrist + rng.normal(scale=0.02, size=(25, 3))
        joints[0] = wrist
        for limit, where in ((c.max_extent, "joint"), (c.workspace_radius, "wrist")):
            for r in (np.nextafter(limit, 0.0), limit, np.nextafter(limit, 1.0)):
                hand = joints.copy()
                if where == "joint":
                    hand[7] = wrist + u / np.linalg.norm(u) * r
                else:
                    hand = hand - wrist + neutral["left"] + u / np.linalg.norm(u) * r
                verdict = kernel(hand, None, 0.0) == 0
                assert verdict == (not python._judge("left", hand, None, 0.0)), (where, r)
                agreed[verdict] += 1
    assert agreed[True] and agreed[False]


def test_a_hand_check_with_another_workspace_is_refused(fresh_kernel, monkeypatch, refused_kernel):
    """A kernel whose workspace is twice the radius judges displaced hands otherwise:
    refused, and the numpy check runs."""
    from payload.teleop import safety_c

    compiled, _, _ = _supervisors()
    with refused_kernel(safety_c, "> p[1]) return 3;", "> 2 * p[1]) return 3;", says="differs"):
        assert compiled._check_kernel("left") is None
    monkeypatch.setenv("PAYLOAD_NATIVE", "0")
    assert _supervisors()[0]._check_kernel("right") is None


# -- the base channel's step --------------------------------------------------------------------
def _base_pair(heading: float, with_right: bool):
    from payload.teleop.channels import _base_channel

    neutral, right = np.array([0.1, 0.25, 0.9]), np.array([0.1, -0.25, 0.9])
    compiled = _base_channel(neutral, heading, right if with_right else None)
    python = _base_channel(neutral, heading, right if with_right else None)
    python.__dict__["_compiled_step"] = None  # numpy's step, for good
    return compiled, python, neutral, right


@pytest.mark.parametrize(("heading", "with_right"), [(0.4, True), (-2.9, False)])
def test_the_compiled_base_step_is_numpys(heading, with_right):
    """3,000 steps of a wandering left wrist (in and out of the sphere), a right wrist
    that now and then holds, lost hands and a turning vehicle: the same commands, twists
    and limiter states, bit for bit, every mode met (hold needs the right neutral)."""
    from payload.teleop.base_c import _same, _same_state

    compiled, python, neutral, right_n = _base_pair(heading, with_right)
    assert compiled._compiled_step is not None
    rng = np.random.default_rng(41)
    left, yaw, modes = neutral.copy(), 0.0, set()
    for k in range(3000):
        if k % 120 == 0:
            aim = rng.normal(scale=(0.02, 0.08, 0.2)[(k // 120) % 3], size=3)
        left = left + 0.05 * (neutral + aim - left)
        right = right_n + (rng.normal(scale=0.1, size=3) if k % 200 > 150 else 0.0)
        yaw += 0.01
        rot = np.array(
            [[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0, 0, 1]]
        )
        args = (None if k % 97 == 3 else left, None if k % 31 == 1 else rot, right)
        a, b = compiled.step(*args), python.step(*args)
        assert _same(a, b) and _same_state(compiled, python), k
        modes.add(a.mode)
    assert modes == ({"drive", "hold", "brake"} if with_right else {"drive", "brake"})


def test_a_bad_wrist_gets_numpys_error_from_the_compiled_channel():
    from payload.teleop.channels import ChannelError

    compiled, python, neutral, _ = _base_pair(0.0, True)
    for bad in (np.array([np.nan, 0.0, 0.0]), np.array([0.1, np.inf, 0.9])):
        for ch in (compiled, python):
            with pytest.raises(ChannelError, match="left wrist is not 3 finite numbers"):
                ch.step(bad, None, None)
            with pytest.raises(ChannelError, match="right wrist is not 3 finite numbers"):
                ch.step(neutral, None, bad)  # the left wrist in neutral: the right one counts
    assert compiled.step(neutral + 0.2, None, None).mode == "drive"


def test_the_compiled_channel_leaves_what_it_does_not_take_to_numpy():
    """A Fortran-ordered rotation (numpy's product then takes another BLAS layout), object
    and integer wrists, a moved neutral, a changed heading or limit, and limiters whose
    state was replaced by one of another shape: the same results (or the same error) as
    numpy's step."""
    from payload.rotations import quat_to_matrix
    from payload.teleop.base_c import _same, _same_state

    compiled, python, neutral, _ = _base_pair(0.8, True)
    rng = np.random.default_rng(42)
    for k in range(400):
        q = rng.normal(size=4)
        rot = quat_to_matrix(q / np.linalg.norm(q))
        left = neutral + rng.normal(scale=0.1, size=3)
        args = [
            (left, np.asfortranarray(rot), None),
            (left.astype(object), rot, None),
            (np.round(left * 10).astype(int), rot[::1, ::1], None),
        ][k % 3]
        assert _same(compiled.step(*args), python.step(*args)), k
        assert _same_state(compiled, python)
        if k == 200:  # the settings change under the compiled step: it steps aside
            for ch in (compiled, python):
                ch.neutral[0] += 0.05  # in place: read in place
                ch.heading0 = -1.0
                ch.linear.max_jerk = 0.03
    for ch in (compiled, python):
        ch.linear.reset(np.zeros(2))
    with pytest.raises(ValueError, match="broadcast"):
        python.step(neutral + 0.2, None, None)
    with pytest.raises(ValueError, match="broadcast"):
        compiled.step(neutral + 0.2, None, None)


def test_a_hand_check_needs_a_neutral_it_can_read_in_place():
    from payload.teleop.safety import SafetyConfig, TrackingSupervisor

    strided = np.zeros((3, 2))[:, 0]  # a view: not contiguous
    sup = TrackingSupervisor(SafetyConfig(), {"left": strided, "right": np.zeros(3)})
    assert sup._check_kernel("left") is None and sup._check_kernel("right") is not None


def test_compiled_steps_follow_settings_changed_after_binding():
    """A limiter whose jerk bound, cap and zero thresholds (class constants an instance may
    set for itself), a base channel whose limiters' thresholds, and a filter whose settings
    change after their first compiled step: each steps as numpy's code with the new
    settings."""
    from payload.teleop.base_c import _same, _same_state
    from payload.teleop.channels import JerkLimiter

    mine, theirs = JerkLimiter(3, 0.0175, 0.02, 0.19), JerkLimiter(3, 0.0175, 0.02, 0.19)
    rng = np.random.default_rng(43)
    for k in range(320):
        if k == 80:
            mine.max_jerk = theirs.max_jerk = 0.05
        if k == 160:  # values below 0.15 have no outward direction for the cap
            mine.ZERO_VALUE = theirs.ZERO_VALUE = 0.15
        if k == 200:  # every braked error counts as none
            mine.ZERO_ERROR = theirs.ZERO_ERROR = 1.0
        if k == 240:
            mine.max_value = theirs.max_value = None
        target = rng.normal(scale=0.2, size=3)
        assert mine.step(target, 0.02).tobytes() == theirs._step_vector(target, 0.02).tobytes()
    assert mine._bound is not None and mine._bound[2] is not None  # compiled, rebound
    compiled, python, neutral, right = _base_pair(0.4, True)
    for k in range(200):
        if k == 100:
            for ch in (compiled, python):
                ch.linear.ZERO_ERROR = 1.0
        left = neutral + np.array([0.3, 0.1, 0.0]) * min(k, 50) / 50
        a, b = compiled.step(left, None, right), python.step(left, None, right)
        assert _same(a, b) and _same_state(compiled, python), k
    f, g = OneEuroFilter(OneEuroConfig()), OneEuroFilter(OneEuroConfig())
    g.__dict__["_stepper"] = lambda x: None  # numpy's step
    for k in range(100):
        if k == 50:
            f.config = g.config = OneEuroConfig(1.0, 0.2, 2.5)
        x = rng.normal(scale=0.01, size=(25, 3))
        assert f(x, 0.02 * k).tobytes() == g(x, 0.02 * k).tobytes()


def test_a_later_base_kernel_runs_the_short_check_and_it_still_refuses(fresh_checks):
    """The base kernel's first check steps each of its three channels 600 times against
    numpy; once that passed (stamped), a later process's check the first 200, and a
    channel whose numpy step answers otherwise on one of them is refused."""
    from payload.teleop import base_c
    from payload.teleop.channels import _base_channel

    asked: list[int] = []

    def factory(neutral, heading, right, lie_at=None):
        channel = _base_channel(neutral, heading, right)
        numpy_step = channel._step_numpy

        def counted(*args):
            asked.append(1)
            out = numpy_step(*args)
            if len(asked) == lie_at:  # a yaw rate off by one ulp
                out = dataclasses.replace(out, yaw_rate=float(np.nextafter(out.yaw_rate, 1.0)))
            return out

        channel._step_numpy = counted
        return channel

    def build(lie_at=None):
        asked.clear()
        base_c.compiled_base.cache_clear()
        try:
            return base_c.compiled_base(lambda *a: factory(*a, lie_at=lie_at)), len(asked)
        finally:
            base_c.compiled_base.cache_clear()

    kernel, n = build()
    channels = len(base_c.CHECK_CHANNELS)
    assert kernel is not None and n == channels * base_c.CHECK_STEPS
    assert len(list(fresh_checks.iterdir())) == 1
    native._CHECKED.clear()  # a later process
    kernel, n = build()
    assert kernel is not None and n == channels * base_c.SHORT_STEPS
    native._CHECKED.clear()
    stamps = sorted(fresh_checks.iterdir())
    lie = base_c.SHORT_STEPS + 150  # in the second channel
    assert build(lie_at=lie) == (None, lie)
    assert sorted(fresh_checks.iterdir()) == stamps  # a short check stamps nothing
    # a failed full check leaves no stamp either
    native._CHECKED.clear()
    for stamp in stamps:
        stamp.unlink()
    assert build(lie_at=1000) == (None, 1000)
    assert not list(fresh_checks.iterdir())


def test_later_hand_features_and_filter_steps_run_the_short_check(fresh_checks):
    """The hand features and the One Euro step are checked on all their probes in the
    first process, then, once a stamp says a full check passed, on the first tenth (a new
    process: their factories forgotten); a numpy answer that differs there still refuses
    the kernel."""
    asked: list[int] = []
    lie_at: list[int | None] = [None]

    def features(hand):
        asked.append(1)
        out = human_features(hand)
        if len(asked) == lie_at[0]:
            return out._replace(span=out.span + 1.0)
        return out

    def step(*args):
        asked.append(1)
        xs, ds = _step_numpy(*args)
        return (xs + 1.0, ds) if len(asked) == lie_at[0] else (xs, ds)

    for factory, reference, full in (
        (hand_c.compiled_hand_features, features, hand_c.CHECK_HANDS),
        (filter_c.compiled_one_euro, step, filter_c.CHECK_SAMPLES),
    ):
        counts = []
        for lie in (None, None, full // native.SHORT_SHARE - 2):
            factory.cache_clear()
            asked.clear()
            lie_at[0] = lie
            counts.append((factory(reference) is not None, len(asked)))
        factory.cache_clear()
        short = full // native.SHORT_SHARE
        assert counts == [(True, full), (True, short), (False, short - 2)]


def test_the_compiled_held_hand_is_numpys(monkeypatch):
    """The synthetic operator's hand through the compiled kernel and through the numpy
    code (the model's joints times the identity, plus the wrist with its tremor, plus the
    noise) on 3,000 random hands: the same bits, and only a wrist with a zero coordinate
    is left to numpy. An operator draws the same frames with the kernel and without it."""
    from payload.teleop import handmodel, handmodel_c
    from payload.teleop.calibration import CalibrationProcedure
    from payload.teleop.operator import OperatorPlan, SyntheticOperator, WorldView

    kernel = handmodel.held_hand_kernel()
    assert kernel is not None  # a compiler is here
    refused = 0
    for args in handmodel_c._probes(3000):
        want = handmodel._held_hand_numpy(*args[:-1], args[-1].copy())
        got = kernel(*args[:-1], args[-1].copy())
        if got is None:
            refused += 1
            wrist = handmodel_c.tremulous_wrist(*args[4:8])
            assert not np.all(wrist != 0.0)
            continue
        assert got.tobytes() == want.tobytes()
    assert refused == 3000 // handmodel_c.ZERO_WRIST_EVERY

    def frames() -> list[bytes]:
        plan = OperatorPlan(route=np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]))
        op = SyntheticOperator(plan, 4, CalibrationProcedure())
        out = []
        for k in range(400):
            fr = op.act(
                WorldView(k * 0.02, np.zeros(3), np.eye(3), np.zeros(3), np.zeros(3), False)
            )
            out += [fr.left.joints.tobytes(), fr.right.joints.tobytes()]
        return out

    compiled = frames()
    monkeypatch.setattr(handmodel, "held_hand_kernel", lambda: None)
    assert frames() == compiled


def test_a_held_hand_kernel_with_other_bits_is_refused(fresh_kernel, refused_kernel):
    """A phalanx added as len cos(a) u + len sin(a) v (the same in exact arithmetic) is
    refused."""
    from payload.teleop import handmodel, handmodel_c

    with refused_kernel(
        handmodel_c,
        "p[k] = p[k] + len * (cs * h->u[3 * r + k] + sn * h->v[3 * r + k]);",
        "p[k] = p[k] + (len * cs * h->u[3 * r + k] + len * sn * h->v[3 * r + k]);",
    ):
        kernel = handmodel_c.compiled_held_hand(handmodel.MODEL_TABLES, handmodel._held_hand_numpy)
        assert kernel is None
