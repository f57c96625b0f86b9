// The emulated Quest 3 and its hands (Meta's iwer), shared by the desktop mode (served
// before desktop.js by `payload teleop serve --desktop`) and the tests' emulated headset
// (injected by payload/teleop/emulate.py). Both load iwer's browser build first and put
// EMULATED_POSE before this file: the operator's neutral wrists, the head's pitch, the
// calibration gestures and the hands' speed (payload/teleop/emulate.py, one fact).
//
// The hands move toward their targets at a human speed (a jump would be a tracking glitch
// to the server), in WebXR's local-floor space (metres, Y up, -Z forward).
window.emulatedQuest = (() => {
  const device = new IWER.XRDevice(IWER.metaQuest3);
  device.installRuntime({ forceInstall: true });
  device.primaryInputMode = 'hand';
  // the head looks down at the vehicle, as an operator does (it floats at hand height a
  // metre ahead), not at the horizon: the view is the scene, the panel above it
  const pitch = EMULATED_POSE.headPitchDeg * Math.PI / 180;
  device.quaternion.set(Math.sin(pitch / 2), 0, 0, Math.cos(pitch / 2));
  const NEUTRAL = EMULATED_POSE.neutral;
  const SPEED = EMULATED_POSE.speed;  // [m/s]
  const PINCH_RATE = 2;  // [1/s] how fast the pinch value follows its target
  const hands = device.hands;
  const targets = {};
  const HALF_OPEN = EMULATED_POSE.gestures.neutral.pinch;
  for (const side of ['left', 'right']) {
    hands[side].position.set(...NEUTRAL[side]);
    hands[side].updatePinchValue(HALF_OPEN);
    targets[side] = { pos: NEUTRAL[side].slice(), pinch: HALF_OPEN };
  }
  // where a side's wrist goes for a gesture (its spread outward from the middle, and an
  // offset of both wrists), and its pinch value
  function place(side, gesture, offset) {
    const s = side === 'left' ? -1 : 1;
    const n = NEUTRAL[side], o = offset || [0, 0, 0];
    return [n[0] + s * gesture.spread + gesture.offset[0] + o[0],
      n[1] + gesture.offset[1] + o[1], n[2] + gesture.offset[2] + o[2]];
  }
  let last = performance.now();
  function follow(now) {
    // a frame's time can be before the script's start: never a step backwards
    const dt = Math.max(0, Math.min(0.1, (now - last) / 1000));
    last = now;
    for (const side of ['left', 'right']) {
      const h = hands[side], t = targets[side];
      const d = [t.pos[0] - h.position.x, t.pos[1] - h.position.y, t.pos[2] - h.position.z];
      const n = Math.hypot(...d), step = Math.min(n, SPEED * dt);
      if (n > 1e-6) {
        h.position.set(h.position.x + d[0] / n * step, h.position.y + d[1] / n * step,
          h.position.z + d[2] / n * step);
      }
      const dp = t.pinch - h.pinchValue;
      h.updatePinchValue(h.pinchValue + Math.sign(dp) * Math.min(Math.abs(dp), PINCH_RATE * dt));
    }
    requestAnimationFrame(follow);
  }
  requestAnimationFrame(follow);
  return {
    device,
    gestures: EMULATED_POSE.gestures,
    target(side, pos, pinch) { targets[side] = { pos, pinch }; },
    // both hands toward a gesture (a GESTURES entry's values), each wrist moved by its
    // side's offset in `offsets` [m] (none: at the gesture's place)
    pose(gesture, offsets) {
      for (const side of ['left', 'right']) {
        const at = place(side, gesture, offsets && offsets[side]);
        targets[side] = { pos: at, pinch: gesture.pinch };
      }
    },
    connect(side, on) { hands[side].connected = on; },
    wrist(side) { const p = hands[side].position; return [p.x, p.y, p.z]; },
  };
})();
