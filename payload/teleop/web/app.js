// The live teleop page: WebXR hand tracking in, frames out over a WebSocket, state drawn.
//
// Each XR frame it reads the 25 XRHand joints of both hands in the local-floor space and
// sends {"type": "frame", "seq", "t", "hands"} (see payload/teleop/messages.py). It answers
// the server's clock pings, shows the calibration prompts and the scene, and reconnects by
// itself when the WebSocket drops (the server brakes the vehicle meanwhile).
//
// What it shows, where: the header's one status line says what is current in a few words
// (the link, or the session state and this page's role); #prompt and #hint over the view
// say what to do and why (the calibration prompt and why the last attempt was refused, how
// to take control, a safe stop's reason, the server's notice); the 3D panel shows the live
// numbers, and in VR, where a headset shows no page, also the prompt, the refusal, the safe
// stop and the role. The server's identifiers (state, step, module names) are shown as
// words, never as they are sent.

import { Renderer, lookAt, moduleHolding, perspective, ANCHOR } from './render.js';

export const JOINTS = [
  'wrist', 'thumb-metacarpal', 'thumb-phalanx-proximal', 'thumb-phalanx-distal', 'thumb-tip',
  ...['index-finger', 'middle-finger', 'ring-finger', 'pinky-finger'].flatMap((f) =>
    ['metacarpal', 'phalanx-proximal', 'phalanx-intermediate', 'phalanx-distal', 'tip']
      .map((p) => `${f}-${p}`)),
];

const token = new URLSearchParams(location.search).get('token');
const tokenQuery = token ? `?token=${encodeURIComponent(token)}` : '';  // the WebSocket's, /status'
const wsUrl = `${location.protocol === 'https:' ? 'wss' : 'ws'}://${location.host}/ws${tokenQuery}`;
const $ = (id) => document.getElementById(id);

// what the browser test (and a curious developer) can look at
const debug = {
  sent: 0, received: 0, connects: 0, state: null, open: false, xr: false,
  role: null, driver: null, hardware: false, link: 'connecting to the teleop server…', canEnter: false,
  why: null, vrError: null, panel: [], fingerLines: [], panelBox: null,
  handedOver: false,  // this page handed control over: it sends no hands until taken back
};
window.__teleop = debug;

// ---- the WebSocket, reconnecting -----------------------------------------------------
class Link {
  constructor(onMessage) {
    this.onMessage = onMessage;
    this.ws = null;
    this.retry = 250;
    this.connect();
  }

  connect() {
    const ws = new WebSocket(wsUrl);
    let opened = false;
    this.ws = ws;
    ws.onopen = () => {
      opened = true;
      this.retry = 250;
      debug.open = true;
      debug.connects += 1;
      debug.link = 'connected';
      debug.why = null;
      debug.state = null;  // nothing of the last connection's session is current any more
      debug.role = null;
      showStatus();
    };
    ws.onmessage = (ev) => {
      debug.received += 1;
      try { this.onMessage(JSON.parse(ev.data)); } catch (e) { console.error(e); }
    };
    ws.onclose = () => {
      const wait = `retrying in ${(this.retry / 1000).toFixed(1)} s`;
      debug.open = false;
      debug.link = `disconnected, ${wait}`;
      debug.why = null;
      debug.state = null;
      debug.role = null;
      showStatus();
      if (!opened) this.explain(wait);  // refused, not dropped: say why when the server can
      setTimeout(() => this.connect(), this.retry);
      this.retry = Math.min(4000, this.retry * 2);
    };
    ws.onerror = () => ws.close();
  }

