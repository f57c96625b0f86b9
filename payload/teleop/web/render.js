// A small WebGL renderer for the live teleop page: wire boxes, lines and a text panel.
//
// The server's world is the workbench frame (REP-103: x forward, y left, z up, metres).
// WebXR's local-floor space is y up, -z forward. The view follows the vehicle: the world
// is turned so the operator's calibrated forward (heading0) points along -z and shifted so
// the vehicle floats in front of the operator at ANCHOR.

export const ANCHOR = [0.0, 1.1, -1.0];

// ---- 4x4 matrices, column-major like WebGL ------------------------------------------
export function mul(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      o[c * 4 + r] = s;
    }
  }
  return o;
}

function fromRows(m) { // 3x3 rows + translation t -> column-major 4x4
  return (t = [0, 0, 0]) => new Float32Array([
    m[0][0], m[1][0], m[2][0], 0,
    m[0][1], m[1][1], m[2][1], 0,
    m[0][2], m[1][2], m[2][2], 0,
    t[0], t[1], t[2], 1,
  ]);
}

export function translation(t) { return fromRows([[1, 0, 0], [0, 1, 0], [0, 0, 1]])(t); }

export function scaling(s) {
  return new Float32Array([s[0], 0, 0, 0, 0, s[1], 0, 0, 0, 0, s[2], 0, 0, 0, 0, 1]);
}

export function quatMatrix(q) { // q = [w, x, y, z]
  const [w, x, y, z] = q;
  return fromRows([
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ])();
}

export function yawMatrix(a) {
  const c = Math.cos(a), s = Math.sin(a);
  return fromRows([[c, -s, 0], [s, c, 0], [0, 0, 1]])();
}

// workbench (x fwd, y left, z up) -> WebXR (x right, y up, -z fwd)
export const WORKBENCH_TO_XR = fromRows([[0, -1, 0], [0, 0, 1], [-1, 0, 0]])();

export function perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1,
    0, 0, 2 * far * near * nf, 0]);
}

export function lookAt(eye, target, up) {
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const norm = (v) => { const n = Math.hypot(...v); return v.map((x) => x / n); };
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
    a[0] * b[1] - a[1] * b[0]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const z = norm(sub(eye, target)), x = norm(cross(up, z)), y = cross(z, x);
  return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
    -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
}

// the 12 edges of the cube [-1, 1]^3
const CUBE = (() => {
  const v = [];
  for (let a = 0; a < 3; a++) {
    const b = (a + 1) % 3, c = (a + 2) % 3;
    for (const sb of [-1, 1]) {
      for (const sc of [-1, 1]) {
        const p = [0, 0, 0], q = [0, 0, 0];
        p[a] = -1; q[a] = 1; p[b] = q[b] = sb; p[c] = q[c] = sc;
        v.push(...p, ...q);
      }
    }
  }
  return new Float32Array(v);
})();

const LINE_VS = `attribute vec3 p; uniform mat4 mvp; void main() { gl_Position = mvp * vec4(p, 1.0); }`;
const LINE_FS = `precision mediump float; uniform vec4 color; void main() { gl_FragColor = color; }`;
// vmax: the part of the texture, from its top, that the quad shows (the panel's used rows)
const TEX_VS = `attribute vec3 p; varying vec2 uv; uniform mat4 mvp; uniform float vmax;
  void main() { uv = vec2(p.x * 0.5 + 0.5, (0.5 - p.y * 0.5) * vmax);
    gl_Position = mvp * vec4(p, 1.0); }`;
const TEX_FS = `precision mediump float; varying vec2 uv; uniform sampler2D tex;
  void main() { gl_FragColor = texture2D(tex, uv); }`;

function program(gl, vs, fs) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(prog, s);
  }
  gl.bindAttribLocation(prog, 0, 'p');
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  return prog;
}

// the panel's texture [px] and its rows: room for the prompt, why the calibration
// restarted and the live numbers in VR, the hardware driver above them; 0.96 m wide in
// the scene, so a row (58 px) is 5.4 cm
const PANEL_W = 1024, PANEL_H = 384, PANEL_ROWS = 6, ROW = 58, PANEL_M_PER_PX = 0.96 / PANEL_W;

