// Desktop mode (payload teleop serve --desktop): try the page without a headset.
//
// Loaded before the page only when the server was started with --desktop, after iwer's
// browser build (/iwer.js, from the project's node_modules): an emulated Quest 3 with
// hands is installed as navigator.xr, and the keyboard moves the emulated hands toward
// targets at a human speed (a jump would be a tracking glitch to the server):
//   W / S  both wrists forward / back     A / D  left / right     R / F  up / down
//   Q  pinch (thumb and index together)   E  open wide            Space  half open, centred
//   Z  wrists together                    X  wrists apart
(() => {
  const device = new IWER.XRDevice(IWER.metaQuest3);
  device.installRuntime({ forceInstall: true });
  device.primaryInputMode = 'hand';
  // the head looks down at the vehicle, as an operator does (it floats at hand height a
  // metre ahead), not at the horizon: the view is the scene, the panel above it.
  // DESKTOP_POSE: put before this file by the server, the tests' emulated headset's pose
  // (payload/teleop/emulate.py: NEUTRAL, HEAD_PITCH_DEG)
  const PITCH = DESKTOP_POSE.headPitchDeg * Math.PI / 180;
  device.quaternion.set(Math.sin(PITCH / 2), 0, 0, Math.cos(PITCH / 2));
  const NEUTRAL = DESKTOP_POSE.neutral;
  const SPEED = 0.4;  // [m/s] how fast a hand moves toward its target
  const STEP = 0.05;  // [m] one key press of W/A/S/D/R/F
  const pose = { offset: [0, 0, 0], spread: 0, pinch: 0.5 };
  const hands = device.hands;
  for (const side of ['left', 'right']) {
    hands[side].position.set(...NEUTRAL[side]);
    hands[side].updatePinchValue(0.5);
  }
  function target(side) {
    const s = side === 'left' ? -1 : 1;
    const n = NEUTRAL[side];
    return [n[0] + s * pose.spread + pose.offset[0], n[1] + pose.offset[1],
      n[2] + pose.offset[2]];
  }
  const keys = {
    w: () => { pose.offset[2] -= STEP; }, s: () => { pose.offset[2] += STEP; },
    a: () => { pose.offset[0] -= STEP; }, d: () => { pose.offset[0] += STEP; },
    r: () => { pose.offset[1] += STEP; }, f: () => { pose.offset[1] -= STEP; },
    q: () => { pose.pinch = 1; }, e: () => { pose.pinch = 0; },
    z: () => { pose.spread = -0.1; }, x: () => { pose.spread = 0.12; },
    ' ': () => { pose.offset = [0, 0, 0]; pose.spread = 0; pose.pinch = 0.5; },
  };
  window.addEventListener('keydown', (ev) => {
    const fn = keys[ev.key.toLowerCase()];
    if (fn) { fn(); ev.preventDefault(); }
  });
  let last = performance.now();
  function follow(now) {
    // a frame's time can be before the script's start: never a step backwards
    const dt = Math.max(0, Math.min(0.1, (now - last) / 1000));
    last = now;
    for (const side of ['left', 'right']) {
      const h = hands[side], t = target(side);
      const d = [t[0] - h.position.x, t[1] - h.position.y, t[2] - h.position.z];
      const n = Math.hypot(...d), step = Math.min(n, SPEED * dt);
      if (n > 1e-6) {
        h.position.set(h.position.x + d[0] / n * step, h.position.y + d[1] / n * step,
          h.position.z + d[2] / n * step);
      }
      const dp = pose.pinch - h.pinchValue;
      h.updatePinchValue(h.pinchValue + Math.sign(dp) * Math.min(Math.abs(dp), 2 * dt));
    }
    requestAnimationFrame(follow);
  }
  requestAnimationFrame(follow);
  const at = (s) => [hands[s].position.x, hands[s].position.y, hands[s].position.z];
  // the key that makes each calibration step's gesture (named in the page's prompt)
  const stepKeys = { neutral: 'Space', pinch: 'Q', open: 'E', together: 'Z', apart: 'X',
    release: 'Space' };
  window.__desktop = { pose, wrist: at, stepKeys };
  window.addEventListener('DOMContentLoaded', () => {
    const help = document.createElement('p');
    help.id = 'desktop-help';
    help.textContent = 'Desktop mode (emulated headset): Enter VR, then W/S/A/D/R/F move ' +
      'the hands, Q pinch, E open, Z together, X apart, Space half open and centred; ' +
      'Exit VR (top) leaves the session.';
    document.querySelector('main').appendChild(help);
  });
})();