  // A WebSocket the server refused looks like any other failure to the page: ask /status
  // (the page's own token) what it is. 403: the token is not this server's (a restarted
  // server makes a new one); reachable: the server has as many pages as it takes. The
  // status line says it in a few words, #hint why and what to do.
  async explain(wait) {
    let link = null, why = null;
    try {
      const r = await fetch(`/status${tokenQuery}`, { cache: 'no-store' });
      if (r.status === 403) {
        link = `refused by the server, ${wait}`;
        why = 'The server refused this page\'s token (a restarted server has a new one): ' +
          'open the address it printed, with its ?token=';
      } else if (r.ok) {
        const status = await r.json();
        link = `turned away by the server, ${wait}`;
        why = `The server turned this page away: it takes at most ${status.max_clients} ` +
          'pages at once (close a spare one).';
      }
    } catch (e) {
      why = null;  // the server is not reachable: "disconnected" says it
    }
    if (why && !debug.open) {
      debug.link = link;
      debug.why = why;
      showStatus();
    }
  }

  send(obj) {
    if (this.ws && this.ws.readyState === WebSocket.OPEN) {
      this.ws.send(JSON.stringify(obj));
      return true;
    }
    return false;
  }
}

// ---- words for the server's identifiers --------------------------------------------------
// The messages name states, calibration steps and modules by identifiers (a contract with the
// server and the recordings, kept as they are); the page shows words instead: the states'
// below, a module's title as the server sends it, and any other identifier's parts spaced.
const STATE_WORDS = {
  waiting: 'waiting for an operator',
  calibrating: 'calibrating',
  teleop: 'teleoperating',
  safe_stop: 'safe stop',
  stopped: 'server stopped',
};

// an identifier without words of its own (or a newer server's state): its parts, spaced
export function words(id) { return String(id).replace(/[_-]+/g, ' ').trim(); }
const say = (table, id) => (Object.hasOwn(table, id) ? table[id] : words(id));

const ROLES = {
  holder: 'you have control',
  watching: 'another operator has control',
  free: 'control free',
};

// ---- drawing ---------------------------------------------------------------------------
const canvas = $('view');
const gl = canvas.getContext('webgl', { xrCompatible: true, antialias: true });
const renderer = new Renderer(gl);

// What takes control, for a free page: outside VR, the step before the calibration, Enter
// VR (where it can); once the session is calibrated the next holder drives with that
// calibration. Null when this page is not free.
function roleHint() {
  if (debug.role !== 'free') return null;
  const kept = debug.state && debug.state.calibrated;
  if (debug.xr && debug.handedOver) {
    return 'You handed control over: the next operator\'s hands take it; press Take control ' +
      'to take it back.';
  }
  if (debug.xr) {
    return kept ? 'Control is free: your hands take it (the calibration is kept).'
      : 'Control is free: calibrate to take it.';
  }
  // no WebXR here: where a headset is, and how to try it without one
  const noHeadset = ' No headset? Start the server with --desktop to emulate one in this ' +
    'browser.';
  if (kept) {
    return debug.canEnter ? 'Control is free: press Enter VR to take it (the calibration is kept).'
      : 'Control is free: open this page in a WebXR headset and press Enter VR to take it ' +
        '(the calibration is kept).' + noHeadset;
  }
  return debug.canEnter ? 'Control is free: press Enter VR, then calibrate to take it.'
    : 'Control is free: open this page in a WebXR headset, press Enter VR and calibrate to ' +
      'take it.' + noHeadset;
}

// The calibration prompt, only while the server says "calibrating": a state message after
// an attempt ended (the page reconnected, control was handed over) still carries that
// attempt's last step and prompt beside "waiting", and showing them would contradict it.
function promptText() {
  const st = debug.state;
  if (!st || st.state !== 'calibrating' || !st.prompt) return '';
  // the desktop mode's emulated hands make each gesture on a key: the prompt names it
  const key = window.__desktop && window.__desktop.stepKeys[st.step];
  const press = key ? ` \u2014 desktop: press ${key}` : '';
  return `${st.prompt}\u00a0(${st.remaining.toFixed(1)}\u00a0s)${press}`;  // countdown in one piece
}

// Why the last calibration attempt was refused, while the next one's prompt shows: the
// operator sees the prompts start again, and this says why.
function restartText() {
  const st = debug.state;
  return promptText() && st.calibration_failure
    ? `calibration restarted: ${st.calibration_failure}` : null;
}