// one line of text as rows no wider than `width` pixels, broken at spaces (a single word
// wider than that stays one row, squeezed by fillText's maxWidth)
function wrap(c, text, width) {
  const rows = [];
  let row = '';
  for (const word of String(text).split(' ')) {
    const next = row ? `${row} ${word}` : word;
    if (row && c.measureText(next).width > width) {
      rows.push(row);
      row = word;
    } else {
      row = next;
    }
  }
  if (row) rows.push(row);
  return rows;
}

// Where the quad [-1, 1]^2 (z = 0) drawn with `mvp` lands in normalised device
// coordinates: {x0, x1, y0, y1} around its corners, or null when a corner is behind the eye.
function screenBox(mvp) {
  const xs = [], ys = [];
  for (const [x, y] of [[-1, -1], [1, -1], [-1, 1], [1, 1]]) {
    const w = mvp[3] * x + mvp[7] * y + mvp[15];
    if (w <= 0) return null;
    xs.push((mvp[0] * x + mvp[4] * y + mvp[12]) / w);
    ys.push((mvp[1] * x + mvp[5] * y + mvp[13]) / w);
  }
  return { x0: Math.min(...xs), x1: Math.max(...xs), y0: Math.min(...ys), y1: Math.max(...ys) };
}

// the scene's module (name, lo, hi: a box in the workbench's world frame) holding the
// point p, or null
export function moduleHolding(scene, p) {
  return ((scene && scene.modules) || []).find(
    (m) => m.lo.every((lo, i) => lo <= p[i] && p[i] <= m.hi[i])) || null;
}

