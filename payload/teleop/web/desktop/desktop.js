// Desktop mode (payload teleop serve --desktop): try the page without a headset.
//
// Loaded before the page only when the server was started with --desktop, after iwer's
// browser build (/iwer.js, from the project's node_modules) and the emulated Quest 3 with
// hands (/hands.js, window.emulatedQuest): the keyboard moves the emulated hands toward
// targets at a human speed. The keys are KEYS below: the handler, the calibration prompts'
// key names and the help line are all made from it.
(() => {
  const quest = window.emulatedQuest;
  const G = quest.gestures;  // the calibration gestures (payload/teleop/emulate.py)
  const STEP = 0.05;  // [m] one key press of a move
  const pose = { offset: [0, 0, 0], spread: G.neutral.spread, pinch: G.neutral.pinch };
  const move = (axis, by) => () => { pose.offset[axis] += by; };
  // a gesture's key sets what that gesture changes from neutral, and keeps the rest (a
  // pinch with the wrists together); `neutral` sets everything back
  const make = (name) => () => {
    for (const field of ['spread', 'pinch']) {
      if (name === 'neutral' || G[name][field] !== G.neutral[field]) pose[field] = G[name][field];
    }
    if (name === 'neutral') pose.offset = [0, 0, 0];
  };
  // [key, what it does, the move it makes, or the gesture it makes]
  const KEYS = [
    ['w', 'forward', move(2, -STEP)], ['s', 'back', move(2, STEP)],
    ['a', 'left', move(0, -STEP)], ['d', 'right', move(0, STEP)],
    ['r', 'up', move(1, STEP)], ['f', 'down', move(1, -STEP)],
    ['q', 'pinch', 'pinch'], ['e', 'open', 'open'], ['z', 'together', 'together'],
    ['x', 'apart', 'apart'], [' ', 'half open and centred', 'neutral'],
  ].map(([key, what, does]) => (typeof does === 'string'
    ? [key, what, make(does), does] : [key, what, does]));
  const label = (key) => (key === ' ' ? 'Space' : key.toUpperCase());  // as the help names it
  const actions = Object.fromEntries(KEYS.map(([key, , act]) => [key, act]));
  window.addEventListener('keydown', (ev) => {
    const act = actions[ev.key.toLowerCase()];
    if (act) {
      act();
      quest.pose({ spread: pose.spread, pinch: pose.pinch, offset: pose.offset });
      ev.preventDefault();
    }
  });
  // the key that makes each calibration step's gesture (named in the page's prompt): the
  // key of that gesture, or of the one with the same values (release: neutral's)
  const same = (a, b) => JSON.stringify(a) === JSON.stringify(b);
  const stepKeys = {};
  for (const step of Object.keys(G)) {
    const made = KEYS.find((k) => k[3] && same(G[k[3]], G[step]));
    if (made) stepKeys[step] = label(made[0]);
  }
  const at = (s) => quest.wrist(s);
  window.__desktop = { pose, wrist: at, stepKeys };
  const moves = KEYS.filter((k) => !k[3]).map((k) => label(k[0])).join('/');
  const gestures = KEYS.filter((k) => k[3]).map((k) => `${label(k[0])} ${k[1]}`).join(', ');
  window.addEventListener('DOMContentLoaded', () => {
    const help = document.createElement('p');
    help.id = 'desktop-help';
    help.textContent = `Desktop mode (emulated headset): Enter VR, then ${moves} move ` +
      `the hands, ${gestures}; Exit VR (top) leaves the session.`;
    document.querySelector('main').appendChild(help);
  });
})();