// the header's one status line, in a few words: the link, or the session state and the role
function statusText() {
  const st = debug.state;
  if (!debug.open) return debug.link;
  let state = 'connected, waiting for the session';
  if (st) {
    state = say(STATE_WORDS, st.state);
    if (st.state === 'calibrating' && st.step) state += `: ${words(st.step)}`;
  }
  return [state, debug.role ? ROLES[debug.role] : null].filter(Boolean).join(' · ');
}

// the server's notice, when it is for this page: one for the holder ("fly with your left
// wrist") is the operator's instruction, not the watchers'
function noticeText(st) {
  if (!st || !st.notice) return null;
  return st.notice_to && st.notice_to !== debug.role ? null : st.notice;
}

// what to do and why, below the prompt: [{text, alert}]
function hintLines() {
  const st = debug.open ? debug.state : null;
  const lines = [];
  if (debug.vrError) lines.push({ text: `Could not start VR: ${debug.vrError}`, alert: true });
  if (!debug.open) {
    if (debug.why) lines.push({ text: debug.why, alert: true });
    return lines;
  }
  const restart = restartText();
  if (restart) lines.push({ text: restart, alert: true });
  if (st && st.safe_stop) {
    lines.push({ text: `Safe stop: ${st.safe_stop}. The vehicle brakes and the fingers hold ` +
      'until the hands are back.', alert: true });
  }
  const role = roleHint();
  if (role) lines.push({ text: role, alert: false });
  const notice = noticeText(st);
  if (notice && !promptText()) lines.push({ text: notice, alert: false });
  return lines;
}

// the live numbers, which nothing else on the page shows
function numbersText(st) {
  const here = moduleHolding(renderer.scene, st.vehicle.pos);
  return (here ? `in ${here.name} · ` : '') +
    `vehicle ${st.vehicle.speed.toFixed(3)} m/s · rail ${(st.rail * 1000).toFixed(0)} mm` +
    (st.contact ? ' · CTB held' : '');
}

// The 3D panel: the live numbers; in VR (a headset shows no page, only this panel) also
// the prompt and why the calibration restarted, a safe stop, the role when it is not
// control, the notice, or the link.
function panelLines() {
  const st = debug.open ? debug.state : null;
  const numbers = st && st.vehicle ? [numbersText(st)] : [];
  if (!debug.xr) return numbers;  // the header, the prompt and the hint say the rest
  if (!debug.open) return [debug.link, debug.why].filter(Boolean);
  const prompt = promptText();
  const role = debug.role === 'holder' ? null : roleHint() || ROLES[debug.role];
  // a headset shows no header: the one driving real servos is told so first
  const hardware = debug.hardware ? debug.driver : null;
  return [hardware && `driver: ${hardware}`, prompt, restartText(),
    st && st.safe_stop ? `safe stop: ${st.safe_stop}` : null, role, ...numbers,
    prompt ? null : noticeText(st)].filter(Boolean);
}

function showStatus() {
  const st = debug.open ? debug.state : null;
  const status = statusText();
  $('status').textContent = status;
  $('status').title = status;  // the whole line, should a narrow window cut it short
  $('status').classList.toggle('alert', Boolean(st && st.safe_stop));
  $('prompt').textContent = promptText();
  const hint = $('hint');
  hint.replaceChildren(...hintLines().map(({ text, alert }) => {
    const p = document.createElement('p');
    p.textContent = text;
    if (alert) p.className = 'alert';
    return p;
  }));
  $('driver').textContent = debug.driver ? `driver: ${debug.driver}` : '';
  // Hand over control while holding it; Take control back after handing it over in VR
  const takeBack = debug.handedOver && debug.xr && debug.role === 'free';
  $('handover').hidden = !(debug.role === 'holder' || takeBack);
  $('handover').textContent = debug.role === 'holder' ? 'Hand over control' : 'Take control';
  debug.panel = panelLines();
  renderer.setPanel(debug.panel, st && st.safe_stop ? '#f96' : '#7fd');
}