export class Renderer {
  constructor(gl) {
    this.gl = gl;
    this.line = program(gl, LINE_VS, LINE_FS);
    this.tex = program(gl, TEX_VS, TEX_FS);
    this.cube = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.cube);
    gl.bufferData(gl.ARRAY_BUFFER, CUBE, gl.STATIC_DRAW);
    this.quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 0, 1, -1, 0, -1, 1, 0, 1, 1, 0]),
      gl.STATIC_DRAW);
    this.dyn = gl.createBuffer();
    this.panelCanvas = document.createElement('canvas');
    this.panelCanvas.width = PANEL_W;
    this.panelCanvas.height = PANEL_H;
    this.panelTex = gl.createTexture();
    this.panelText = null;
    this.panelRows = 0;
    this.panelBox = null;  // where the last draw put the panel (normalised device coords)
    this.scene = null;
    this.state = null;
  }

  // The panel's text: each line wrapped at spaces to the panel's width, at most
  // PANEL_ROWS rows (the first lines kept); the panel is as tall as its rows, and not drawn
  // without any.
  setPanel(lines, color = '#7fd') {
    const key = lines.join('\n') + color;
    if (key === this.panelText) return;
    this.panelText = key;
    const c = this.panelCanvas.getContext('2d');
    c.font = '44px sans-serif';
    const rows = lines.flatMap((l) => wrap(c, l, PANEL_W - 48)).slice(0, PANEL_ROWS);
    this.panelRows = rows.length;
    c.clearRect(0, 0, PANEL_W, PANEL_H); // the last text gone, not showing through the new
    c.fillStyle = 'rgba(10, 16, 24, 0.85)';
    c.fillRect(0, 0, PANEL_W, PANEL_H);
    c.fillStyle = color;
    rows.forEach((l, i) => c.fillText(l, 24, 62 + i * ROW, PANEL_W - 48));
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, this.panelTex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, this.panelCanvas);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  // workbench world -> XR local-floor
  worldMatrix() {
    const st = this.state;
    const pos = st && st.vehicle ? st.vehicle.pos : [0, 0, 0];
    const heading = st && typeof st.heading0 === 'number' ? st.heading0 : 0;
    return mul(translation(ANCHOR), mul(WORKBENCH_TO_XR,
      mul(yawMatrix(-heading), translation(pos.map((x) => -x)))));
  }

  box(vp, centre, quat, size, color, label) {
    const gl = this.gl;
    const m = mul(vp, mul(translation(centre), mul(quatMatrix(quat), scaling(size.map((s) => s / 2)))));
    // the box's label at its centre, in normalised device coordinates (drawn by the page)
    if (label && m[15] > 0) this.labels.push({ text: label, x: m[12] / m[15], y: m[13] / m[15] });
    gl.uniformMatrix4fv(gl.getUniformLocation(this.line, 'mvp'), false, m);
    gl.uniform4fv(gl.getUniformLocation(this.line, 'color'), color);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.cube);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    gl.drawArrays(gl.LINES, 0, 24);
  }

  segments(vp, points, color) {
    const gl = this.gl;
    gl.uniformMatrix4fv(gl.getUniformLocation(this.line, 'mvp'), false, vp);
    gl.uniform4fv(gl.getUniformLocation(this.line, 'color'), color);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.dyn);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(points.flat()), gl.DYNAMIC_DRAW);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    gl.drawArrays(gl.LINES, 0, points.length);
  }

  // draw one view: projection and view matrices from the XR view (or the desktop camera)
  draw(projection, view) {
    const gl = this.gl;
    gl.enable(gl.DEPTH_TEST);
    const vpXr = mul(projection, view);
    const vp = mul(vpXr, this.worldMatrix());
    this.labels = [];
    gl.useProgram(this.line);
    gl.enableVertexAttribArray(0);
    const id = [1, 0, 0, 0];
    const st = this.state;
    // the module the vehicle is in is all around the view, its centre near the vehicle's:
    // the live numbers name it instead of a label on the vehicle
    const here = st && st.vehicle ? moduleHolding(this.scene, st.vehicle.pos) : null;
    for (const m of (this.scene && this.scene.modules) || []) {
      const c = m.lo.map((lo, i) => (lo + m.hi[i]) / 2), s = m.lo.map((lo, i) => m.hi[i] - lo);
      this.box(vp, c, id, s, [0.45, 0.55, 0.7, 1], m === here ? null : m.name);
    }
    if (st && st.vehicle) {
      // the design's body box (an older server sends only a cube's edge; a scene with
      // neither draws no box rather than one of no size)
      const sc = this.scene || {};
      const vs = sc.vehicle_body_size || (sc.vehicle_size ? Array(3).fill(sc.vehicle_size) : null);
      if (vs) {
        this.box(vp, st.vehicle.pos, st.vehicle.quat, vs, [0.95, 0.8, 0.2, 1],
          'Astrobee + payload');
      }
      if (st.ctb && st.ctb.pos && this.scene && this.scene.ctb_size) {
        this.box(vp, st.ctb.pos, st.ctb.quat, this.scene.ctb_size,
          st.contact ? [0.3, 1, 0.4, 1] : [0.9, 0.9, 0.9, 1], st.contact ? 'CTB (held)' : 'CTB');
      }
      // a line from the body's underside (its centre less half its height) to each tip
      const tips = Object.values(st.fingers || {});
      const below = vs ? vs[2] / 2 : 0;
      const base = [st.vehicle.pos[0], st.vehicle.pos[1], st.vehicle.pos[2] - below];
      this.fingerLines = tips.map((p) => [base, p]);  // what was drawn (the page's debug)
      this.segments(vp, this.fingerLines.flat(), [1, 0.5, 0.3, 1]);
      for (const p of tips) this.box(vp, p, id, [0.02, 0.02, 0.02], [1, 0.4, 0.2, 1]);
    }
    // the text panel floats above the vehicle, facing the operator: its top edge fixed, as
    // tall as its rows (the texture's top part)
    this.panelBox = null;
    if (!this.panelRows) return;
    gl.useProgram(this.tex);
    const used = Math.min(PANEL_H, 24 + this.panelRows * ROW);  // [px]
    const half = (used * PANEL_M_PER_PX) / 2;  // half the panel's height [m]
    const top = ANCHOR[1] + 0.5 + 0.12;
    const panel = mul(vpXr, mul(translation([0, top - half, ANCHOR[2] + 0.1]),
      scaling([(PANEL_W * PANEL_M_PER_PX) / 2, half, 1])));
    this.panelBox = screenBox(panel);
    gl.uniformMatrix4fv(gl.getUniformLocation(this.tex, 'mvp'), false, panel);
    gl.uniform1f(gl.getUniformLocation(this.tex, 'vmax'), used / PANEL_H);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.panelTex);
    gl.uniform1i(gl.getUniformLocation(this.tex, 'tex'), 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.quad);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  }
}