const link = new Link((msg) => {
  if (msg.type === 'ping') {
    link.send({ type: 'pong', id: msg.id, t: performance.now() });
  } else if (msg.type === 'hello') {
    const scene = msg.scene || {};  // the modules labelled by their titles, not identifiers
    renderer.scene = { ...scene, modules: (scene.modules || []).map((m) => (
      { ...m, name: m.title || words(m.name || '') })) };
    debug.driver = msg.driver || null;
    debug.hardware = Boolean(msg.hardware);  // the server says whether it drives servos
    showStatus();
  } else if (msg.type === 'state') {
    debug.state = msg;
    renderer.state = msg;
    if (msg.driver) debug.driver = msg.driver;
    showStatus();
  } else if (msg.type === 'control') {
    debug.role = msg.role;
    showStatus();
  }
});
$('handover').addEventListener('click', () => {
  if (debug.role === 'holder') {
    // this page's hands stop here: they would take control straight back (the next page
    // to send frames takes it), and the hand-over would be no hand-over
    debug.handedOver = true;
    link.send({ type: 'release' });
  } else {
    debug.handedOver = false;  // Take control: this page's hands take it again
  }
  showStatus();
});
showStatus();

const overlap = (a, b) => a.left < b.right && b.left < a.right && a.top < b.bottom &&
  b.top < a.bottom;

// The boxes' labels over the view. `region` is where the drawn view lies on the page (CSS
// pixels, as getBoundingClientRect gives them: the canvas outside VR, the emulator's view
// of the first eye in the desktop mode); `labels` and `panel` are in that view's normalised
// device coordinates. A label the 3D panel would cover is put just under the panel (the
// panel stands in front of the scene, and a label over it would cross its text), below
// any label already there.
function placeLabels(region, labels, panel) {
  const box = $('labels');
  const origin = box.getBoundingClientRect();
  const px = (x, y) => [region.left + ((x + 1) / 2) * region.width,
    region.top + ((1 - y) / 2) * region.height];
  let covered = null;  // the panel on the page
  if (panel) {
    const [left, top] = px(panel.x0, panel.y1), [right, bottom] = px(panel.x1, panel.y0);
    covered = { left, top, right, bottom };
  }
  debug.panelBox = covered;
  while (box.children.length < labels.length) box.appendChild(document.createElement('span'));
  const placed = [];
  [...box.children].forEach((el, i) => {
    const l = labels[i];
    el.hidden = !l || Math.abs(l.x) > 1 || Math.abs(l.y) > 1;
    if (el.hidden) return;
    el.textContent = l.text;
    const [x, y] = px(l.x, l.y);
    el.style.left = `${x - origin.left}px`;
    el.style.top = `${y - origin.top}px`;
    let r = el.getBoundingClientRect();
    if (covered && overlap(r, covered)) {
      let top = covered.bottom + 2;
      for (let moved = true; moved;) {  // down past every label in the way
        const at = { left: r.left, right: r.right, top, bottom: top + r.height };
        const hit = placed.find((o) => overlap(at, o));
        moved = Boolean(hit);
        if (hit) top = hit.bottom + 2;
      }
      el.style.top = `${top + r.height / 2 - origin.top}px`;
      r = el.getBoundingClientRect();
    }
    placed.push(r);
  });
}

function drawDesktop() {
  if (debug.xr) return;
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.viewport(0, 0, w, h);
  gl.clearColor(0.04, 0.06, 0.09, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  const eye = [0, 1.6, 0.8];
  renderer.draw(perspective(1.0, w / Math.max(h, 1), 0.05, 60), lookAt(eye, ANCHOR, [0, 1, 0]));
  debug.fingerLines = renderer.fingerLines || [];
  placeLabels(canvas.getBoundingClientRect(), renderer.labels || [], renderer.panelBox);
  requestAnimationFrame(drawDesktop);
}
requestAnimationFrame(drawDesktop);

// ---- WebXR -------------------------------------------------------------------------------
let seq = 0;

function readHand(frame, source, space) {
  const joints = [];
  for (const name of JOINTS) {
    const jointSpace = source.hand.get(name);
    const pose = jointSpace && frame.getJointPose(jointSpace, space);
    if (!pose) return { tracked: false, joints: null };
    const p = pose.transform.position;
    joints.push([p.x, p.y, p.z]);
  }
  return { tracked: true, joints };
}

function onXRFrame(t, frame) {
  const session = frame.session;
  session.requestAnimationFrame(onXRFrame);
  const space = debug.space;
  const hands = { left: null, right: null };
  for (const source of session.inputSources) {
    if (source.hand && (source.handedness === 'left' || source.handedness === 'right')) {
      hands[source.handedness] = readHand(frame, source, space);
    }
  }
  // a watching page sends no frames (the server would refuse them); a free one takes
  // control, unless it has just handed it over
  const sending = debug.role !== 'watching' && !debug.handedOver;
  if (sending && link.send({ type: 'frame', seq, t, hands })) debug.sent += 1;
  seq += 1;
  const pose = frame.getViewerPose(space);
  const layer = session.renderState.baseLayer;
  gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
  gl.clearColor(0.02, 0.03, 0.05, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  if (!pose) return;
  let first = null;
  for (const view of pose.views) {
    const vp = layer.getViewport(view);
    gl.viewport(vp.x, vp.y, vp.width, vp.height);
    renderer.draw(view.projectionMatrix, view.transform.inverse.matrix);
    if (!first) first = { vp, labels: renderer.labels, panel: renderer.panelBox };
  }
  // the labels over the first eye's view where the page shows it (the desktop mode's
  // emulator: its view of the session covers the window; a headset shows no page)
  const r = canvas.getBoundingClientRect();
  const fw = layer.framebufferWidth || canvas.width, fh = layer.framebufferHeight || canvas.height;
  const { vp } = first;
  placeLabels({
    left: r.left + (vp.x / fw) * r.width, width: (vp.width / fw) * r.width,
    top: r.top + ((fh - vp.y - vp.height) / fh) * r.height, height: (vp.height / fh) * r.height,
  }, first.labels, first.panel);
}

// In VR the button ends the session: a headset shows no page then, but the desktop
// mode's emulator does (its full-window view lies under the header, see page.css).
async function enterXR() {
  const button = $('enter');
  button.disabled = true;
  const session = await navigator.xr.requestSession('immersive-vr', {
    requiredFeatures: ['local-floor', 'hand-tracking'],
  });
  debug.session = session;  // from here on the button ends it, whatever fails below
  debug.handedOver = false;  // entering VR is taking control when it is free
  session.addEventListener('end', () => {
    // leaving VR is leaving the controls: hand them over, saying so (the vehicle is braked
    // until the next holder's frames, this page's own if it enters VR again, and the safe
    // stop says the operator left VR, not that the page disconnected). Sent whatever role
    // the page was last told: the server acts on it only from the page holding control.
    link.send({ type: 'xr_end' });
    const drawing = debug.xr;  // the desktop view's loop stopped only once in VR
    debug.xr = false;
    document.body.classList.remove('xr');
    debug.session = null;
    button.textContent = 'Enter VR';
    button.disabled = false;
    showStatus();
    if (drawing) requestAnimationFrame(drawDesktop);
  });
  button.textContent = 'Exit VR';
  debug.vrError = null;
  await gl.makeXRCompatible();
  session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
  debug.space = await session.requestReferenceSpace('local-floor');
  debug.xr = true;
  document.body.classList.add('xr');  // the labels over the emulator's view (page.css)
  button.disabled = false;
  showStatus();
  session.requestAnimationFrame(onXRFrame);
}

async function setup() {
  const button = $('enter');
  if (!navigator.xr) {
    button.textContent = 'WebXR unavailable (HTTPS or localhost needed)';
    return;
  }
  const ok = await navigator.xr.isSessionSupported('immersive-vr');
  button.disabled = !ok;
  button.textContent = ok ? 'Enter VR' : 'immersive VR not supported here';
  debug.canEnter = ok;
  showStatus();
  button.addEventListener('click', () => {
    if (debug.session) { debug.session.end(); return; }
    enterXR().catch((e) => {
      console.error(e);
      button.disabled = false;
      debug.vrError = e.message;  // said in #hint until VR starts
      showStatus();
    });
  });
}
setup();
